"""The trade panel: the CLI's trade.csv plotted, a suggestion per budget applied to the preview,
and a quick trade measured on the live frame."""

from __future__ import annotations

from typing import Any

import numpy as np

from recon.trade import TradeRow


def _rows() -> list[TradeRow]:
    def row(setting: str, method: str, tau: float, wall: float, q: float) -> TradeRow:
        return TradeRow("c", setting, method, tau, "float32", 1, 0, 100, wall, 5.0, q, 0.01)

    return [row("fista tau=1e-05", "fista", 1e-5, 0.2, 30.0),
            row("fista tau=0.0001", "fista", 1e-4, 0.5, 33.0),
            row("admm tau=0.001", "admm", 1e-3, 2.0, 35.0),
            row("udn ch32", "udn", 0.0, 50.0, 36.0)]


def test_csv_round_trip_plot_and_suggestion(make_window: Any, tmp_path: Any) -> None:
    import csv

    from app.gui.trade_panel import read_trade_csv

    path = tmp_path / "trade.csv"
    rows = _rows()
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0].as_dict()))
        w.writeheader()
        for r in rows:
            w.writerow(r.as_dict())
    assert [r.as_dict() for r in read_trade_csv(path)] == [r.as_dict() for r in rows]
    win = make_window(autoconnect=False)
    panel = win.trade_panel
    panel.load_csv(path)
    assert len(panel.plot.listDataItems()) == 4  # three methods + the Pareto line
    panel.budget.setValue(1.0)
    assert "fista tau=0.0001" in panel.suggestion.text()
    panel.apply_suggestion()
    assert win.preview_controls.settings().tau == 1e-4
    assert win.engine.settings.tau == 1e-4
    panel.budget.setValue(0.05)
    assert "nothing fits" in panel.suggestion.text() and not panel.apply_button.isEnabled()
    panel.load_csv(tmp_path / "missing.csv")
    assert "cannot load" in panel.suggestion.text()


def test_measure_on_the_live_frame(live_window: Any, qtbot: Any) -> None:
    from recon.trade import Config

    w = live_window
    panel = w.trade_panel
    qtbot.waitUntil(lambda: w.engine.psf is not None, timeout=10_000)
    w.set_live(False)  # the measurement has the machine to itself
    qtbot.waitUntil(lambda: w.camera_state == "stopped", timeout=5_000)
    # a small workload for the test: 37x50, two solvers, two taus, two iteration counts
    panel.downsample.setValue(4)
    panel.grid = [Config(m, t, (10, 30)) for m in ("fista", "admm") for t in (1e-4, 1e-3)]
    panel.measure_current()
    assert panel.running
    qtbot.waitUntil(lambda: not panel.running, timeout=60_000)
    assert len(panel.rows) == 8, panel.suggestion.text()
    assert {r.method for r in panel.rows} == {"fista", "admm"}
    assert all(np.isfinite(r.heldout_psnr) for r in panel.rows)
    assert panel.quality_key == "heldout_psnr"
    assert "within" in panel.suggestion.text() or "nothing fits" in panel.suggestion.text()


def test_the_plot_has_the_docks_height_at_1366x768(make_window: Any, qtbot: Any) -> None:
    """Stacked under its controls in the bottom dock the plot was 45 px tall at 1366x768,
    its axis title cut to 'quality (d': it is now beside them."""
    win = make_window(autoconnect=False)
    win.resize(1366, 740)
    win.trade_dock.show()
    win.trade_dock.raise_()
    panel = win.trade_panel
    qtbot.waitUntil(lambda: panel.isVisible() and panel.plot.height() > 0, timeout=5_000)
    assert panel.plot.height() >= 150, (panel.plot.height(), panel.height())
    assert panel.plot.height() >= panel.height() - 30
    assert panel.plot.width() >= 320
    # the quality axis' title fits its height ("held-out prediction (dE")
    import dataclasses

    for rows in (_rows(), [dataclasses.replace(r, psnr=None) for r in _rows()]):
        panel.set_rows(rows)  # with the truth's PSNR, and with the held-out proxy only
        qtbot.wait(50)
        label = panel.plot.getAxis("left").label
        assert label.boundingRect().width() <= panel.plot.getViewBox().height(), (
            panel.quality_key, label.toPlainText())
