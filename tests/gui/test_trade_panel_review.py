"""The trade panel: findings of a hostile review (the old behaviour in each test's docstring).

The panel stands alone here, its measurement given by ``current()``; the solvers are replaced
by a stand-in for ``recon.trade.run_trade`` (rows at once, or held until the test lets go), so
that the tests are about the panel.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np
import pytest

from recon.trade import Case, Config, TradeRow, read_trade, write_trade_csv

GRID = [Config("fista", 1e-4, (10,)), Config("admm", 1e-3, (10,)), Config("fista", 1e-2, (10,))]


def _frame(pixels: np.ndarray, *, camera: str = "simcam", bit_depth: int = 12,
           sensor: tuple[int, int] | None = None, roi: tuple[int, int, int, int] | None = None
           ) -> Any:
    from drivers.camera import Frame, Roi

    h, w = pixels.shape
    x, y, rw, rh = roi or (0, 0, w, h)
    return Frame(np.asarray(pixels), 1, time.time(), 1000.0, 1.0, Roi(x, y, rw, rh), 1,
                 "Mono12", bit_depth, None, "sim", camera, sensor=sensor or (h, w))


def _scene(h: int = 32, w: int = 40, offset: float = 1000.0) -> np.ndarray:
    rng = np.random.default_rng(0)
    return (offset + 1000.0 * rng.random((h, w))).astype(np.uint16)


def _psf(h: int = 32, w: int = 40) -> np.ndarray:
    p = np.random.default_rng(1).random((h, w)).astype(np.float32) ** 8
    return p / p.sum()


class FakeTrade:
    """``run_trade`` stand-in: one row per setting; ``hold``: wait after the first setting
    until released or cancelled."""

    def __init__(self, hold: bool = False) -> None:
        self.cases: list[Any] = []
        self.release = threading.Event()
        self.hold = hold

    def __call__(self, case: Any, grid: Any, *, cancel: Any = None, finished: Any = None,
                 **_: Any) -> Any:
        self.cases.append(case)
        for i, cfg in enumerate(grid):
            if cancel is not None and cancel():
                return
            yield TradeRow(case.name, cfg.label, cfg.method, cfg.tau, "float32", 1, 0, 10,
                           0.1 * (i + 1), 1.0, 30.0 + i, 0.01)
            if finished is not None:
                finished(cfg.label)
            if self.hold and i == 0:
                while not self.release.is_set() and not (cancel is not None and cancel()):
                    time.sleep(0.01)


@pytest.fixture
def panel_for(qtbot: Any, monkeypatch: pytest.MonkeyPatch) -> Any:
    """Factory: ``(panel, fake run_trade, applied taus)`` measuring ``state['m']``."""
    import recon.trade as rt
    from app.gui.jobs_panel import Measurement
    from app.gui.trade_panel import TradePanel

    def make(frame: Any, psf: Any = None, dark: float | None = None, hold: bool = False,
             ) -> tuple[Any, FakeTrade, list[float], dict[str, Any]]:
        fake = FakeTrade(hold)
        monkeypatch.setattr(rt, "run_trade", fake)
        state = {"m": Measurement(frame, _psf() if psf is None else psf, dark=dark)}
        applied: list[float] = []
        panel = TradePanel(lambda: state["m"], applied.append, grid=list(GRID))
        qtbot.addWidget(panel)
        panel.show()
        return panel, fake, applied, state

    yield make


def _finish(panel: Any, fake: FakeTrade, qtbot: Any) -> None:
    fake.release.set()
    qtbot.waitUntil(lambda: not panel.running, timeout=10_000)


# -- A: a trade.csv of several cases ---------------------------------------------------------


def _protocol_csv(path: Any) -> Any:
    def row(case: str, tau: float, wall: float, q: float) -> TradeRow:
        return TradeRow(case, f"fista tau={tau:g}", "fista", tau, "float32", 1, 0, 100, wall,
                        5.0, 36.0, 0.01, psnr=q, ssim=0.5)

    rows = [row("im408 99%", 1e-5, 0.1, 12.0), row("im408 99%", 1e-3, 0.5, 13.5),
            row("im740 90%", 1e-5, 0.1, 19.4), row("im740 90%", 1e-3, 0.5, 17.0)]
    z = np.full((1, 8, 8), 1 / 64, np.float32)
    return write_trade_csv(path, rows, [Case("im408 99%", z, z), Case("im740 90%", z, z)])


def test_a_file_of_several_cases_shows_one_case_at_a_time(panel_for: Any, qtbot: Any,
                                                          tmp_path: Any) -> None:
    """A trade.csv of `trade --protocol` was pooled into one front and one suggestion (the
    other case's tau 1e-5 at 19.4 dB won for im408, whose best within 1 s is tau 1e-3), the
    case not named."""
    panel, _, applied, _ = panel_for(_frame(_scene()))
    panel.load_csv(_protocol_csv(tmp_path / "trade.csv"))
    panel.budget.setValue(1.0)
    assert not panel.case_box.isHidden()
    assert [panel.case_box.itemText(i) for i in range(panel.case_box.count())] == [
        "im408 99%", "im740 90%"]
    assert panel.case == "im408 99%"  # the first case by default
    assert "im408 99%" in panel.suggestion.text()
    assert "fista tau=0.001" in panel.suggestion.text()
    front = [i for i in panel.plot.listDataItems() if i.opts["pen"] is not None]
    assert len(front) == 1 and list(front[0].yData) == [12.0, 13.5]  # this case's front only
    panel.apply_suggestion()
    panel.case_box.setCurrentIndex(1)
    assert "im740 90%" in panel.suggestion.text()
    assert "fista tau=1e-05" in panel.suggestion.text()
    panel.apply_suggestion()
    assert applied == [1e-3, 1e-5]


def test_one_case_hides_the_case_box(panel_for: Any, qtbot: Any) -> None:
    panel, fake, _, _ = panel_for(_frame(_scene()))
    panel.measure_current()
    _finish(panel, fake, qtbot)
    assert panel.case_box.isHidden() and len(panel.rows) == 3


# -- B: Load while measuring ------------------------------------------------------------------


def test_load_waits_for_a_measurement_and_rows_never_mix(panel_for: Any, qtbot: Any,
                                                         tmp_path: Any) -> None:
    """Load stayed enabled while a measurement ran, and the worker's rows were then appended
    to the loaded file's."""
    path = _protocol_csv(tmp_path / "trade.csv")
    panel, fake, _, _ = panel_for(_frame(_scene()), hold=True)
    panel.measure_current()
    qtbot.waitUntil(lambda: len(panel.rows) == 1, timeout=10_000)
    assert not panel.load_button.isEnabled()
    panel.load_csv(path)
    assert "cancel it first" in panel.suggestion.text()
    _finish(panel, fake, qtbot)
    assert {r.case for r in panel.rows} == {"current frame"} and len(panel.rows) == 3
    assert panel.load_button.isEnabled()
    # rows given while measuring stop the measurement: its later rows never join them
    fake.release.clear()
    panel.measure_current()
    qtbot.waitUntil(lambda: len(panel.rows) == 1, timeout=10_000)
    panel.load_csv(path)  # refused
    panel.set_rows(read_trade(path).rows)
    assert not panel.running
    fake.release.set()
    qtbot.wait(200)
    assert {r.case for r in panel.rows} == {"im408 99%", "im740 90%"} and len(panel.rows) == 4


# -- C: the Pareto front's line and the legend ----------------------------------------------


def test_the_front_line_is_visible_and_the_legend_is_outside_the_plot(panel_for: Any,
                                                                      tmp_path: Any) -> None:
    """The front was drawn in black ("k") on pyqtgraph's black background; the legend sat in
    the plot's top-left corner over the data points."""
    from PySide6.QtGui import QColor

    panel, _, _, _ = panel_for(_frame(_scene()))
    panel.load_csv(_protocol_csv(tmp_path / "trade.csv"))
    front = [i for i in panel.plot.listDataItems() if i.opts["pen"] is not None]
    assert len(front) == 1
    pen = front[0].opts["pen"]
    colour = pen.color() if hasattr(pen, "color") else QColor(pen)
    background = panel.plot.backgroundBrush().color()
    assert abs(colour.lightness() - background.lightness()) >= 128, (
        colour.name(), background.name())
    assert pen.widthF() >= 2
    assert panel.plot.getPlotItem().legend is None  # no legend over the points
    text = panel.legend.text()
    assert all(m in text for m in ("fista", "admm", "udn", "Pareto front"))


# -- D: progress and Cancel -------------------------------------------------------------------


def test_a_measurement_shows_progress_and_can_be_cancelled(panel_for: Any, qtbot: Any) -> None:
    """No Cancel (Measure disabled, "measuring…" until the end) and no progress."""
    panel, fake, _, _ = panel_for(_frame(_scene()), hold=True)
    assert not panel.cancel_button.isEnabled()
    panel.measure_current()
    assert panel.running and panel.cancel_button.isEnabled()
    qtbot.waitUntil(lambda: panel.progress.text() == "1 of 3 settings", timeout=10_000)
    panel.cancel_button.click()
    qtbot.waitUntil(lambda: not panel.running, timeout=10_000)
    assert panel.progress.text() == "cancelled after 1 of 3 settings"
    assert [r.setting for r in panel.rows] == [GRID[0].label]  # what was measured stays
    assert "within" in panel.suggestion.text() and panel.apply_button.isEnabled()
    assert panel.measure_button.isEnabled() and not panel.cancel_button.isEnabled()
    panel.measure_current()
    _finish(panel, fake, qtbot)
    assert panel.progress.text() == "measured 3 of 3 settings" and len(panel.rows) == 3


# -- E: the frame read as the preview reads it ------------------------------------------------


def test_the_preview_dark_level_is_subtracted(panel_for: Any, qtbot: Any) -> None:
    """The panel subtracted the frame's 1st percentile whatever the preview's dark was: a
    frame of 1000 + scene with the preview's dark 0 lost its offset."""
    panel, fake, _, state = panel_for(_frame(_scene()), dark=0.0)
    panel.measure_current()
    _finish(panel, fake, qtbot)
    meas = fake.cases[-1].meas
    assert meas.min() > 0.3, meas.min()  # 1000 of at most 2000 kept, normalised to max 1
    assert fake.cases[-1].source["dark"] == 0.0
    from app.gui.jobs_panel import Measurement, _dark_level

    state["m"] = Measurement(_frame(_scene()), _psf(), dark=None)  # auto: the jobs' rule
    panel.measure_current()
    _finish(panel, fake, qtbot)
    assert fake.cases[-1].source["dark"] == _dark_level(state["m"]) > 1000
    assert fake.cases[-1].meas.min() < 0.3


def test_auto_takes_the_cameras_black_level_as_the_preview_does(panel_for: Any,
                                                                 qtbot: Any) -> None:
    """Auto was an estimate from the frame even where the camera reports its black level: on
    a lensless frame that is scene light (tests/test_camera_black_level.py)."""
    from dataclasses import replace

    from app.gui.jobs_panel import _dark_level

    frame = replace(_frame(_scene()), black_level=900.0)
    panel, fake, _, state = panel_for(frame, dark=None)
    panel.measure_current()
    _finish(panel, fake, qtbot)
    assert fake.cases[-1].source["dark"] == _dark_level(state["m"]) == 900.0
    assert fake.cases[-1].meas.min() > 0.0  # 100 of at most 1100 codes kept everywhere


def test_a_saturated_frame_is_not_measured(panel_for: Any, qtbot: Any) -> None:
    """A 64 %-saturated frame (which the preview refuses) was measured and suggested on."""
    px = _scene()
    px.ravel()[: int(0.64 * px.size)] = 4095
    panel, fake, _, state = panel_for(_frame(px, bit_depth=12))
    panel.measure_current()
    assert not panel.running and not fake.cases
    assert "frame saturated (64 %" in panel.suggestion.text()
    few = _scene()
    few[0, :3] = 4095
    from app.gui.jobs_panel import Measurement

    state["m"] = Measurement(_frame(few, bit_depth=12), _psf())
    panel.measure_current()
    _finish(panel, fake, qtbot)
    assert "3 saturated pixel(s)" in panel.suggestion.text()


# -- F: Save trade… ---------------------------------------------------------------------------


def test_a_measured_trade_is_saved_as_the_cli_writes_it(panel_for: Any, qtbot: Any,
                                                        tmp_path: Any) -> None:
    """A trade measured in the panel could not be saved (plan --trade had nothing to read)."""
    from recon.formats import FORMAT_VERSION

    panel, fake, _, _ = panel_for(_frame(_scene()), dark=0.0)
    assert not panel.save_button.isEnabled()
    panel.measure_current()
    _finish(panel, fake, qtbot)
    assert panel.save_button.isEnabled()
    path = panel.save(tmp_path / "out" / "trade.csv")
    assert path == tmp_path / "out" / "trade.csv"
    trade = read_trade(path)  # the one reader, plan --trade's
    assert trade.format_version == FORMAT_VERSION
    assert [r.as_dict() for r in trade.rows] == [r.as_dict() for r in panel.rows]
    (case,) = trade.cases
    assert case["name"] == "current frame" and case["shape"] == [1, 16, 20]
    assert case["source"]["dark"] == 0.0 and case["source"]["downsample"] == 2
    assert "downsampled by 2" in trade.meta["command"]
    md = (tmp_path / "out" / "trade.md").read_text()
    assert md.startswith("# Speed/accuracy trade") and "## current frame" in md
    assert "Pareto front" in md and GRID[0].label in md


def test_save_is_refused_for_a_loaded_file(panel_for: Any, tmp_path: Any) -> None:
    panel, _, _, _ = panel_for(_frame(_scene()))
    panel.load_csv(_protocol_csv(tmp_path / "trade.csv"))
    assert not panel.save_button.isEnabled()
    assert panel.save(tmp_path / "again.csv") is None
    assert not (tmp_path / "again.csv").exists()


# -- I: stale messages ------------------------------------------------------------------------


def test_a_wrong_size_psf_on_a_full_sensor_frame_does_not_speak_of_a_roi(panel_for: Any
                                                                         ) -> None:
    """'set the preview's PSF for this ROI first' was said of a full-sensor frame."""
    panel, fake, _, state = panel_for(_frame(_scene()), psf=_psf(16, 20))
    panel.measure_current()
    text = panel.suggestion.text()
    assert "differ in size" in text and "ROI" not in text and not fake.cases
    from app.gui.jobs_panel import Measurement

    roi = _frame(_scene(), sensor=(64, 80), roi=(8, 8, 40, 32))
    state["m"] = Measurement(roi, _psf(64, 80))
    panel.measure_current()
    assert "ROI" in panel.suggestion.text()


def test_rows_of_another_camera_are_not_applied(panel_for: Any, qtbot: Any) -> None:
    """After switching camera mid-trade, the old camera's rows stayed and Apply stayed
    enabled for them: their tau went to the new camera's preview."""
    from app.gui.jobs_panel import Measurement

    panel, fake, applied, state = panel_for(_frame(_scene(), camera="A"), hold=True)
    panel.measure_current()
    qtbot.waitUntil(lambda: len(panel.rows) == 1, timeout=10_000)
    state["m"] = Measurement(_frame(_scene(24, 30), camera="B"), _psf(24, 30))
    _finish(panel, fake, qtbot)
    assert "measure again" in panel.suggestion.text()
    assert not panel.apply_button.isEnabled()
    panel.apply_suggestion()
    assert applied == []
    assert "not applied" in panel.suggestion.text()


def test_the_window_tells_the_panel_of_another_camera_at_its_first_frame(
        live_window: Any, qtbot: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """The panel found a camera switch by looking once a second: Apply stayed on that long."""
    from dataclasses import replace

    w = live_window
    told: list[int] = []
    monkeypatch.setattr(w.trade_panel, "notice_source", lambda: told.append(1))
    frame = w.last_frame
    w._show_frame(replace(frame, frame_id=frame.frame_id + 1))  # the same camera and size
    assert told == []
    w._show_frame(replace(frame, camera_id="another camera"))
    assert told == [1]


def test_notice_source_takes_apply_away_at_once(panel_for: Any, qtbot: Any) -> None:
    from app.gui.jobs_panel import Measurement

    panel, fake, _applied, state = panel_for(_frame(_scene(), camera="A"))
    panel.measure_current()
    _finish(panel, fake, qtbot)
    assert panel.apply_button.isEnabled()
    state["m"] = Measurement(_frame(_scene(24, 30), camera="B"), _psf(24, 30))
    panel.notice_source()
    assert not panel.apply_button.isEnabled() and "measure again" in panel.suggestion.text()


def test_a_failed_measurement_says_so_and_its_notes_do_not_follow_a_loaded_file(
        panel_for: Any, qtbot: Any, tmp_path: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """(diff review) A failure after one setting showed "measured 1 of 3 settings" and saved
    without a word of it; a file loaded afterwards kept "(trade failed: ...)" (or a saturation
    warning) in its suggestion."""
    import recon.trade as rt
    from recon.trade import read_trade

    panel, _fake, _, _ = panel_for(_frame(_scene()))

    def boom(case: Any, grid: Any, *, cancel: Any = None, finished: Any = None,
             **_k: Any) -> Any:
        yield rt.TradeRow(case.name, "fista tau=0.0001", "fista", 1e-4, "float32", 1, 0, 10,
                          0.1, 1.0, 30.0, 0.01)
        finished("fista tau=0.0001")
        raise RuntimeError("boom")

    monkeypatch.setattr(rt, "run_trade", boom)
    panel.measure_current()
    qtbot.waitUntil(lambda: not panel.running, timeout=10_000)
    assert panel.progress.text().startswith("failed after 1 of ")
    saved = panel.save(tmp_path / "t.csv")
    assert saved is not None and "failed after 1 of" in read_trade(saved).meta["command"]
    assert "failed after 1 of" in (tmp_path / "t.md").read_text()
    panel.load_csv(_protocol_csv(tmp_path / "trade.csv"))
    assert "boom" not in panel.suggestion.text() and "failed" not in panel.suggestion.text()


def test_a_trade_is_saved_under_a_csv_name_only(panel_for: Any, qtbot: Any,
                                                tmp_path: Any) -> None:
    """(diff review) Saving as results.md wrote the CSV there, then trade.md over it."""
    panel, fake, _, _ = panel_for(_frame(_scene()))
    panel.measure_current()
    _finish(panel, fake, qtbot)
    assert panel.save(tmp_path / "results.md") is None
    assert "saved as a .csv file" in panel.suggestion.text()
    assert list(tmp_path.iterdir()) == []


def test_a_trade_csv_over_csvs_field_limit_is_said_for_that_file(panel_for: Any,
                                                                 tmp_path: Any) -> None:
    """(GUI review) Load trade.csv… printed a traceback and kept the previous file's error."""
    panel, _fake, _, _ = panel_for(_frame(_scene()))
    (tmp_path / "bad.csv").write_text("not,a,trade\n")
    panel.load_csv(tmp_path / "bad.csv")
    big = tmp_path / "big.csv"
    big.write_text("case,setting\nim65,\"" + "x" * 200_000 + "\"\n")
    panel.load_csv(big)
    assert panel.suggestion.text().startswith(f"cannot load {big}: ")
    assert "field larger than field limit" in panel.suggestion.text()
