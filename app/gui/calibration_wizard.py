"""Calibration wizard: PSF capture and shutter function, step by step, with progress and save.

The wizard runs the workflows of :mod:`calibration` (generators of
:class:`~calibration.workflow.Progress` events) on the camera's worker thread through
:meth:`MainWindow.run_camera_workflow`, which pauses the live view for the duration. Each event
updates a progress bar, a stage line and the latest frame; Cancel takes effect at the next
event (the workflow switches the source off and saves nothing). When a capture ends the
quality report (formatted lines) and the PSF (auto-levelled: the darks shown during the
capture set no levels) are shown, and Save writes the calibration file (atomically, through
:mod:`recon.calibfile`) under a name no file has (:func:`recon.atomic.write_new`: nothing is ever
replaced). On Finish the saved PSF can become the live preview's PSF.

The shutter function takes the CLI's path (:func:`calibration.calibrate_shutter`): the same
default bins (the finest the rows resolve), checks, metadata and strobe-time rule.

While a capture runs its page is incomplete and Back is disabled; closing the wizard (or
Finish) cancels it. The main window keeps one wizard: reopened, it shows the run still
winding down, or its first page with what was typed.

With the simulated bench the scene is hidden while the wizard captures (a PSF is taken with
the point source alone, as at the bench with the object removed) and restored afterwards.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import QRectF, Qt
from PySide6.QtGui import QFontDatabase
from PySide6.QtWidgets import (
    QAbstractSpinBox,
    QCheckBox,
    QFileDialog,
    QFormLayout,
    QHBoxLayout,
    QLabel,
    QLineEdit,
    QPlainTextEdit,
    QProgressBar,
    QPushButton,
    QVBoxLayout,
    QWidget,
    QWizard,
    QWizardPage,
)

from app.devices_state import LightState
from app.gui.image_view import ImagePanel
from app.gui.widgets import ComboBox, DoubleSpinBox, SpinBox

if TYPE_CHECKING:
    from app.gui.main_window import MainWindow

__all__ = ["CalibrationWizard", "output_folder_problem"]

#: the smallest source intensity the wizard captures with (at 0 a PSF capture can only fail)
MIN_INTENSITY = 0.01


def _stamp() -> str:
    return time.strftime("%Y%m%d-%H%M%S")


def _one_line(exc: BaseException) -> str:
    """An error as one line for people (an OSError as "file: reason", not "[Errno 13] ...")."""
    if isinstance(exc, OSError) and exc.strerror:
        where = exc.filename if exc.filename is not None else ""
        return f"{where}: {exc.strerror}" if where else str(exc.strerror)
    return " ".join(str(exc).split()) or type(exc).__name__


def output_folder_problem(text: str, *, probe: bool = False) -> str | None:
    """What is wrong with ``text`` as the output folder (one line), or None.

    Empty, a file (or a file where a parent folder should be), or not writable (the nearest
    folder that exists: the folder is made on the first save). ``probe``: also create and
    remove a file there, which finds what permissions do not say (a read-only file system).
    """
    if not text.strip():
        return "name an output folder"
    folder = Path(text.strip()).expanduser().absolute()
    for place in (folder, *folder.parents):
        if not place.exists():
            continue
        if not place.is_dir():
            if place == folder:
                return f"output folder {folder} is a file, not a folder"
            return f"output folder {folder}: {place} is a file, not a folder"
        if not os.access(place, os.W_OK | os.X_OK):
            return f"output folder {folder} is not writable ({place})"
        if probe:
            try:
                with tempfile.TemporaryFile(dir=place):
                    pass
            except OSError as exc:
                reason = exc.strerror or str(exc)
                return f"output folder {folder} is not writable ({place}: {reason})"
        return None
    return f"output folder {folder}: no part of it exists"


def _is_cancel(exc: BaseException) -> bool:
    """Whether a run ended by a cancel (the workflow's, or the worker's at shutdown)."""
    from app.gui.workers import Cancelled
    from calibration import CalibrationCancelled

    return isinstance(exc, CalibrationCancelled | Cancelled)


class _RunBox(QWidget):
    """Start / Cancel, a progress bar, the stage line, the latest image, a report."""

    def __init__(self, title: str) -> None:
        super().__init__()
        self.start = QPushButton(f"Start {title}")
        self.cancel = QPushButton("Cancel")
        self.cancel.setEnabled(False)
        self.save = QPushButton("Save")
        self.save.setEnabled(False)
        self.progress = QProgressBar()
        self.progress.setRange(0, 1000)
        self.stage = QLabel("not started")
        self.stage.setWordWrap(True)
        self.image = ImagePanel(title)
        self.image.setMinimumHeight(200)
        # a result with physical axes (the shutter function: time across, rows down)
        self.plot = pg.PlotWidget()
        self.plot.setMinimumHeight(200)
        self.plot.getViewBox().invertY(True)
        self.plot_image = pg.ImageItem()
        self.plot.addItem(self.plot_image)
        self.plot_bar = pg.ColorBarItem(values=(0.0, 1.0), colorMap=pg.colormap.get("viridis"),
                                        label="exposed fraction")
        self.plot_bar.setImageItem(self.plot_image, insert_in=self.plot.getPlotItem())
        self.plot.setVisible(False)
        self.report = QPlainTextEdit()
        self.report.setReadOnly(True)
        self.report.setMaximumHeight(150)
        self.report.setFont(QFontDatabase.systemFont(QFontDatabase.SystemFont.FixedFont))
        self.saved = QLabel("")
        self.saved.setWordWrap(True)
        row = QHBoxLayout()
        row.addWidget(self.start)
        row.addWidget(self.cancel)
        row.addWidget(self.save)
        lay = QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.addLayout(row)
        lay.addWidget(self.progress)
        lay.addWidget(self.stage)
        lay.addWidget(self.image, 1)
        lay.addWidget(self.plot, 1)
        lay.addWidget(self.report)
        lay.addWidget(self.saved)

    def running(self, on: bool) -> None:
        self.start.setEnabled(not on)
        self.cancel.setEnabled(on)
        if on:
            self.save.setEnabled(False)
            self.saved.setText("")
            self.image.setVisible(True)
            self.plot.setVisible(False)

    def show_result_image(self, image: np.ndarray) -> None:
        """Show a result image with levels from its own values (min to max)."""
        self.image.setVisible(True)
        self.plot.setVisible(False)
        self.image.set_image(np.asarray(image, dtype=np.float32))
        self.image.autoscale()

    def show_axes_image(self, image: np.ndarray, *, x: tuple[float, float],
                        y: tuple[float, float], x_label: str, y_label: str) -> None:
        """Show ``image`` (rows, cols) on axes: columns span ``x``, rows span ``y``."""
        img = np.asarray(image, dtype=np.float32)
        self.plot_image.setImage(img, autoLevels=False)
        hi = float(img.max()) if img.size else 1.0
        self.plot_bar.setLevels((0.0, hi if hi > 0 else 1.0))
        self.plot_image.setRect(QRectF(x[0], y[0], x[1] - x[0], y[1] - y[0]))
        self.plot.setLabel("bottom", x_label)
        self.plot.setLabel("left", y_label)
        self.plot.autoRange(padding=0.0)
        self.image.setVisible(False)
        self.plot.setVisible(True)

    def show_progress(self, p: Any) -> None:
        self.progress.setValue(int(1000 * min(max(p.fraction, 0.0), 1.0)))
        self.stage.setText(f"{p.stage}: {p.message}")
        if p.frame is not None:
            self.image.set_image(np.asarray(p.frame, dtype=np.float32))


class SetupPage(QWizardPage):
    """Devices, output folder, capture settings."""

    def __init__(self, window: MainWindow) -> None:
        super().__init__()
        self.window_ = window
        self.setTitle("Set up")
        self.setSubTitle("Connect the camera and the point source (Devices panel), place the "
                         "source on axis, choose where the calibration files go.")
        self.devices = QLabel("")
        self.devices.setWordWrap(True)
        s = window.settings
        default_out = s.calibration_dir or str(Path.home() / "lenslesscam-calibration")
        self.out_dir = QLineEdit(default_out)
        browse = QPushButton("Browse…")
        browse.clicked.connect(self._browse)
        self.n_frames = SpinBox()
        self.n_frames.setRange(1, 1000)
        self.n_frames.setValue(16)
        self.n_darks = SpinBox()
        self.n_darks.setRange(1, 1000)
        self.n_darks.setValue(16)
        self.auto_exposure = QCheckBox("auto-exposure (peak at 75% of full scale)")
        self.auto_exposure.setChecked(True)
        self.intensity = DoubleSpinBox()
        self.intensity.setRange(MIN_INTENSITY, 1.0)
        self.intensity.setSingleStep(0.1)
        self.intensity.setValue(1.0)
        # emptied or junk: the value before (the nearest bound is kept for a number out of range)
        self.intensity.setCorrectionMode(QAbstractSpinBox.CorrectionMode.CorrectToPreviousValue)
        self.hide_scene = QCheckBox("simulated bench: hide the scene while calibrating")
        self.hide_scene.setChecked(True)
        self.out_error = QLabel("")
        self.out_error.setWordWrap(True)
        self.out_error.setStyleSheet("color: #b00020")
        self.out_dir.textChanged.connect(self._out_changed)
        form = QFormLayout(self)
        form.addRow(self.devices)
        row = QHBoxLayout()
        row.addWidget(self.out_dir, 1)
        row.addWidget(browse)
        form.addRow("Output folder", row)
        form.addRow(self.out_error)
        form.addRow("PSF frames", self.n_frames)
        form.addRow("Dark frames", self.n_darks)
        form.addRow(self.auto_exposure)
        form.addRow("Source intensity", self.intensity)
        form.addRow(self.hide_scene)
        window.camera_state_changed.connect(lambda _s: self._refresh())
        window.light_state_changed.connect(lambda _s: self._refresh())

    def _browse(self) -> None:
        d = QFileDialog.getExistingDirectory(self, "Calibration folder", self.out_dir.text())
        if d:
            self.out_dir.setText(d)

    def initializePage(self) -> None:
        self._refresh()

    def _out_changed(self) -> None:
        self.out_error.setText(output_folder_problem(self.out_dir.text()) or "")
        self.completeChanged.emit()

    def _refresh(self) -> None:
        w = self.window_
        cam_ok = w.bench.camera is not None and w.camera_state.ready
        light_ok = w.light_state is LightState.CONNECTED
        self.hide_scene.setVisible(w.bench.is_simulated)
        lines = [
            f"Camera: {'ready' if cam_ok else 'not ready'} ({w.camera_state})",
            f"Point source: {'ready' if light_ok else 'not ready'} ({w.light_state})",
        ]
        if not (cam_ok and light_ok):
            lines.append("Connect both in the Devices panel to continue.")
        self.devices.setText("\n".join(lines))
        self.completeChanged.emit()

    def isComplete(self) -> bool:
        w = self.window_
        return (w.bench.camera is not None and w.camera_state.ready
                and w.light_state is LightState.CONNECTED
                and output_folder_problem(self.out_dir.text()) is None)

    def validatePage(self) -> bool:
        """Check the output folder before any capture (one line when it cannot be used)."""
        problem = output_folder_problem(self.out_dir.text(), probe=True)
        self.out_error.setText(problem or "")
        if problem is not None:
            return False
        self.out_dir.setText(str(self.out_path()))  # absolute: it outlives this folder
        self.window_.settings.calibration_dir = str(self.out_path())
        return True

    def out_path(self) -> Path:
        """The chosen output folder, absolute (a relative one is lost in the next session)."""
        return Path(self.out_dir.text().strip()).expanduser().absolute()


class _RunPage(QWizardPage):
    """A page that runs one workflow at a time, shows it in a :class:`_RunBox` and saves it.

    ``result`` is the newest result (saved or not); ``saved_result`` and ``saved_path`` the
    last one saved, kept until a newer one is saved (a cancelled or refused re-capture keeps
    it). While a run goes the page is incomplete and cannot be left (:meth:`validatePage`).
    """

    prefix = ""
    suffix = ""
    title = ""

    def __init__(self, window: MainWindow, setup: SetupPage) -> None:
        super().__init__()
        self.window_ = window
        self.setup = setup
        self.box = _RunBox(self.title)
        self.box.start.clicked.connect(self.start)
        self.box.cancel.clicked.connect(self.cancel)
        self.box.save.clicked.connect(self.save)
        self.result: Any = None
        self.saved_result: Any = None
        self.saved_path: Path | None = None
        self.error = ""
        self._handle: Any = None
        self._running = False

    @property
    def running(self) -> bool:
        """Whether a run of this page has not ended yet."""
        return self._running

    def start(self) -> None:  # pragma: no cover - each page has its own
        raise NotImplementedError

    def _run(self, make_steps: Any, *, name: str, hide_scene: bool) -> None:
        self.result = None  # the pending result only: the saved one stays until replaced
        self.error = ""
        self._running = True
        self.box.running(True)
        self.box.report.setPlainText("")
        self.completeChanged.emit()
        self._handle = self.window_.run_camera_workflow(
            make_steps, name=name, hide_scene=hide_scene, on_progress=self.box.show_progress,
            on_done=self._finished, on_error=self._failed)

    def cancel(self) -> None:
        """Cancel at the next progress point."""
        if self._handle is not None and self._running:
            self._handle.cancel()

    def _finished(self, result: Any) -> None:
        self._running = False
        self.result = result
        self.box.running(False)
        self.box.save.setEnabled(True)
        self._show(result)
        self._show_saved()
        self.completeChanged.emit()

    def _show(self, result: Any) -> None:  # pragma: no cover - each page has its own
        raise NotImplementedError

    def _failed(self, exc: BaseException) -> None:
        self._running = False
        self.box.running(False)
        self.error = _one_line(exc)
        kind = "cancelled" if _is_cancel(exc) else "refused / failed"
        self.box.stage.setText(f"{kind}: {self.error}")
        self.box.report.setPlainText(str(exc))
        self._show_saved()
        self.completeChanged.emit()

    def _show_saved(self) -> None:
        if self.saved_path is not None:
            self.box.saved.setText(f"saved before: {self.saved_path}")

    def save(self) -> Path | None:
        """Save the newest result into the output folder under a new name; None if not saved."""
        if self.result is None:
            return None
        problem = output_folder_problem(self.setup.out_dir.text())  # (typed since Next)
        folder = self.setup.out_path()
        try:
            if problem is not None:
                raise ValueError(problem)
            from recon.atomic import write_new

            path = write_new(self.result.save, folder, f"{self.prefix}-{_stamp()}", self.suffix)
        except Exception as exc:  # shown in the wizard (disk full, permissions...), never a crash
            self.box.saved.setText(f"not saved: {_one_line(exc)}")
            return None
        self.saved_path = path
        self.saved_result = self.result
        self.box.saved.setText(f"saved {path}")
        self.box.save.setEnabled(False)
        self.window_.settings.calibration_dir = str(folder)
        self.completeChanged.emit()
        return path

    def reset(self) -> None:
        """Forget the results (a new session of the wizard); the settings stay as typed."""
        self.result = self.saved_result = self.saved_path = None
        self.error = ""
        self._handle = None
        self.box.running(False)
        self.box.progress.setValue(0)
        self.box.stage.setText("not started")
        self.box.report.setPlainText("")
        self.box.saved.setText("")
        self.completeChanged.emit()

    def validatePage(self) -> bool:
        return not self._running


class PsfPage(_RunPage):
    """Capture the PSF, show the quality report and the PSF, save it."""

    prefix = "psf"
    suffix = ".tif"
    title = "PSF capture"

    def __init__(self, window: MainWindow, setup: SetupPage) -> None:
        super().__init__(window, setup)
        self.setTitle("PSF capture")
        self.setSubTitle("Darks with the source off, auto-exposure with it on, averaged PSF "
                         "frames, dark subtraction and hot-pixel repair, quality checks.")
        QVBoxLayout(self).addWidget(self.box)

    def start(self) -> None:
        """Run :func:`calibration.capture_psf` on the camera's worker."""
        from calibration import PsfSettings, capture_psf

        s = PsfSettings(n_frames=self.setup.n_frames.value(),
                        n_darks=self.setup.n_darks.value(),
                        auto_exposure=self.setup.auto_exposure.isChecked(),
                        intensity=float(self.setup.intensity.value()))
        self._run(lambda cam, light: capture_psf(cam, light, s), name="PSF capture",
                  hide_scene=self.setup.hide_scene.isChecked())

    def _show(self, result: Any) -> None:
        self.box.report.setPlainText(psf_report(result))
        self.box.show_result_image(result.psf)
        self.box.stage.setText("done: review the PSF and the report, then Save")

    def isComplete(self) -> bool:
        return not self.running and self.saved_path is not None


class ShutterPage(_RunPage):
    """Shutter function from the timing model, or measured by a strobe scan; save.

    The CLI's path and defaults (:func:`calibration.calibrate_shutter`): time bins "auto"
    (the finest the rows resolve), pulse and step "auto" or on the source's 0.1 µs grid.
    """

    prefix = "shutter"
    suffix = ".npz"
    title = "shutter"

    def __init__(self, window: MainWindow, setup: SetupPage) -> None:
        super().__init__(window, setup)
        from drivers.lightsource import TIME_RESOLUTION_US

        self.setTitle("Shutter function")
        self.setSubTitle("From the camera's timing model (instant), or measured by strobing "
                         "the point source at increasing delays. Optional: Next skips it.")
        self.method = ComboBox()
        self.method.addItem("from the timing model", "timing")
        self.method.addItem("measured (strobe scan)", "measured")
        self.bin_lines = SpinBox()
        self.bin_lines.setRange(0, 100_000)
        self.bin_lines.setSpecialValueText("auto")
        self.bin_lines.setValue(0)
        self.bin_lines.setToolTip("Width of one time bin in line times (auto: the finest the "
                                  "rows resolve; more bins than rows are refused)")
        self.pulse = self._strobe_box()
        self.step = self._strobe_box()
        self.pulse.setToolTip(f"auto: one line time; the source's step is "
                              f"{TIME_RESOLUTION_US:g} µs")
        self.step.setToolTip("auto: half the pulse")
        form = QFormLayout()
        form.addRow("Method", self.method)
        form.addRow("Time bin", self.bin_lines)
        form.addRow("Strobe pulse", self.pulse)
        form.addRow("Delay step", self.step)
        lay = QVBoxLayout(self)
        lay.addLayout(form)
        lay.addWidget(self.box, 1)

    @staticmethod
    def _strobe_box() -> DoubleSpinBox:
        """0 is "auto"; otherwise the source's time grid (0.1 µs), as the CLI takes it."""
        from drivers.lightsource import MAX_TIME_US, TIME_RESOLUTION_US

        box = DoubleSpinBox()
        box.setDecimals(1)
        box.setRange(0.0, MAX_TIME_US)
        box.setSingleStep(TIME_RESOLUTION_US)
        box.setSpecialValueText("auto")
        box.setSuffix(" µs")
        return box

    def shutter_settings(self) -> Any:
        """The strobe scan's settings (the CLI's defaults; strobe times by its rule)."""
        from calibration import ShutterSettings, strobe_time

        def strobe(box: DoubleSpinBox, what: str) -> float | None:
            value = float(box.value())
            return None if value <= 0 else strobe_time(value, f"{what} {value:g} us")[0]

        return ShutterSettings(pulse_us=strobe(self.pulse, "strobe pulse"),
                               step_us=strobe(self.step, "delay step"),
                               intensity=float(self.setup.intensity.value()))

    def start(self) -> None:
        """Compute or measure the shutter function on the camera's worker."""
        from calibration import calibrate_shutter

        bin_lines = int(self.bin_lines.value()) or None
        measured = self.method.currentData() == "measured"
        try:
            settings = self.shutter_settings()
        except ValueError as exc:
            self._failed(exc)
            return

        def steps(cam: Any, light: Any) -> Any:
            return calibrate_shutter(cam, light if measured else None, settings,
                                     bin_lines=bin_lines, timeout_s=settings.frame_timeout_s)

        self._run(steps, name="shutter",
                  hide_scene=measured and self.setup.hide_scene.isChecked())

    def _show(self, sf: Any) -> None:
        m = np.asarray(sf.shutter, dtype=np.float32)
        k, rows = m.shape
        self.box.show_axes_image(m.T.copy(), x=(0.0, k * float(sf.bin_us)), y=(0.0, float(rows)),
                                 x_label="time after the trigger (µs)", y_label="sensor row")
        self.box.report.setPlainText(shutter_report(sf))
        self.box.stage.setText("done: review, then Save (rows down, time across)")

    def isComplete(self) -> bool:
        return not self.running


class FinishPage(QWizardPage):
    """What was saved; use the PSF for the preview."""

    def __init__(self, psf_page: PsfPage, shutter_page: ShutterPage) -> None:
        super().__init__()
        self.psf_page = psf_page
        self.shutter_page = shutter_page
        self.setTitle("Done")
        self.summary = QLabel("")
        self.summary.setWordWrap(True)
        self.summary.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        self.use_psf = QCheckBox("use the new PSF for the live reconstruction preview")
        self.use_psf.setChecked(True)
        lay = QVBoxLayout(self)
        lay.addWidget(self.summary)
        lay.addWidget(self.use_psf)
        lay.addStretch(1)

    def initializePage(self) -> None:
        lines = []
        if self.psf_page.saved_path is not None:
            lines.append(f"PSF: {self.psf_page.saved_path}")
            lines.append(f"  {self.psf_page.saved_result.quality.summary()}")
        if self.shutter_page.saved_path is not None:
            lines.append(f"Shutter function: {self.shutter_page.saved_path}")
        self.summary.setText("\n".join(lines) or "nothing saved")


class CalibrationWizard(QWizard):
    """The calibration wizard of a :class:`MainWindow` (non-modal, one per window).

    Closing it (Cancel, the window's close button) or Finish cancels a run still going;
    :meth:`reopen` shows it again.
    """

    def __init__(self, window: MainWindow) -> None:
        super().__init__(window)
        self.window_ = window
        self.setWindowTitle("Calibration wizard")
        self.setWizardStyle(QWizard.WizardStyle.ClassicStyle)
        self.setModal(False)
        self.resize(720, 700)
        self.setup_page = SetupPage(window)
        self.psf_page = PsfPage(window, self.setup_page)
        self.shutter_page = ShutterPage(window, self.setup_page)
        self.finish_page = FinishPage(self.psf_page, self.shutter_page)
        for p in (self.setup_page, self.psf_page, self.shutter_page, self.finish_page):
            self.addPage(p)
        for p in (self.setup_page, self.psf_page, self.shutter_page, self.finish_page):
            # after QWizard's own update of every button (connected by addPage, on any page's
            # completeChanged): Back off while running
            p.completeChanged.connect(self._sync_back)
        self.currentIdChanged.connect(lambda _id: self._sync_back())
        self.accepted.connect(self._finish)

    def run_pages(self) -> tuple[_RunPage, ...]:
        """The pages that run workflows."""
        return (self.psf_page, self.shutter_page)

    @property
    def running(self) -> bool:
        """Whether a capture of this wizard has not ended yet."""
        return any(p.running for p in self.run_pages())

    def _sync_back(self) -> None:
        if self.running:
            self.button(QWizard.WizardButton.BackButton).setEnabled(False)

    def back(self) -> None:
        """The previous page, except while a capture runs (its page is where to cancel it)."""
        if not self.running:
            super().back()

    def done(self, result: int) -> None:
        """Close (Finish, Cancel): a capture still running is cancelled, never left orphaned."""
        self._cancel_running()
        super().done(result)

    def reopen(self) -> None:
        """Shown again: a run still ending as it is, else page one with what was typed."""
        if self.running:
            return
        for p in self.run_pages():
            p.reset()
        self.restart()

    def _cancel_running(self) -> None:
        for p in self.run_pages():
            p.cancel()

    def _finish(self) -> None:
        page = self.psf_page
        if self.finish_page.use_psf.isChecked() and page.saved_result is not None:
            assert page.saved_path is not None
            self.window_.use_psf(page.saved_result.normalised(),
                                 f"calibration {page.saved_path.name}", str(page.saved_path))


def psf_report(result: Any) -> str:
    """The PSF capture's quality report as lines for people."""
    q = result.quality
    md = result.metadata
    gain = "–" if result.gain is None else f"{result.gain:g}"
    return "\n".join([
        f"peak            {q.peak_adu:.4g} ADU ({100 * q.peak_fraction:.0f} % of full scale)",
        f"saturated       {q.saturated_pixels} px",
        f"noise / SNR     {q.noise_adu:.3g} ADU / {q.snr:.3g}",
        f"support         {q.support_pixels} px ({100 * q.support_fraction:.1f} % of the "
        "sensor)",
        f"resolution      {q.resolution_px:.2f} px (autocorrelation FWHM "
        f"{q.autocorr_fwhm_px[0]:.2f} x {q.autocorr_fwhm_px[1]:.2f} px)",
        f"centroid offset ({q.offset_px[0]:+.1f}, {q.offset_px[1]:+.1f}) px from the centre",
        f"exposure, gain  {result.exposure_us / 1000:.3f} ms, {gain}",
        f"frames          {md.get('frames_averaged')} PSF, {md.get('darks_averaged')} dark "
        "(averaged)",
        # saved, but worth a look (a crop that cut off part of the PSF's light)
        *(f"warning         {w}" for w in getattr(result, "warnings", ())),
    ])


def shutter_report(sf: Any) -> str:
    """The shutter function's description as lines for people."""
    k, rows = np.asarray(sf.shutter).shape
    t = sf.timing
    lines = [
        f"time bins       {k} of {sf.bin_lines} lines ({sf.bin_us:.1f} µs each)",
        f"rows            {rows}",
        f"method          {sf.method}",
    ]
    if t is not None:
        pattern = getattr(t.pattern, "value", t.pattern)
        lines += [
            f"line time       {t.line_time_us:.4g} µs",
            f"exposure        {t.exposure_lines} lines ({t.exposure_lines * t.line_time_us:.4g} "
            "µs)",
            f"readout         {pattern}, trigger delay {t.trigger_delay_us:.4g} µs",
            f"frame time      {t.frame_time_us / 1000:.3f} ms",
        ]
    if sf.measurement is not None:
        lines.append(f"measured        {sf.measurement.summary()}")
    return "\n".join(lines)
