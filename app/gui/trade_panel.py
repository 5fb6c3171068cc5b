"""The speed/accuracy trade in the app: the same plot as ``lenslesscam trade``, and a suggestion.

The panel either loads a ``trade.csv`` written by the CLI, or measures a quick trade on the
current raw frame with the preview's PSF, box-downsampled by the panel's factor (FISTA-TV and
ADMM-TV over tau and iterations, the held-out proxy as quality: there is no ground truth at the
bench) in a worker thread. For a time budget it suggests the best setting found, and *Apply to
preview* hands its tau to the preview.

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
from app.gui.widgets import DoubleSpinBox, SpinBox
from recon.trade import TradeRow, best_for_budgets, pareto_front, read_trade_csv

COLOURS = {"fista": (31, 119, 180), "admm": (255, 127, 14), "udn": (44, 160, 44)}


class _TradeWorker(QObject):
    row = Signal(object)
    finished = Signal()
    failed = Signal(str)

    def __init__(self, case: Any, grid: list[Any] | None) -> None:
        super().__init__()
        self.case = case
        self.grid = grid
        self._stop = threading.Event()

    def run(self) -> None:
        from recon.trade import default_grid, run_trade

        try:
            grid = self.grid or default_grid(quick=True, with_udn=False)
            for r in run_trade(self.case, grid, cancel=self._stop.is_set):
                self.row.emit(r)
        except Exception as exc:  # shown in the panel, never a crash
            self.failed.emit(f"{type(exc).__name__}: {exc}")
        self.finished.emit()

    def stop(self) -> None:
        self._stop.set()


class TradePanel(QWidget):
    """Plot of quality against wall time, with the Pareto front and a budget suggestion."""

    rows_changed = Signal()

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
        self.measure_button = QPushButton("Measure on current frame")
        self.load_button = QPushButton("Load trade.csv…")
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
        self.plot.addLegend(offset=(5, 5))
        top = QHBoxLayout()
        for w in (self.measure_button, QLabel("downsample"), self.downsample,
                  self.load_button):
            top.addWidget(w)
        top.addStretch(1)
        second = QHBoxLayout()
        for w in (QLabel("time budget"), self.budget, self.apply_button):
            second.addWidget(w)
        second.addStretch(1)
        # controls on the left, the plot beside them with the dock's whole height: stacked
        # under them in the bottom dock at 1366x768 it was 45 px tall, its labels cut
        controls = QVBoxLayout()
        controls.addLayout(top)
        controls.addLayout(second)
        controls.addWidget(self.suggestion)
        controls.addStretch(1)
        lay = QHBoxLayout(self)
        lay.addLayout(controls, 0)
        lay.addWidget(self.plot, 1)
        self.plot.setMinimumSize(320, 150)
        self.measure_button.clicked.connect(self.measure_current)
        self.load_button.clicked.connect(self._choose_csv)
        self.budget.valueChanged.connect(self._suggest)
        self.apply_button.clicked.connect(self.apply_suggestion)
        self._suggested: TradeRow | None = None

    # -- data ----------------------------------------------------------------------------------

    @property
    def quality_key(self) -> str:
        """True PSNR when every row has it (simulated cases), else the held-out proxy."""
        if self.rows and all(r.psnr is not None for r in self.rows):
            return "psnr"
        return "heldout_psnr"

    def set_rows(self, rows: list[TradeRow]) -> None:
        """Show ``rows`` and update the suggestion."""
        self.rows = list(rows)
        self._redraw()
        self._suggest()
        self.rows_changed.emit()

    def load_csv(self, path: str | Path) -> None:
        """Load a CLI-produced ``trade.csv`` (errors go to the suggestion line)."""
        try:
            self.set_rows(read_trade_csv(path))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            self.suggestion.setText(f"cannot load {path}: {exc}")

    def _choose_csv(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Load trade.csv", "", "CSV (*.csv)")
        if path:
            self.load_csv(path)

    # -- measuring -----------------------------------------------------------------------------

    def measure_current(self) -> None:
        """Run a quick trade on the latest frame with the preview's PSF (downsampled)."""
        from recon.io import box_downsample
        from recon.trade import Case

        m = None if self._current is None else self._current()
        frame = None if m is None else m.frame
        psf = None if m is None else m.psf
        if frame is None or psf is None:
            self.suggestion.setText("needs a live frame and a PSF")
            return
        pixels = np.asarray(getattr(frame, "pixels", frame), dtype=np.float32)
        if pixels.shape != psf.shape[-2:]:
            self.suggestion.setText(f"frame {pixels.shape} and PSF {psf.shape[-2:]} differ in "
                                    "size: set the preview's PSF for this ROI first")
            return
        meas = pixels - np.percentile(pixels, 1)
        meas = np.clip(meas, 0, None)
        top = float(meas.max())
        if top <= 0:
            self.suggestion.setText("the frame is empty: nothing to reconstruct")
            return
        f = int(self.downsample.value())
        try:
            small = box_downsample(meas / top, f)
            small_psf = box_downsample(np.asarray(psf, dtype=np.float32), f)
        except ValueError as exc:
            self.suggestion.setText(str(exc))
            return
        small_psf = small_psf / max(float(small_psf.sum()), 1e-30)
        case = Case("current frame", small_psf[None].astype(np.float32),
                    (small / max(float(small.max()), 1e-30))[None].astype(np.float32))
        self.stop()
        self.rows = []
        self._redraw()
        self.suggestion.setText("measuring…")
        self.measure_button.setEnabled(False)
        self._worker = _TradeWorker(case, self.grid)
        self._thread = QThread()
        self._worker.moveToThread(self._thread)
        self._thread.started.connect(self._worker.run)
        self._worker.row.connect(self._add_row)
        self._worker.failed.connect(lambda msg: self.suggestion.setText(f"trade failed: {msg}"))
        self._worker.finished.connect(self._done)
        self._thread.start()

    def _add_row(self, row: TradeRow) -> None:
        self.rows.append(row)
        self._redraw()

    def _done(self) -> None:
        self.measure_button.setEnabled(True)
        if self._thread is not None:
            self._thread.quit()
            if not self._thread.wait(5000):
                from app.gui.workers import detach_thread

                detach_thread(self._thread, self._worker)
        self._thread = self._worker = None
        self._suggest()
        self.rows_changed.emit()

    @property
    def running(self) -> bool:
        """True while a measurement runs."""
        return self._thread is not None

    def stop(self) -> None:
        """Cancel a running measurement (it stops after the current setting)."""
        if self._worker is not None:
            self._worker.stop()
        if self._thread is not None:
            self._thread.quit()
            if not self._thread.wait(30_000):  # a long setting: never destroy a running thread
                from app.gui.workers import detach_thread

                detach_thread(self._thread, self._worker)
            self._thread = self._worker = None
            self.measure_button.setEnabled(True)

    # -- display -------------------------------------------------------------------------------

    def _redraw(self) -> None:
        self.plot.clear()
        key = self.quality_key
        # short: the dock is about 160 px tall at 1366x768 ("held-out prediction (dB)" was cut
        # to "held-out prediction (dE"); the tooltip says what it is
        self.plot.setLabel("left", "PSNR (dB)" if key == "psnr" else "held-out (dB)")
        self.plot.setToolTip("quality: PSNR against the truth" if key == "psnr" else
                             "quality: PSNR of the prediction of held-out measured pixels "
                             "(no truth given)")
        for method, colour in COLOURS.items():
            pts = [r for r in self.rows if r.method == method and getattr(r, key) is not None]
            if pts:
                self.plot.plot([max(r.wall_s, 1e-4) for r in pts], [getattr(r, key) for r in pts],
                               pen=None, symbol="o", symbolSize=6, symbolBrush=colour,
                               name=method)
        front = pareto_front(self.rows, key) if self.rows else []
        if front:
            self.plot.plot([max(r.wall_s, 1e-4) for r in front], [getattr(r, key) for r in front],
                           pen=pg.mkPen("k", width=1))

    def _suggest(self) -> None:
        if not self.rows:
            self._suggested = None
            self.apply_button.setEnabled(False)
            return
        key = self.quality_key
        budget = float(self.budget.value())
        best = best_for_budgets(self.rows, [budget], key)[budget]
        self._suggested = best
        if best is None:
            fastest = min(self.rows, key=lambda r: r.wall_s)
            self.suggestion.setText(f"nothing fits {budget:g} s; the fastest setting takes "
                                    f"{fastest.wall_s:.3g} s ({fastest.setting})")
            self.apply_button.setEnabled(False)
            return
        self.suggestion.setText(
            f"within {budget:g} s: {best.setting}, {best.iterations} iterations "
            f"({best.wall_s:.2f} s, {getattr(best, key):.2f} dB "
            f"{'PSNR' if key == 'psnr' else 'held-out'})")
        self.apply_button.setEnabled(best.method in ("fista", "admm"))

    def apply_suggestion(self) -> None:
        """Hand the suggested tau to the preview."""
        best = self._suggested
        if self._apply_tau is None or best is None or best.method not in ("fista", "admm"):
            return
        self._apply_tau(float(best.tau))
