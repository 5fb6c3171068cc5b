"""Calibration wizard: PSF capture and shutter function, step by step, with progress and save.

The wizard runs the workflows of :mod:`calibration` (generators of
:class:`~calibration.workflow.Progress` events) on the camera's worker thread through
:meth:`MainWindow.run_camera_workflow`, which pauses the live view for the duration. Each event
updates a progress bar, a stage line and the latest frame; Cancel takes effect at the next
event (the workflow switches the source off and saves nothing). When a capture ends the
quality report (formatted lines) and the PSF (auto-levelled: the darks shown during the
capture set no levels) are shown, and Save writes the calibration file (atomically, through
:mod:`recon.calibfile`). On Finish the new PSF can become the live preview's PSF.

With the simulated bench the scene is hidden while the wizard captures (a PSF is taken with
the point source alone, as at the bench with the object removed) and restored afterwards.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import QRectF, Qt
from PySide6.QtGui import QFontDatabase
from PySide6.QtWidgets import (
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

__all__ = ["CalibrationWizard"]


def _stamp() -> str:
    return time.strftime("%Y%m%d-%H%M%S")

def _save_result(page: Any, prefix: str, suffix: str) -> Path | None:
    """Save ``page.result`` as ``<out>/<prefix>-<time><suffix>``; show the outcome on the page."""
    if page.result is None:
        return None
    path = page.setup.out_path() / f"{prefix}-{_stamp()}{suffix}"
    try:
        page.saved_path = page.result.save(path)
    except Exception as exc:  # shown in the wizard (disk full, permissions...), never a crash
        page.box.saved.setText(f"not saved: {exc}")
        return None
    page.box.saved.setText(f"saved {page.saved_path}")
    page.box.save.setEnabled(False)
    return Path(page.saved_path)



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
        self.intensity.setRange(0.0, 1.0)
        self.intensity.setSingleStep(0.1)
        self.intensity.setValue(1.0)
        self.hide_scene = QCheckBox("simulated bench: hide the scene while calibrating")
        self.hide_scene.setChecked(True)
        form = QFormLayout(self)
        form.addRow(self.devices)
        row = QHBoxLayout()
        row.addWidget(self.out_dir, 1)
        row.addWidget(browse)
        form.addRow("Output folder", row)
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
                and w.light_state is LightState.CONNECTED)

    def out_path(self) -> Path:
        """The chosen output folder."""
        return Path(self.out_dir.text()).expanduser()


class PsfPage(QWizardPage):
    """Capture the PSF, show the quality report and the PSF, save it."""

    def __init__(self, window: MainWindow, setup: SetupPage) -> None:
        super().__init__()
        self.window_ = window
        self.setup = setup
        self.setTitle("PSF capture")
        self.setSubTitle("Darks with the source off, auto-exposure with it on, averaged PSF "
                         "frames, dark subtraction and hot-pixel repair, quality checks.")
        self.box = _RunBox("PSF capture")
        QVBoxLayout(self).addWidget(self.box)
        self.box.start.clicked.connect(self.start)
        self.box.cancel.clicked.connect(self.cancel)
        self.box.save.clicked.connect(self.save)
        self.result: Any = None
        self.saved_path: Path | None = None
        self.error = ""
        self._handle: Any = None

    def start(self) -> None:
        """Run :func:`calibration.capture_psf` on the camera's worker."""
        from calibration import PsfSettings, capture_psf

        s = PsfSettings(n_frames=self.setup.n_frames.value(),
                        n_darks=self.setup.n_darks.value(),
                        auto_exposure=self.setup.auto_exposure.isChecked(),
                        intensity=float(self.setup.intensity.value()))
        self.result = None
        self.saved_path = None
        self.error = ""
        self.box.running(True)
        self.box.report.setPlainText("")
        self.completeChanged.emit()
        self._handle = self.window_.run_camera_workflow(
            lambda cam, light: capture_psf(cam, light, s),
            name="PSF capture",
            hide_scene=self.setup.hide_scene.isChecked(),
            on_progress=self.box.show_progress,
            on_done=self._done,
            on_error=self._failed,
        )

    def cancel(self) -> None:
        """Cancel at the next progress point."""
        if self._handle is not None:
            self._handle.cancel()

    def _done(self, result: Any) -> None:
        self.result = result
        self.box.running(False)
        self.box.save.setEnabled(True)
        self.box.report.setPlainText(psf_report(result))
        self.box.show_result_image(result.psf)
        self.box.stage.setText("done: review the PSF and the report, then Save")
        self.completeChanged.emit()

    def _failed(self, exc: BaseException) -> None:
        self.box.running(False)
        self.error = str(exc)
        from calibration import CalibrationCancelled

        kind = "cancelled" if isinstance(exc, CalibrationCancelled) else "refused / failed"
        self.box.stage.setText(f"{kind}: {exc}")
        self.box.report.setPlainText(str(exc))
        self.completeChanged.emit()

    def save(self) -> Path | None:
        """Save the captured PSF into the output folder."""
        if _save_result(self, "psf", ".tif") is None:
            return None
        self.window_.settings.calibration_dir = str(self.setup.out_path())
        self.completeChanged.emit()
        return self.saved_path

    def isComplete(self) -> bool:
        return self.saved_path is not None


class ShutterPage(QWizardPage):
    """Shutter function from the timing model, or measured by a strobe scan; save."""

    def __init__(self, window: MainWindow, setup: SetupPage) -> None:
        super().__init__()
        self.window_ = window
        self.setup = setup
        self.setTitle("Shutter function")
        self.setSubTitle("From the camera's timing model (instant), or measured by strobing "
                         "the point source at increasing delays. Optional: Next skips it.")
        self.method = ComboBox()
        self.method.addItem("from the timing model", "timing")
        self.method.addItem("measured (strobe scan)", "measured")
        self.bin_lines = SpinBox()
        self.bin_lines.setRange(1, 100_000)
        self.bin_lines.setValue(100)
        self.bin_lines.setToolTip("Width of one time bin in line times")
        self.pulse = DoubleSpinBox()
        self.pulse.setRange(0.0, 1e6)
        self.pulse.setSpecialValueText("auto")
        self.pulse.setSuffix(" µs")
        self.step = DoubleSpinBox()
        self.step.setRange(0.0, 1e6)
        self.step.setSpecialValueText("auto")
        self.step.setSuffix(" µs")
        form = QFormLayout()
        form.addRow("Method", self.method)
        form.addRow("Time bin", self.bin_lines)
        form.addRow("Strobe pulse", self.pulse)
        form.addRow("Delay step", self.step)
        self.box = _RunBox("shutter")
        lay = QVBoxLayout(self)
        lay.addLayout(form)
        lay.addWidget(self.box, 1)
        self.box.start.clicked.connect(self.start)
        self.box.cancel.clicked.connect(self.cancel)
        self.box.save.clicked.connect(self.save)
        self.result: Any = None
        self.saved_path: Path | None = None
        self._handle: Any = None

    def start(self) -> None:
        """Compute or measure the shutter function on the camera's worker."""
        from calibration import ShutterSettings, measure_shutter, shutter_from_timing
        from calibration.workflow import Progress

        bin_lines = int(self.bin_lines.value())
        self.result = None
        self.saved_path = None
        self.box.running(True)
        if self.method.currentData() == "timing":
            def steps(cam: Any, light: Any) -> Any:
                yield Progress("timing", "reading the camera's timing model", 0.5)
                timing = cam.timing
                if timing is None:
                    from calibration import CalibrationError

                    raise CalibrationError("the camera has no timing model",
                                           "Measure the shutter with the strobe scan")
                roi = cam.roi
                sf = shutter_from_timing(timing, bin_lines=bin_lines,
                                         roi_rows=(roi.y, roi.height), binning=cam.binning)
                yield Progress("done", f"{sf.shutter.shape[0]} time bins", 1.0)
                return sf

            hide = False
        else:
            ss = ShutterSettings(pulse_us=self.pulse.value() or None,
                                 step_us=self.step.value() or None,
                                 intensity=float(self.setup.intensity.value()))

            def steps(cam: Any, light: Any) -> Any:
                return measure_shutter(cam, light, ss, bin_lines=bin_lines)

            hide = self.setup.hide_scene.isChecked()
        self._handle = self.window_.run_camera_workflow(
            steps, name="shutter", hide_scene=hide, on_progress=self.box.show_progress,
            on_done=self._done, on_error=self._failed)

    def cancel(self) -> None:
        """Cancel at the next progress point."""
        if self._handle is not None:
            self._handle.cancel()

    def _done(self, sf: Any) -> None:
        self.result = sf
        self.box.running(False)
        self.box.save.setEnabled(True)
        m = np.asarray(sf.shutter, dtype=np.float32)
        k, rows = m.shape
        self.box.show_axes_image(m.T.copy(), x=(0.0, k * float(sf.bin_us)), y=(0.0, float(rows)),
                                 x_label="time after the trigger (µs)", y_label="sensor row")
        self.box.report.setPlainText(shutter_report(sf))
        self.box.stage.setText("done: review, then Save (rows down, time across)")

    def _failed(self, exc: BaseException) -> None:
        self.box.running(False)
        self.box.stage.setText(f"failed: {exc}")
        self.box.report.setPlainText(str(exc))

    def save(self) -> Path | None:
        """Save the shutter function into the output folder."""
        return _save_result(self, "shutter", ".npz")


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
            lines.append(f"  {self.psf_page.result.quality.summary()}")
        if self.shutter_page.saved_path is not None:
            lines.append(f"Shutter function: {self.shutter_page.saved_path}")
        self.summary.setText("\n".join(lines) or "nothing saved")


class CalibrationWizard(QWizard):
    """The calibration wizard of a :class:`MainWindow` (non-modal)."""

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
        self.accepted.connect(self._finish)
        self.rejected.connect(self._cancel_running)

    def _cancel_running(self) -> None:
        self.psf_page.cancel()
        self.shutter_page.cancel()

    def _finish(self) -> None:
        page = self.psf_page
        if self.finish_page.use_psf.isChecked() and page.result is not None:
            name = page.saved_path.name if page.saved_path else "captured"
            self.window_.use_psf(page.result.normalised(), f"calibration {name}",
                                 str(page.saved_path or ""))


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
