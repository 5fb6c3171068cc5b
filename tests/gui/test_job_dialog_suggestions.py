"""The UDN job dialog offers the settings a plan or trade found for the selected measurement."""

from __future__ import annotations

import csv
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PySide6.QtWidgets import QLabel

from recon.plan import Plan
from recon.suggest import input_hashes, write_plan_suggestion, write_trade_inputs
from recon.trade import TradeRow, write_trade_csv


@dataclass
class _Frame:
    pixels: np.ndarray
    frame_id: int = 7
    backend: str = "test"
    black_level: float | None = 100.0  # the offset _measurement puts the frame on

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.pixels.shape[0]), int(self.pixels.shape[1]))

    def metadata(self) -> dict[str, Any]:
        return {"frame_id": self.frame_id}


def _measurement(seed: int) -> Any:
    from app.gui.jobs_panel import Measurement

    rng = np.random.default_rng(seed)
    psf = np.zeros((48, 64), np.float32)
    psf[rng.integers(0, 48, 30), rng.integers(0, 64, 30)] = 1.0
    scene = np.zeros((48, 64), np.float32)
    scene[16:32, 20:44] = 1.0
    meas = np.real(np.fft.ifft2(np.fft.fft2(psf) * np.fft.fft2(scene)))
    pixels = (100 + 3000 * meas / meas.max() + rng.normal(0, 5, meas.shape)).astype(np.uint16)
    return Measurement(_Frame(pixels), psf, psf_source="test")


def _plan(downsample: int, iterations: int = 1234) -> Plan:
    return Plan(model="2d", k=1, sensor=(48, 64), field=(48, 64), region=(0, 0, 48, 64),
                downsample=downsample, method="udn", iterations=iterations, budget_s=7200.0)


def _hashes(m: Any) -> dict[str, str]:
    return input_hashes(m.frame.pixels, m.psf)


@pytest.fixture
def panel(qtbot: Any, tmp_path: Path) -> Any:
    from app.gui.jobs_panel import JobsPanel

    state: dict[str, Any] = {"m": _measurement(0)}
    p = JobsPanel(tmp_path / "jobs", lambda: state["m"], poll_ms=60_000)
    p.state = state
    qtbot.addWidget(p)
    yield p
    p.stop()
    dlg = getattr(p, "dialog", None)
    if dlg is not None:
        dlg.close()


def test_a_matching_plan_is_offered_and_fills_the_fields(panel: Any, qtbot: Any) -> None:
    folder = panel.suggestion_dirs[0]
    mine = write_plan_suggestion(folder, _plan(downsample=4), _hashes(panel.state["m"]))
    write_plan_suggestion(folder, _plan(downsample=6, iterations=99),
                          _hashes(_measurement(1)))  # another measurement: not offered
    dlg = panel.new_job_dialog()
    assert dlg is not None
    assert dlg.suggestion_box.isEnabled() and dlg.apply_suggestion_button.isEnabled()
    assert dlg.suggestion_box.count() == 1
    assert mine.name in dlg.suggestion_box.itemText(0)
    assert dlg.downsample.value() == 2  # nothing changes until Apply
    qtbot.mouseClick(dlg.apply_suggestion_button, _left())
    assert dlg.downsample.value() == 4
    assert dlg.max_iter.value() == 1234
    assert dlg.time_limit.value() == pytest.approx(2.0)
    assert f"from plan {mine.name}" in dlg.suggestion_note.text()
    # still editable, and what the user sets is what the job gets
    dlg.max_iter.setValue(50)
    assert dlg.sections()["stopping"]["max_iter"] == 50
    assert dlg.sections()["stopping"]["time_limit_s"] == pytest.approx(7200.0)


def test_a_plan_of_another_frame_of_this_psf_is_offered_and_said_so(panel: Any) -> None:
    """A live camera's frames all differ: a plan made on the last frame was never offered
    again. It is now, after this frame's, and the note does not call it this measurement's."""
    m = panel.state["m"]
    folder = panel.suggestion_dirs[0]
    earlier = m.frame.pixels + 1  # another frame, the same PSF
    write_plan_suggestion(folder, _plan(downsample=4), input_hashes(earlier, m.psf))
    dlg = panel.new_job_dialog()
    assert dlg.suggestion_box.count() == 1
    assert "another frame, same PSF" in dlg.suggestion_box.itemText(0)
    assert dlg.suggestion_note.text() == ("1 made on another frame with this PSF: choose one "
                                          "and Apply")
    dlg.reject()
    write_plan_suggestion(folder, _plan(downsample=6), _hashes(m))
    # one made on a frame of another size (a camera ROI) is not offered: recon auto refuses it
    small = Plan(model="2d", k=1, sensor=(24, 32), field=(24, 32), region=(0, 0, 24, 32),
                 downsample=2, method="udn", iterations=9, budget_s=60.0)
    write_plan_suggestion(folder, small, input_hashes(earlier[:24, :32], m.psf))
    dlg = panel.new_job_dialog()
    assert dlg.suggestion_box.count() == 2 and "another" not in dlg.suggestion_box.itemText(0)
    assert dlg.suggestion_note.text().startswith(
        "1 for this measurement and 1 made on another frame with this PSF")
    dlg.reject()


def test_a_matching_trade_sets_channels_and_precision(panel: Any, qtbot: Any) -> None:
    m = panel.state["m"]
    folder = panel.suggestion_dirs[0] / "trade-1"
    folder.mkdir(parents=True)
    rows = [TradeRow("current frame", "udn ch16", "udn", 0.0, "float32", 1, 16, 100, 2.0,
                     None, 31.0, 0.1),
            TradeRow("current frame", "udn ch24 bf16", "udn", 0.0, "bf16", 3, 24, 300, 5.0,
                     None, 34.0, 0.1)]
    with open(folder / "trade.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0].as_dict()))
        w.writeheader()
        for r in rows:
            w.writerow(r.as_dict())
    write_trade_inputs(folder, _hashes(m))
    dlg = panel.new_job_dialog()
    assert dlg.suggestion_box.count() == 1
    assert "(trade-1)" in dlg.suggestion_box.itemText(0)
    assert dlg.channels.value() != 24
    dlg.apply_selected_suggestion()
    assert (dlg.channels.value(), dlg.precision.currentText(), dlg.downsample.value(),
            dlg.max_iter.value()) == (24, "bf16", 3, 300)
    assert dlg.sections()["network"]["channels"] == 24
    assert "from trade trade-1" in dlg.suggestion_note.text()


def test_nothing_for_this_measurement_says_so(panel: Any) -> None:
    write_plan_suggestion(panel.suggestion_dirs[0], _plan(downsample=6),
                          _hashes(_measurement(1)))
    dlg = panel.new_job_dialog()
    assert not dlg.suggestion_box.isEnabled()
    assert not dlg.apply_suggestion_button.isEnabled()
    assert dlg.suggestion_note.text().startswith("no plan or trade found for this measurement")
    assert "\n" not in dlg.suggestion_note.text()
    assert dlg.plan_button.isEnabled()  # offers to compute
    before = dlg.sections()
    dlg.apply_selected_suggestion()  # nothing to apply: nothing changes
    assert dlg.sections() == before


def test_run_planner_off_the_gui_thread_then_offer_its_plan(qtbot: Any, tmp_path: Path) -> None:
    from app.gui.jobs_panel import NewJobDialog

    m = _measurement(0)
    gui_thread = threading.get_ident()
    ran_on: list[int] = []

    def planner(cancelled: Any) -> Plan:
        ran_on.append(threading.get_ident())
        assert not cancelled()
        return _plan(downsample=3, iterations=777)

    dlg = NewJobDialog((48, 64), "test", hashes=_hashes(m), suggestion_dirs=[tmp_path],
                       run_planner=planner, save_dir=tmp_path)
    qtbot.addWidget(dlg)
    assert not dlg.suggestion_box.isEnabled()
    qtbot.mouseClick(dlg.plan_button, _left())
    qtbot.waitUntil(lambda: dlg.suggestion_box.isEnabled(), timeout=10_000)
    assert ran_on and ran_on[0] != gui_thread
    assert "plan saved as plan-" in dlg.suggestion_note.text()
    dlg.apply_selected_suggestion()
    assert (dlg.downsample.value(), dlg.max_iter.value()) == (3, 777)
    assert len(list(tmp_path.glob("plan-*.json"))) == 1


def test_closing_the_dialog_does_not_wait_for_its_planner(qtbot: Any, tmp_path: Path) -> None:
    """Closing the job dialog while *Run planner* ran held the GUI thread until the plan
    ended (its tau search: minutes at 960x1280). The dialog now closes at once and the planner
    is told to stop; it ends in the background, and its result is neither applied nor saved."""
    from app.gui.jobs_panel import NewJobDialog

    m = _measurement(0)
    started, release, finished = threading.Event(), threading.Event(), threading.Event()
    seen_cancel = threading.Event()

    def planner(cancelled: Any) -> Plan:
        started.set()
        while not release.wait(0.05):  # a plan's seconds: released 5 s after it starts
            if cancelled():  # as the tau search checks between iterations
                seen_cancel.set()
                break
        finished.set()
        return _plan(downsample=3, iterations=777)

    dlg = NewJobDialog((48, 64), "test", hashes=_hashes(m), suggestion_dirs=[tmp_path],
                       run_planner=planner, save_dir=tmp_path)
    qtbot.addWidget(dlg)
    qtbot.mouseClick(dlg.plan_button, _left())
    assert started.wait(10)
    threading.Timer(5.0, release.set).start()
    dlg.reject()  # waited for the planner before, so it had finished when this returned
    assert not finished.is_set() and not dlg.isVisible()
    assert finished.wait(4)  # it stops at its next check, before the 5 s release
    from app.gui import workers

    qtbot.waitUntil(lambda: not any(t.isRunning() for t, _ in workers._DETACHED),
                    timeout=10_000)
    assert seen_cancel.is_set()  # the planner was told to stop (a tau search took minutes)
    assert dlg.max_iter.value() != 777  # the late plan was not applied to a closed dialog
    assert not list(tmp_path.glob("plan-*.json"))  # nor saved: a search cut short


def test_the_real_planner_from_the_panel(panel: Any, qtbot: Any) -> None:
    """`Run planner` runs recon.plan.make_plan on the dark-corrected frame and saves it."""
    dlg = panel.new_job_dialog()
    qtbot.mouseClick(dlg.plan_button, _left())
    qtbot.waitUntil(lambda: dlg.suggestion_box.isEnabled(), timeout=60_000)
    (saved,) = panel.suggestion_dirs[0].glob("plan-*.json")
    plan = Plan.from_json(__import__("json").loads(saved.read_text()))
    assert plan.sensor == (48, 64)
    dlg.apply_selected_suggestion()
    assert dlg.downsample.value() == plan.downsample
    # the next dialog for the same measurement finds the plan; another measurement does not
    dlg.close()
    assert panel.new_job_dialog().suggestion_box.isEnabled()
    panel.dialog.close()
    panel.state["m"] = _measurement(2)
    assert not panel.new_job_dialog().suggestion_box.isEnabled()


@pytest.mark.filterwarnings("ignore:PSF file .* looks saturated")  # the test's binary PSF
def test_the_apps_planner_makes_the_plan_the_command_makes(panel: Any, qtbot: Any,
                                                          tmp_path: Path,
                                                          capsys: Any) -> None:
    """The app's `Run planner` called make_plan alone and kept the fixed default tau (1e-3,
    "the default TV weight"), while `lenslesscam plan` on the same frame chose tau and
    iterations from held-out pixels (1e-4, 100): two plans for one measurement."""
    import json

    from app.cli import main
    from app.gui.jobs_panel import _dark_level

    dlg = panel.new_job_dialog()
    qtbot.mouseClick(dlg.plan_button, _left())
    qtbot.waitUntil(lambda: dlg.suggestion_box.isEnabled(), timeout=60_000)
    (saved,) = panel.suggestion_dirs[0].glob("plan-*.json")
    gui = json.loads(saved.read_text())
    m = panel.state["m"]
    meas = np.clip(m.frame.pixels.astype(np.float32) - _dark_level(m), 0, None)
    np.save(tmp_path / "meas.npy", meas)
    np.save(tmp_path / "psf.npy", m.psf)
    capsys.readouterr()
    assert main(["plan", "--psf", str(tmp_path / "psf.npy"), "--meas",
                 str(tmp_path / "meas.npy"), "--json", "--no-probe"]) == 0
    cli = json.loads(capsys.readouterr().out)
    assert gui["method"] == cli["method"] == "fista-tv"
    assert "held-out" in gui["reasons"]["tau"]
    for key in ("model", "downsample", "region", "tau", "iterations"):
        assert gui[key] == pytest.approx(cli[key]), key
    dlg.close()


def test_dialog_fits_1366x768(panel: Any) -> None:
    write_plan_suggestion(panel.suggestion_dirs[0], _plan(downsample=4),
                          _hashes(panel.state["m"]))
    dlg = panel.new_job_dialog()
    dlg.apply_selected_suggestion()  # the note after Apply is one line
    hint = dlg.sizeHint()
    assert hint.width() <= 1366 and hint.height() <= 768 - 80  # room for a title bar and panel


def _left() -> Any:
    from PySide6.QtCore import Qt

    return Qt.MouseButton.LeftButton


def test_a_job_that_could_not_run_is_not_queued(panel: Any, tmp_path: Path) -> None:
    """Downsampling 64 of a 48x64 frame: the Memory line said "cannot estimate: downsampling
    by 64 leaves nothing", yet Queue job queued it (and its job.log then failed)."""
    from PySide6.QtWidgets import QDialog, QDialogButtonBox

    dlg = panel.new_job_dialog()
    ok = dlg.buttons.button(QDialogButtonBox.StandardButton.Ok)
    assert ok.isEnabled()
    dlg.downsample.setValue(64)
    assert "leaves nothing" in dlg.memory.text()
    assert not ok.isEnabled() and "leaves nothing" in ok.toolTip()
    dlg.accept()  # Enter in the dialog: refused as well
    assert dlg.result() != QDialog.DialogCode.Accepted
    jobs = tmp_path / "jobs"

    def queued() -> list[Path]:
        return [p for p in jobs.iterdir() if p.name != "suggestions"] if jobs.exists() else []

    assert queued() == []
    m = panel.state["m"]
    assert panel.create_job(m, "x", 64, dlg.sections()) is None  # the panel refuses too
    assert "cannot queue" in panel.message.text() and "leaves nothing" in panel.message.text()
    assert queued() == []
    dlg.downsample.setValue(2)
    assert ok.isEnabled() and ok.toolTip() == ""


def _udn_settings(**config: Any) -> dict[str, Any]:
    """A trade row's recorded UDN settings (recon.trade.udn_settings) with some changed."""
    from recon.trade import UDN_NOT_RECORDED
    from recon.udn import NetworkConfig, UDNConfig

    run = {k: v for k, v in UDNConfig(precision="bf16", lr=0.005,
                                      reg_noise=0.03).to_dict().items()
           if k not in UDN_NOT_RECORDED}
    run.update(config)
    net = NetworkConfig(scales=4, channels=24, skip_channels=2, input_channels=16).to_dict()
    return {"network": net, "config": run}


def test_a_trade_row_s_whole_udn_settings_reach_the_job(panel: Any, tmp_path: Path) -> None:
    """A trade row records every UDN setting it ran (udn_settings); the suggestion offered only
    channels and precision, so the job ran the default network (skip channels, input
    channels, early stop with held-out pixels) instead of the one measured."""
    from recon.udn.spec import load_spec

    m = panel.state["m"]
    folder = panel.suggestion_dirs[0] / "trade-2"
    folder.mkdir(parents=True)
    row = TradeRow("current frame", "udn ch24", "udn", 0.0, "bf16", 3, 24, 300, 5.0, None,
                   34.0, 0.1, udn_settings=_udn_settings(lr=0.5))
    write_trade_csv(folder / "trade.csv", [row], [])  # as lenslesscam trade writes it
    write_trade_inputs(folder, _hashes(m))
    dlg = panel.new_job_dialog()
    assert "recorded UDN settings" in dlg.suggestion_box.itemText(0)
    dlg.apply_selected_suggestion()
    # the settings the dialog shows are set; lr 0.5 is past its control's range: said
    held_out = dlg.holdout.value()  # the job's own early stop: not the trade's (none)
    assert (dlg.scales.value(), dlg.channels.value(), dlg.precision.currentText()) == (
        4, 24, "bf16") and held_out > 0
    assert "cannot take lr 0.5 (set to 0.1)" in dlg.suggestion_note.text()
    assert "go to the job" in dlg.suggestion_note.text()
    hint = dlg.sizeHint()
    assert hint.width() <= 1366 and hint.height() <= 768 - 80
    secs = dlg.sections()
    assert secs["network"]["skip_channels"] == 2 and secs["network"]["input_channels"] == 16
    assert secs["optimizer"]["reg_noise"] == pytest.approx(0.03)
    assert secs["optimizer"]["gain"] == "auto"
    assert secs["stopping"]["holdout"] == pytest.approx(held_out)
    job = panel.create_job(m, "t", int(dlg.downsample.value()), secs)
    assert job is not None
    spec = load_spec(job / "job.toml")
    assert (spec["network"]["skip_channels"], spec["network"]["input_channels"],
            spec["device"]["precision"]) == (2, 16, "bf16")
    assert spec["stopping"]["holdout"] == pytest.approx(held_out)
    # another suggestion replaces them: a plan without UDN settings leaves the defaults
    write_plan_suggestion(panel.suggestion_dirs[0], _plan(downsample=4), _hashes(m))
    dlg.close()
    dlg = panel.new_job_dialog()
    i = next(i for i, s in enumerate(dlg.suggestions_found) if s.source == "plan")
    dlg.apply_suggestion(dlg.suggestions_found[i])
    assert "skip_channels" not in dlg.sections()["network"]


def test_the_next_dialog_offers_the_last_jobs_settings(panel: Any, qtbot: Any,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """The new-job dialog came back with the defaults every time (seven fields to type again
    for a second tiny job, and a forgotten thread count put it on every core); values of
    the wrong kind in the remembered settings (an edited settings file) are skipped."""
    from app.gui.settings import AppSettings

    queued: list[Any] = []
    monkeypatch.setattr(panel, "create_job", lambda *a, **k: queued.append((a, k)))
    dlg = panel.new_job_dialog()
    assert dlg.max_iter.value() == 3000  # the spec's default, nothing remembered yet
    dlg.downsample.setValue(4)
    dlg.max_iter.setValue(600)
    dlg.scales.setValue(3)
    dlg.channels.setValue(8)
    dlg.threads.setValue(1)
    dlg.time_limit.setValue(0.5)
    dlg.seeds.setValue(2)
    dlg.device.setCurrentText("cpu")
    dlg.accept()
    assert len(queued) == 1 and queued[0][1]["seeds"] == 2
    dlg2 = panel.new_job_dialog()
    got = (dlg2.downsample.value(), dlg2.max_iter.value(), dlg2.scales.value(),
           dlg2.channels.value(), dlg2.threads.value(), dlg2.seeds.value(),
           dlg2.device.currentText())
    assert got == (4, 600, 3, 8, 1, 2, "cpu")
    assert dlg2.time_limit.value() == pytest.approx(0.5)
    assert "last job queued" in dlg2.suggestion_note.text()
    assert dlg2.sections() == dlg.sections()
    dlg2.close()
    # through the settings file's round trip, and a damaged entry
    s = AppSettings.from_dict({**AppSettings().to_dict(), "last_job": panel.last_job})
    assert s.last_job == panel.last_job
    panel.last_job = {"downsample": "four", "sections": {"stopping": {"max_iter": None},
                                                         "network": "x"}}
    dlg3 = panel.new_job_dialog()
    assert dlg3.downsample.value() == 2 and dlg3.max_iter.value() == 3000
    dlg3.close()


def test_a_frame_of_another_size_than_the_psf_is_refused_before_the_dialog(panel: Any) -> None:
    """The dialog said 'frame 340 (200x150, sim); PSF (150x200)', as if they differed, and a
    frame that did differ (a camera ROI) was refused only after the dialog was filled in."""
    from app.gui.jobs_panel import Measurement

    dlg = panel.new_job_dialog()
    assert dlg is not None
    said = [w.text() for w in dlg.findChildren(QLabel) if "measurement: frame" in w.text()]
    assert len(said) == 1 and "(48x64, test)" in said[0], said  # HxW, as the PSF's
    dlg.reject()
    m = panel.state["m"]
    panel.state["m"] = Measurement(_Frame(m.frame.pixels[:24, :32]), m.psf, psf_source="test")
    assert panel.new_job_dialog() is None
    msg = panel.message.text()
    assert "the frame (24x32) and the PSF (48x64) differ in size (HxW)" in msg, msg


def test_enter_in_a_box_ends_the_edit_and_queues_nothing(panel: Any, qtbot: Any) -> None:
    """Typing 20000 in Iterations and pressing Return queued the job at once (Queue job was
    the default button), with the other fields as they were; with Seeds set, up to 16 jobs."""
    from PySide6.QtCore import Qt
    from PySide6.QtWidgets import QDialog

    dlg = panel.new_job_dialog()
    dlg.show()
    qtbot.waitExposed(dlg)
    box = dlg.max_iter
    box.setFocus()
    box.lineEdit().selectAll()
    qtbot.keyClicks(box, "20000")
    qtbot.keyClick(box, Qt.Key.Key_Return)
    assert box.value() == 20000  # the edit ended
    assert dlg.isVisible() and dlg.result() != QDialog.DialogCode.Accepted
    qtbot.keyClick(dlg, Qt.Key.Key_Enter)
    assert dlg.isVisible()
    qtbot.mouseClick(dlg.ok_button, _left())  # the button queues
    assert dlg.result() == QDialog.DialogCode.Accepted
