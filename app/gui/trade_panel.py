"""The speed/accuracy trade in the app: the same plot as ``lenslesscam trade``, and a suggestion.

The panel either loads a ``trade.csv`` written by the CLI, or measures a quick trade on the
current raw frame with the preview's PSF (FISTA-TV and ADMM-TV over tau and iterations, the
held-out proxy as quality: there is no ground truth at the bench) in a worker thread. For a
time budget it suggests the best setting found, and *Apply to preview* copies its tau into the
live preview's controls.
"""

from __future__ import annotations

import dataclasses
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import QObject, Qt, QThread, Signal
from PySide6.QtWidgets import (
    QDockWidget,
    QDoubleSpinBox,
    QFileDialog,
    QHBoxLayout,
    QLabel,
    QPushButton,
    QVBoxLayout,
    QWidget,
)

from recon.trade import TradeRow, best_for_budgets, pareto_front, read_trade_csv

if TYPE_CHECKING:
    from app.gui.main_window import MainWindow

COLOURS = {"fista": (31, 119, 180), "admm": (255, 127, 14), "udn": (44, 160, 44)}


class _TradeWorker(QObject):
    row = Signal(object)
    finished = Signal()
    failed = Signal(str)

    def __init__(self, case: Any) -> None:
        super().__init__()
        self.case = case
        self._stop = threading.Event()

    def run(self) -> None:
        from recon.trade import default_grid, run_trade

        try:
            for r in run_trade(self.case, default_grid(quick=True, with_udn=False),
                               cancel=self._stop.is_set):
                self.row.emit(r)
        except Exception as exc:  # shown in the panel, never a crash
            self.failed.emit(f"{type(exc).__name__}: {exc}")
        self.finished.emit()

    def stop(self) -> None:
        self._stop.set()


class TradePanel(QWidget):
    """Plot of quality against wall time, with the Pareto front and a budget suggestion."""

    rows_changed = Signal()

    def __init__(self, window: MainWindow | None = None) -> None:
        super().__init__()
        self.window_ = window
        self.rows: list[TradeRow] = []
        self._thread: QThread | None = None
        self._worker: _TradeWorker | None = None
        self.measure_button = QPushButton("Measure on current frame")
        self.load_button = QPushButton("Load trade.csv…")
        self.budget = QDoubleSpinBox()
        self.budget.setRange(0.01, 1e5)
        self.budget.setDecimals(2)
        self.budget.setValue(1.0)
        self.budget.setSuffix(" s")
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
        for w in (self.measure_button, self.load_button, QLabel("budget"), self.budget,
                  self.apply_button):
            top.addWidget(w)
        lay = QVBoxLayout(self)
        lay.addLayout(top)
        lay.addWidget(self.suggestion)
        lay.addWidget(self.plot, 1)
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
        """Run a quick trade on the window's latest frame with the preview's PSF."""
        from recon.trade import Case

        w = self.window_
        frame = None if w is None else w.last_frame
        psf = None if w is None else w.engine.psf
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
        case = Case("current frame", psf[None].astype(np.float32),
                    (meas / top)[None].astype(np.float32))
        self.stop()
        self.rows = []
        self._redraw()
        self.suggestion.setText("measuring…")
        self.measure_button.setEnabled(False)
        self._worker = _TradeWorker(case)
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
            self._thread.wait(5000)
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
            self._thread.wait(30_000)
            self._thread = self._worker = None
            self.measure_button.setEnabled(True)

    # -- display -------------------------------------------------------------------------------

    def _redraw(self) -> None:
        self.plot.clear()
        key = self.quality_key
        self.plot.setLabel("left", "PSNR vs truth (dB)" if key == "psnr"
                           else "held-out prediction (dB)")
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
                                    f"{fastest.wall_s:.2f} s ({fastest.setting})")
            self.apply_button.setEnabled(False)
            return
        self.suggestion.setText(
            f"within {budget:g} s: {best.setting}, {best.iterations} iterations "
            f"({best.wall_s:.2f} s, {getattr(best, key):.2f} dB "
            f"{'PSNR' if key == 'psnr' else 'held-out'})")
        self.apply_button.setEnabled(best.method in ("fista", "admm"))

    def apply_suggestion(self) -> None:
        """Copy the suggested tau into the live preview's controls."""
        w, best = self.window_, self._suggested
        if w is None or best is None or best.method not in ("fista", "admm"):
            return
        s = dataclasses.replace(w.preview_controls.settings(), tau=float(best.tau))
        w.preview_controls.set_settings(s)
        w.set_preview_settings(s)


def add_trade_dock(window: MainWindow) -> None:
    """Put a :class:`TradePanel` in a (hidden by default) right dock of ``window``."""
    panel = TradePanel(window)
    dock = QDockWidget("Speed / accuracy trade", window)
    dock.setObjectName("trade-dock")
    dock.setWidget(panel)
    window.addDockWidget(Qt.DockWidgetArea.RightDockWidgetArea, dock)
    dock.hide()
    window.trade_panel = panel
    window.trade_dock = dock
    act = dock.toggleViewAction()
    act.setText("Speed/accuracy trade panel")
    window.tools_menu.addAction(act)
    window._close_hooks = [*getattr(window, "_close_hooks", []), panel.stop]
