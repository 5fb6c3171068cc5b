"""The speed/accuracy trade in the app: the same plot as ``lenslesscam trade``, and a suggestion.

The panel either loads a ``trade.csv`` written by the CLI, or measures a quick trade on the
current raw frame with the preview's PSF, box-downsampled by the panel's factor (FISTA-TV and
ADMM-TV over tau and iterations, the held-out proxy as quality: there is no ground truth at the
bench) in a worker thread. The frame is read as the preview and the jobs read it: the preview's
dark level and saturation verdict (``preview_engine.frame_dark_level``,
``saturation_verdict``): a frame the preview refuses as saturated is not measured. A
measurement shows its progress (``N of M settings``) and can be cancelled (the settings
measured so far stay); *Save trade…* writes it as the CLI does (``trade.csv`` and
``trade.md``), so that ``plan --trade`` reads it. Rows of one source only are shown: a file, or
the measurement (*Load* waits for a measurement to end). A file of several cases (``trade
--protocol``) shows one case at a time, chosen in the case box. For a time budget the panel
suggests the best setting found, and *Apply to preview* hands its tau to the preview (not when
the camera or frame size changed since the trade was measured).

Collaborators come in the constructor: ``current()`` gives the measurement (newest frame and
the preview's PSF), ``apply_tau(tau)`` sets the preview's tau.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import QObject, QThread, Signal
from PySide6.QtWidgets import (
    QFileDialog,
    QHBoxLayout,
    QLabel,
    QPushButton,
    QVBoxLayout,
    QWidget,
)

from app.gui.jobs_panel import Measurement
from app.gui.widgets import ComboBox, DoubleSpinBox, SpinBox
from recon.trade import TradeRow, best_for_budgets, pareto_front, read_trade_csv

COLOURS = {"fista": (31, 119, 180), "admm": (255, 127, 14), "udn": (44, 160, 44)}
#: the Pareto front's line: light grey on pyqtgraph's black background (it was black on black)
FRONT_PEN = {"color": (220, 220, 220), "width": 2}
#: the name of the case a measurement on the current frame makes
CURRENT_CASE = "current frame"


class _TradeWorker(QObject):
    # every signal carries the worker's run id: a stopped worker's late rows are dropped
    row = Signal(int, object)
    progress = Signal(int, int, int)  # run id, settings measured, settings in the grid
    finished = Signal(int)
    failed = Signal(int, str)

    def __init__(self, case: Any, grid: list[Any], run_id: int) -> None:
        super().__init__()
        self.case = case
        self.grid = grid
        self.run_id = run_id
        self._stop = threading.Event()

    def run(self) -> None:
        from recon.trade import run_trade

        done = 0

        def finished(label: str) -> None:
            nonlocal done
            done += 1
            self.progress.emit(self.run_id, done, len(self.grid))

        try:
            for r in run_trade(self.case, self.grid, cancel=self._stop.is_set,
                               finished=finished):
                self.row.emit(self.run_id, r)
        except Exception as exc:  # shown in the panel, never a crash
            self.failed.emit(self.run_id, f"{type(exc).__name__}: {exc}")
        self.finished.emit(self.run_id)

    def stop(self) -> None:
        self._stop.set()


def frame_source(frame: Any) -> tuple[Any, ...] | None:
    """What a measured trade holds for: the frame's camera and size (None: no frame).

    The one rule of the panel's stale check and of the window's notice of a change.
    """
    if frame is None:
        return None
    shape = tuple(np.shape(getattr(frame, "pixels", frame)))
    return (getattr(frame, "backend", None), getattr(frame, "camera_id", None), shape)


def _source_of(m: Measurement | None) -> tuple[Any, ...] | None:
    """:func:`frame_source` of a measurement's frame."""
    return frame_source(None if m is None else m.frame)


def _describe(source: tuple[Any, ...]) -> str:
    backend, camera, shape = source
    who = " ".join(str(v) for v in (backend, camera) if v) or "a camera"
    return f"{who} ({'x'.join(str(n) for n in shape)})"


def _size_problem(frame: Any, pixels: np.ndarray, psf: np.ndarray) -> str | None:
    """Why the frame and the PSF cannot be used together (HxW, as everywhere), or None."""
    if pixels.shape == psf.shape[-2:]:
        return None
    text = (f"the frame ({pixels.shape[0]}x{pixels.shape[1]}) and the PSF "
            f"({psf.shape[-2]}x{psf.shape[-1]}) differ in size (HxW): ")
    roi, sensor = getattr(frame, "roi", None), getattr(frame, "sensor", None)
    is_roi = roi is not None and sensor is not None and (
        (roi.x, roi.y, roi.height, roi.width) != (0, 0, *sensor))
    if is_roi:
        return text + "the frame is a camera ROI: set the preview's PSF for this ROI first"
    return text + "load a PSF calibrated for this camera first"


class TradePanel(QWidget):
    """Plot of quality against wall time, with the Pareto front and a budget suggestion."""

    rows_changed = Signal()
    #: True when a measurement starts, False when it has ended: the window holds its preview
    #: meanwhile (its FISTA on the same cores doubled the wall times measured)
    measuring = Signal(bool)

    def __init__(
        self,
        current: Callable[[], Measurement | None] | None = None,
        apply_tau: Callable[[float], None] | None = None,
        parent: QWidget | None = None,
        grid: list[Any] | None = None,
    ) -> None:
        """A trade panel; ``grid``: the settings to measure.

        The default grid is ``recon.trade.default_grid(quick=True)`` without the UDN.
        """
        super().__init__(parent)
        self.grid = grid
        self._current = current
        self._apply_tau = apply_tau
        self.rows: list[TradeRow] = []
        self._thread: QThread | None = None
        self._worker: _TradeWorker | None = None
        self._run_id = 0
        #: the measured trade's case (its data, for *Save trade…*), None for a loaded file
        self._case: Any = None
        #: what the measured rows hold for (:func:`_source_of`); None for a loaded file
        self._measured_on: tuple[Any, ...] | None = None
        #: how the measurement was made (trade.csv's header and trade.md)
        self._measured_meta: dict[str, Any] = {}
        self._grid_size = 0
        self._settings_done = 0
        self._cancelled = False
        self._warning = ""
        self._failure = ""  # why the last measurement failed ("": it did not)
        self.measure_button = QPushButton("Measure on current frame")
        self.cancel_button = QPushButton("Cancel")
        self.cancel_button.setEnabled(False)
        self.cancel_button.setToolTip("Stop after the current setting; the settings measured "
                                      "so far stay")
        self.load_button = QPushButton("Load trade.csv…")
        self.save_button = QPushButton("Save trade…")
        self.save_button.setEnabled(False)
        self.save_button.setToolTip("Write the measured trade as trade.csv and trade.md (as "
                                    "lenslesscam trade does; plan --trade reads it)")
        self.case_box = ComboBox()  # the wheel only when focused, as every box
        self.case_box.setToolTip("The case shown: a trade.csv of several cases (trade "
                                 "--protocol) has a front and a suggestion per case")
        self.case_box.setVisible(False)
        self.progress = QLabel("")
        self.budget = DoubleSpinBox()
        self.budget.setRange(0.01, 1e5)
        self.budget.setDecimals(2)
        self.budget.setValue(1.0)
        self.budget.setSuffix(" s")
        self.downsample = SpinBox()
        self.downsample.setRange(1, 16)
        self.downsample.setValue(2)
        self.downsample.setToolTip("Measure on the frame and PSF box-downsampled by this factor")
        self.apply_button = QPushButton("Apply to preview")
        self.apply_button.setEnabled(False)
        self.suggestion = QLabel("no trade measured yet")
        self.suggestion.setWordWrap(True)
        self.plot = pg.PlotWidget()
        self.plot.setLogMode(x=True, y=False)
        self.plot.setLabel("bottom", "wall time (s)")
        self.plot.setLabel("left", "quality (dB)")
        # the legend beside the controls, not in the plot: inside it covered the data points
        front = "#{:02x}{:02x}{:02x}".format(*FRONT_PEN["color"])
        self.legend = QLabel(" ".join(
            f"<span style='color:#{r:02x}{g:02x}{b:02x}'>●</span> {m}"
            for m, (r, g, b) in COLOURS.items())
            + f" <span style='color:{front}; background:black'>━━</span> Pareto front")
        top = QHBoxLayout()
        for w in (self.measure_button, self.cancel_button, QLabel("downsample"),
                  self.downsample, self.progress):
            top.addWidget(w)
        top.addStretch(1)
        files = QHBoxLayout()
        for w in (self.load_button, self.save_button, self.case_box):
            files.addWidget(w)
        files.addStretch(1)
        second = QHBoxLayout()
        for w in (QLabel("time budget"), self.budget, self.apply_button):
            second.addWidget(w)
        second.addStretch(1)
        # controls on the left, the plot beside them with the dock's whole height: stacked
        # under them in the bottom dock at 1366x768 it was 45 px tall, its labels cut
        controls = QVBoxLayout()
        controls.addLayout(top)
        controls.addLayout(files)
        controls.addLayout(second)
        controls.addWidget(self.suggestion)
        controls.addWidget(self.legend)
        controls.addStretch(1)
        lay = QHBoxLayout(self)
        lay.addLayout(controls, 0)
        lay.addWidget(self.plot, 1)
        self.plot.setMinimumSize(320, 150)
        self.measure_button.clicked.connect(self.measure_current)
        self.cancel_button.clicked.connect(self.cancel)
        self.load_button.clicked.connect(self._choose_csv)
        self.save_button.clicked.connect(self._choose_save)
        self.case_box.currentIndexChanged.connect(self._case_chosen)
        self.budget.valueChanged.connect(self._suggest)
        self.apply_button.clicked.connect(self.apply_suggestion)
        self._suggested: TradeRow | None = None

    # -- data ----------------------------------------------------------------------------------

    @property
    def case(self) -> str | None:
        """The case shown (None: no rows)."""
        if self.case_box.count():
            return self.case_box.currentText()
        return self.rows[0].case if self.rows else None

    @property
    def shown_rows(self) -> list[TradeRow]:
        """The rows of the case shown: the plot, the front and the suggestion use these."""
        if self.case_box.count() > 1:
            name = self.case_box.currentText()
            return [r for r in self.rows if r.case == name]
        return self.rows

    @property
    def quality_key(self) -> str:
        """True PSNR when every row shown has it (simulated cases), else the held-out proxy."""
        rows = self.shown_rows
        if rows and all(r.psnr is not None for r in rows):
            return "psnr"
        return "heldout_psnr"

    def set_rows(self, rows: list[TradeRow]) -> None:
        """Show ``rows`` (of a file) and update the suggestion.

        A running measurement is stopped first: rows of two sources are never mixed.
        """
        if self.running:
            self.stop()
        self._case, self._measured_on, self._measured_meta = None, None, {}
        self._warning = self._failure = ""  # the measurement's, not the file's
        self.progress.setText("")
        self._show(rows)

    def _show(self, rows: list[TradeRow]) -> None:
        self.rows = list(rows)
        names = list(dict.fromkeys(r.case for r in self.rows))
        self.case_box.blockSignals(True)
        self.case_box.clear()
        self.case_box.addItems(names)
        self.case_box.setCurrentIndex(0 if names else -1)
        self.case_box.blockSignals(False)
        self.case_box.setVisible(len(names) > 1)
        self._redraw()
        self._suggest()
        self._update_buttons()
        self.rows_changed.emit()

    def _case_chosen(self, _index: int) -> None:
        self._redraw()
        self._suggest()

    def load_csv(self, path: str | Path) -> None:
        """Load a CLI-produced ``trade.csv`` (errors go to the suggestion line).

        Refused while a measurement runs (its rows and the file's would mix): cancel it first.
        """
        if self.running:
            self.suggestion.setText(f"cannot load {path} while a trade is being measured: "
                                    "cancel it first")
            return
        try:
            self.set_rows(read_trade_csv(path))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            self.suggestion.setText(f"cannot load {path}: {exc}")

    def _choose_csv(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Load trade.csv", "", "CSV (*.csv)")
        if path:
            self.load_csv(path)

    def save(self, path: str | Path) -> Path | None:
        """Write the measured trade to ``path`` (trade.csv) and trade.md beside it.

        The writers of ``lenslesscam trade`` (:func:`recon.trade.write_trade_csv`, atomic, its
        header with the format version and the case's data; ``trade.md`` from
        the command's :func:`recon.trade.trade_markdown` with the panel's budget). Returns the CSV's
        path, or None (the reason on the suggestion line).
        """
        from recon.atomic import atomic_write_bytes
        from recon.trade import trade_markdown, write_trade_csv

        if self.running:
            self.suggestion.setText("cannot save while the trade is being measured: wait for "
                                    "it or cancel it")
            return None
        if self._case is None or not self.rows:
            self.suggestion.setText("nothing to save: measure a trade on the current frame "
                                    "first (a loaded trade.csv is a file already)")
            return None
        path = Path(path)
        if path.suffix.lower() != ".csv":  # "x.md" wrote the CSV, then trade.md over it
            self.suggestion.setText(f"cannot save {path}: a trade is saved as a .csv file "
                                    "(its trade.md is written beside it)")
            return None
        meta = self._measured_meta
        try:
            write_trade_csv(path, self.rows, [self._case], command=meta.get("command"),
                            threads=meta.get("threads"))
            md = trade_markdown(self.rows, [self._case], [float(self.budget.value())],
                                f"Produced by the app's trade panel ({meta.get('command')}), "
                                f"{meta.get('threads')} torch thread(s).",
                                f"Every point is in `{path.name}`.")
            atomic_write_bytes(path.with_suffix(".md"), md.encode())
        except (OSError, ValueError) as exc:
            self.suggestion.setText(f"cannot save {path}: {exc}")
            return None
        self.progress.setText(f"saved {path.name} and {path.with_suffix('.md').name}")
        return path

    def _choose_save(self) -> None:
        path, _ = QFileDialog.getSaveFileName(self, "Save trade", "trade.csv", "CSV (*.csv)")
        if path:
            self.save(path)

    # -- measuring -----------------------------------------------------------------------------

    def _frame_case(self, m: Measurement | None) -> Any:
        """The measurement's case, read as the preview reads it; a str says why not."""
        from recon.io import box_downsample
        from recon.trade import Case

        frame = None if m is None else m.frame
        psf = None if m is None else m.psf
        if m is None or frame is None:
            return "needs a live frame (connect a camera) and the preview's PSF"
        if psf is None:
            return "needs the preview's PSF for this camera: load or calibrate one first"
        pixels = np.asarray(getattr(frame, "pixels", frame), dtype=np.float32)
        psf = np.asarray(psf, dtype=np.float32)
        problem = _size_problem(frame, pixels, psf)
        if problem is not None:
            return problem
        # the preview's rules: its saturation verdict and its dark level
        from app.gui.preview_engine import frame_dark_level, saturation_verdict

        bits = getattr(frame, "bit_depth", None)
        sat = int(np.count_nonzero(pixels >= (1 << int(bits)) - 1)) if bits else 0
        refusal, self._warning = saturation_verdict(sat, pixels.size)
        if refusal is not None:
            return refusal
        dark = frame_dark_level(pixels, m.dark, getattr(frame, "black_level", None))
        meas = np.clip(pixels - dark, 0, None)
        top = float(meas.max())
        if top <= 0:
            return "the frame is empty: nothing to reconstruct"
        f = int(self.downsample.value())
        try:
            small = box_downsample(meas / top, f)
            small_psf = box_downsample(psf, f)
        except ValueError as exc:
            return str(exc)
        small_psf = small_psf / max(float(small_psf.sum()), 1e-30)
        source = {"camera": getattr(frame, "camera_id", None),
                  "backend": getattr(frame, "backend", None),
                  "frame_id": getattr(frame, "frame_id", None), "frame_shape": list(pixels.shape),
                  "dark": float(dark), "downsample": f, "psf_source": m.psf_source or None,
                  "psf": m.psf_path or None}
        return Case(CURRENT_CASE, small_psf[None].astype(np.float32),
                    (small / max(float(small.max()), 1e-30))[None].astype(np.float32),
                    source={k: v for k, v in source.items() if v is not None})

    def measure_current(self) -> None:
        """Run a quick trade on the latest frame with the preview's PSF (downsampled)."""
        from recon.trade import default_grid

        m = None if self._current is None else self._current()
        case = self._frame_case(m)
        if isinstance(case, str):
            self.suggestion.setText(case)
            return
        self.stop()
        import torch

        grid = list(self.grid or default_grid(quick=True, with_udn=False))
        self._case, self._measured_on = case, _source_of(m)
        on = _describe(self._measured_on) if self._measured_on else "a frame"
        self._measured_meta = {"command": f"measured on the current frame of {on}, "
                                          f"downsampled by {case.source.get('downsample')}",
                               "threads": torch.get_num_threads()}
        self._grid_size, self._settings_done, self._cancelled = len(grid), 0, False
        self._failure = ""
        self._show([])
        self.suggestion.setText("measuring…" + (f" ({self._warning})" if self._warning else ""))
        self._progress_text()
        self._run_id += 1
        self._worker = _TradeWorker(case, grid, self._run_id)
        self._thread = QThread()
        self._worker.moveToThread(self._thread)
        self._thread.started.connect(self._worker.run)
        self._worker.row.connect(self._add_row)
        self._worker.progress.connect(self._progress)
        self._worker.failed.connect(self._failed)
        self._worker.finished.connect(self._done)
        self._thread.start()
        self.measuring.emit(True)
        self._update_buttons()

    def _add_row(self, run_id: int, row: TradeRow) -> None:
        if run_id != self._run_id or not self.running:  # a stopped measurement's late row
            return
        self.rows.append(row)
        self._redraw()

    def _progress(self, run_id: int, done: int, total: int) -> None:
        if run_id == self._run_id:
            self._settings_done, self._grid_size = done, total
            self._progress_text()

    def _progress_text(self) -> None:
        what = f"{self._settings_done} of {self._grid_size} settings"
        if self.running:
            text = f"cancelling: {what} measured" if self._cancelled else what
        elif self._failure:
            text = f"failed after {what}"
        else:
            text = f"cancelled after {what}" if self._cancelled else f"measured {what}"
        self.progress.setText(text)

    def _failed(self, run_id: int, msg: str) -> None:
        if run_id == self._run_id:
            self.suggestion.setText(f"trade failed: {msg}")
            self._warning = self._failure = f"trade failed: {msg}"
            # what a saved trade.csv / trade.md says of how it was made
            self._measured_meta["command"] = (
                f"{self._measured_meta.get('command')}; it failed after "
                f"{self._settings_done} of {self._grid_size} settings ({msg})")

    def _done(self, run_id: int) -> None:
        if run_id != self._run_id or self._thread is None:
            return
        self._thread.quit()
        if not self._thread.wait(5000):
            from app.gui.workers import detach_thread

            detach_thread(self._thread, self._worker)
        self._thread = self._worker = None
        self.measuring.emit(False)
        self._progress_text()
        self._show(self.rows)

    @property
    def running(self) -> bool:
        """True while a measurement runs."""
        return self._thread is not None

    def cancel(self) -> None:
        """Ask a running measurement to stop after the current setting (without waiting).

        The rows measured so far stay; the suggestion is made from them when it has stopped.
        """
        if self._worker is not None:
            self._worker.stop()
            self._cancelled = True
            self.cancel_button.setEnabled(False)
            self._progress_text()

    def stop(self) -> None:
        """Cancel a running measurement and wait for it (it stops after the current setting)."""
        if self._worker is not None:
            self._worker.stop()
            self._cancelled = True
        if self._thread is not None:
            self._thread.quit()
            if not self._thread.wait(30_000):  # a long setting: never destroy a running thread
                from app.gui.workers import detach_thread

                detach_thread(self._thread, self._worker)
            self._thread = self._worker = None
            self.measuring.emit(False)
            self._run_id += 1  # its queued rows and signals are dropped
            self._progress_text()
        self._update_buttons()

    def _update_buttons(self) -> None:
        running = self.running
        self.measure_button.setEnabled(not running)
        self.load_button.setEnabled(not running)
        self.cancel_button.setEnabled(running and not self._cancelled)
        self.save_button.setEnabled(not running and self._case is not None and bool(self.rows))

    # -- display -------------------------------------------------------------------------------

    def _redraw(self) -> None:
        self.plot.clear()
        key = self.quality_key
        rows = self.shown_rows
        # short: the dock is about 160 px tall at 1366x768 ("held-out prediction (dB)" was cut
        # to "held-out prediction (dE"); the tooltip says what it is
        self.plot.setLabel("left", "PSNR (dB)" if key == "psnr" else "held-out (dB)")
        self.plot.setToolTip("quality: PSNR against the truth" if key == "psnr" else
                             "quality: PSNR of the prediction of held-out measured pixels "
                             "(no truth given)")
        for method, colour in COLOURS.items():
            pts = [r for r in rows if r.method == method and getattr(r, key) is not None]
            if pts:
                self.plot.plot([max(r.wall_s, 1e-4) for r in pts], [getattr(r, key) for r in pts],
                               pen=None, symbol="o", symbolSize=6, symbolBrush=colour,
                               name=method)
        front = pareto_front(rows, key) if rows else []
        if front:
            self.plot.plot([max(r.wall_s, 1e-4) for r in front], [getattr(r, key) for r in front],
                           pen=pg.mkPen(**FRONT_PEN), name="Pareto front")

    def _stale(self) -> str | None:
        """Why the measured rows no longer hold (another camera or frame size), or None."""
        if self._measured_on is None or self._current is None:
            return None
        now = _source_of(self._current())
        if now is None or now == self._measured_on:
            return None
        return (f"measured on {_describe(self._measured_on)}; the camera is now "
                f"{_describe(now)}: measure again")

    def notice_source(self) -> None:
        """The camera or its frame size changed: the window says so at its first frame.

        A measured trade holds for its camera and frame size only, so Apply goes at once (the
        panel looked for a change once a second).
        """
        if (self._measured_on is not None and not self.running
                and self.apply_button.isEnabled() and self._stale()):
            self._suggest()

    def _suggest(self) -> None:
        rows = self.shown_rows
        if not rows:
            self._suggested = None
            self.apply_button.setEnabled(False)
            return
        key = self.quality_key
        budget = float(self.budget.value())
        best = best_for_budgets(rows, [budget], key)[budget]
        self._suggested = best
        case = f"{self.case}: " if self.case_box.count() > 1 else ""
        notes = [n for n in (self._warning, self._stale()) if n]
        tail = f" ({'; '.join(notes)})" if notes else ""
        if best is None:
            fastest = min(rows, key=lambda r: r.wall_s)
            self.suggestion.setText(f"{case}nothing fits {budget:g} s; the fastest setting "
                                    f"takes {fastest.wall_s:.3g} s ({fastest.setting}){tail}")
            self.apply_button.setEnabled(False)
            return
        self.suggestion.setText(
            f"{case}within {budget:g} s: {best.setting}, {best.iterations} iterations "
            f"({best.wall_s:.2f} s, {getattr(best, key):.2f} dB "
            f"{'PSNR' if key == 'psnr' else 'held-out'}){tail}")
        self.apply_button.setEnabled(best.method in ("fista", "admm") and not self.running
                                     and self._stale() is None)

    def apply_suggestion(self) -> None:
        """Hand the suggested tau to the preview (not one measured on another camera)."""
        best = self._suggested
        if self._apply_tau is None or best is None or best.method not in ("fista", "admm"):
            return
        stale = self._stale()
        if stale is not None:
            self.apply_button.setEnabled(False)
            self.suggestion.setText(f"not applied: {stale}")
            return
        self._apply_tau(float(best.tau))
