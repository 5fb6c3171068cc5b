"""UDN jobs from the GUI: launched as separate processes, survive the window, found again."""

from __future__ import annotations

import contextlib
import json
import os
import re
from collections.abc import Iterator
from typing import Any

import pytest

pytestmark = pytest.mark.gui


@pytest.fixture
def jobs_window(make_window: Any, job_server: Any) -> Any:
    """:func:`make_window` whose jobs start through the fork server (conftest's
    ``job_server``): each job is a real process that does not import torch again."""

    def make(*args: Any, **kwargs: Any) -> Any:
        return make_window(*args, job_spawn=job_server.spawn, **kwargs)

    return make


@pytest.fixture(autouse=True)
def _reap_jobs() -> Iterator[None]:
    """Terminate and reap every job process the test started (a test hook kept out of the
    app: the app itself leaves jobs running when it closes)."""
    yield
    import subprocess

    from app.gui import jobs_core

    for pid, proc in list(jobs_core._CHILDREN.items()):
        if proc.poll() is None:
            proc.terminate()
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(20)
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        jobs_core._CHILDREN.pop(pid, None)


def _tiny(dlg: Any, iters: int) -> None:
    dlg.name.setText("tiny")
    dlg.downsample.setValue(4)
    dlg.scales.setValue(3)
    dlg.channels.setValue(8)
    dlg.max_iter.setValue(iters)
    dlg.device.setCurrentText("cpu")
    dlg.threads.setValue(1)
    dlg.checkpoint_every.setValue(10)
    dlg.preview_every.setValue(10)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_job_survives_closing_the_window_and_is_found_again(jobs_window: Any,
                                                            qtbot: Any) -> None:
    from app.gui.settings import AppSettings

    # no point source, 10 frames/s: a smaller workload
    w = jobs_window(AppSettings(connect_light=False, frame_rate_hz=10.0))
    qtbot.waitUntil(lambda: w.frames_shown >= 2, timeout=20_000)
    dlg = w.jobs_panel.new_job_dialog()
    _tiny(dlg, 1_000_000)
    dlg.accept()
    panel = w.jobs_panel
    qtbot.waitUntil(lambda: panel.views and panel.views[0].state == "running"
                    and panel.views[0].iteration > 0, timeout=30_000)
    pid = panel.views[0].pid
    assert pid is not None
    w.close()
    assert _alive(pid)

    w2 = jobs_window(autoconnect=False)  # the jobs panel needs no devices
    p2 = w2.jobs_panel
    qtbot.waitUntil(lambda: p2.views and p2.views[0].state == "running", timeout=10_000)
    it0 = p2.views[0].iteration
    qtbot.waitUntil(lambda: p2.views[0].iteration > it0, timeout=15_000)
    p2.table.selectRow(0)
    p2.cancel_button.click()
    qtbot.waitUntil(lambda: p2.views[0].state == "finished", timeout=20_000)
    assert p2.views[0].finish_reason == "cancelled"
    stopped_at = p2.views[0].iteration
    # resume continues from the last checkpoint in a new process
    qtbot.waitUntil(lambda: p2.resume_button.isEnabled(), timeout=5_000)
    p2.resume_button.click()
    qtbot.waitUntil(lambda: p2.views[0].state == "running"
                    and p2.views[0].iteration > stopped_at, timeout=30_000)
    assert p2.views[0].pid != pid
    p2.cancel_button.click()
    qtbot.waitUntil(lambda: p2.views[0].state == "finished", timeout=20_000)


def test_jobs_from_the_gui_complete_open_and_combine(jobs_window: Any, qtbot: Any) -> None:
    """Seeds 2 queues two tiny jobs (seeds 0, 1, one after another): each completes, its result
    opens with its metadata, and Combine averages them."""
    import numpy as np

    from app.gui.settings import AppSettings
    from recon.io import read_reconstruction

    w = jobs_window(AppSettings(connect_light=False, frame_rate_hz=10.0))
    qtbot.waitUntil(lambda: w.frames_shown >= 2, timeout=20_000)
    panel = w.jobs_panel
    dlg = panel.new_job_dialog()
    assert dlg is not None
    _tiny(dlg, 10)
    assert "about" in dlg.memory.text() and "available" in dlg.memory.text()
    dlg.seeds.setValue(2)
    dlg.accept()
    qtbot.waitUntil(lambda: len(panel.views) == 2, timeout=5_000)
    assert sorted(v.name for v in panel.views) == ["tiny-s0", "tiny-s1"]
    assert len(panel.selected_all()) == 2  # the new jobs are selected ...
    if not all(v.state == "finished" for v in panel.views):
        assert not panel.combine_button.isEnabled()  # ... and not all have finished yet
    qtbot.waitUntil(lambda: all(v.state == "finished" for v in panel.views), timeout=90_000)
    panel.refresh()
    assert len(panel.selected_all()) == 2  # the selection survives the polling
    for v in panel.views:
        assert v.finish_reason == "completed" and v.iteration == 10
        assert set(v.results) == {"best", "final", "with_fista"}  # 10 < average_every

    # one job: its curves, its preview, its result with the metadata
    panel._select_folders({panel.views[0].folder})
    qtbot.waitUntil(lambda: panel.open_button.isEnabled(), timeout=5_000)
    assert len(panel.loss_curve.getData()[0]) == 10
    assert panel.preview.image is not None
    dlg2 = panel.open_selected()
    assert dlg2 is not None
    assert dlg2.panels["best"].image.shape == (37, 50)
    # the best estimate is labelled with its own iteration, not the run's (it said "10 it")
    best_it = dlg2.meta["best"]["best_iteration"]
    assert dlg2.panels["best"].title.text() == f"<b>best (it {best_it} of 10)</b>"
    assert dlg2.panels["final"].title.text() == "<b>final (10 it)</b>"
    assert dlg2.meta["final"]["method"] == "udn"
    text = dlg2.metadata.toPlainText()
    assert "[best]" in text and "[final]" in text and "method: udn" in text
    # one finished job alone cannot be averaged (only with FISTA-TV); the core refuses it too
    assert not panel.combine_action.isEnabled() and panel.combine_fista_action.isEnabled()
    panel.combine_selected()
    assert "cannot combine: an ensemble needs at least two runs" in panel.message.text()
    # a job without previews shows none, not the one shown before (another job's)
    import shutil

    first, other = panel.views[0], panel.views[1]
    assert panel.preview.footer.text().startswith(f"{first.name}: iter_")
    shutil.rmtree(other.run_dir / "previews")
    panel.refresh()
    panel._select_folders({other.folder})
    qtbot.waitUntil(lambda: panel.preview.image is None, timeout=5_000)
    assert panel.preview.footer.text().startswith(f"{other.name}: preview iter_")
    import json

    rec = json.loads((other.run_dir / "run.json").read_text())
    rec["progress"]["last_preview"] = None  # a run that has written none
    (other.run_dir / "run.json").write_text(json.dumps(rec))
    panel.refresh()
    qtbot.waitUntil(lambda: panel.preview.footer.text() == f"{other.name}: no preview yet",
                    timeout=5_000)
    assert panel.preview.image is None

    panel._select_folders({v.folder for v in panel.views})
    qtbot.waitUntil(lambda: panel.combine_action.isEnabled(), timeout=5_000)
    panel.combine_action.trigger()  # the button opens the menu of the two ways to combine
    qtbot.waitUntil(lambda: "combining" not in panel.message.text(), timeout=30_000)
    msg = panel.message.text()
    assert "ensemble of 2 jobs (best estimates) written to" in msg, msg
    out = sorted((panel.queue.jobs_dir / "ensembles").glob("*.tif"))
    assert len(out) == 1
    x, meta = read_reconstruction(out[0])
    assert sorted(m["seed"] for m in meta["members"]) == [0, 1]
    bests = [read_reconstruction(v.run_dir / "best.tif")[0] for v in panel.views]
    np.testing.assert_allclose(x, np.mean(bests, axis=0), rtol=1e-6, atol=1e-7)
    assert len(panel.views) == 2  # the ensembles folder is not taken for a job


def test_job_dialog_defaults_come_from_the_spec(live_window: Any, tmp_path: Any) -> None:
    from recon.udn.spec import SCHEMA

    dlg = live_window.jobs_panel.new_job_dialog()
    assert dlg is not None
    dlg.show()
    # (GUI review) a second click brings the open dialog forward (two could queue two jobs)
    assert live_window.jobs_panel.new_job_dialog() is dlg
    assert dlg.max_iter.value() == SCHEMA["stopping"]["max_iter"].default
    assert dlg.channels.value() == SCHEMA["network"]["channels"].default
    assert dlg.scales.value() == SCHEMA["network"]["scales"].default
    assert dlg.lr.value() == pytest.approx(SCHEMA["optimizer"]["lr"].default, rel=1e-3)
    assert dlg.headroom.value() == pytest.approx(SCHEMA["optimizer"]["headroom"].default,
                                                 abs=0.005)
    assert dlg.patience.value() == SCHEMA["stopping"]["patience"].default
    assert dlg.with_fista.isChecked() is SCHEMA["output"]["with_fista"].default is True
    # the one default of its own: a live frame is the full sensor (docs/app.md says so)
    assert dlg.downsample.value() == 2 != SCHEMA["data"]["downsample"].default
    # a typed value out of range becomes the nearest bound, not the value typed on the way
    # there (0.9 into the 0-0.5 held-out box left 0: no held-out stop), and a time limit
    # takes thousandths of an hour (0.004 h became "none")
    from PySide6.QtCore import Qt
    from PySide6.QtTest import QTest

    # and in any notation: '1e-5' lost its 'e' and '-' and became 15, clamped to 1.0; a TV
    # weight of 1e-7 became 0 (six decimals)
    for box, typed, want in ((dlg.holdout, "0.9", 0.5), (dlg.lr, "0.000005", 1e-5),
                             (dlg.time_limit, "0.004", 0.004), (dlg.patience, "0", 1),
                             (dlg.tv_weight, "1e-5", 1e-5), (dlg.tv_weight, "2.5e-7", 2.5e-7),
                             (dlg.lr, "1e-3", 1e-3), (dlg.holdout, "5e-2", 0.05),
                             # to the box's decimals, as shown (4e-4 was kept as 0.0004
                             # while "0.000" showed); 1e-5 h is "none"
                             (dlg.holdout, "4e-4", 0.0), (dlg.time_limit, "1e-5", 0.0),
                             # whole-number boxes: '1e4' became 14, '2.5' 25
                             (dlg.max_iter, "1e4", 10_000), (dlg.patience, "2.5", 3),
                             # beyond any integer: the nearest bound ('1e30' became 1)
                             (dlg.max_iter, "1e30", dlg.max_iter.maximum()),
                             (dlg.max_iter, "-1e30", dlg.max_iter.minimum())):
        box.lineEdit().selectAll()
        QTest.keyClicks(box.lineEdit(), typed)
        QTest.keyClick(box.lineEdit(), Qt.Key.Key_Return)
        assert box.value() == pytest.approx(want), (typed, box.value())
    from recon.threads import MAX_THREADS_PER_CORE, machine_state

    # a thread count the job would refuse (more than 4 per core) is not offered
    assert dlg.threads.maximum() == MAX_THREADS_PER_CORE * machine_state()[0]
    dlg.lr.setValue(0.002)
    dlg.headroom.setValue(1.5)
    dlg.holdout.setValue(0.1)
    secs = dlg.sections()
    assert secs["optimizer"]["lr"] == pytest.approx(0.002)
    assert secs["optimizer"]["headroom"] == pytest.approx(1.5)
    assert secs["stopping"]["holdout"] == pytest.approx(0.1)
    from recon.udn.spec import normalise_spec

    for name in ("p.npy", "m.npy"):
        (tmp_path / name).write_bytes(b"")
    spec = normalise_spec({"data": {"psf": "p.npy", "measurement": "m.npy"}, **secs},
                          base_dir=tmp_path)  # the dialog's sections are a valid job spec
    assert spec["optimizer"]["headroom"] == pytest.approx(1.5)
    assert spec["output"]["with_fista"] is True
    dlg.with_fista.setChecked(False)
    assert dlg.sections()["output"]["with_fista"] is False
    dlg.reject()


def test_one_damaged_job_file_does_not_hide_the_others(tmp_path):
    """A launch entry with a pid that is not a number made discover_jobs raise, so the panel
    showed nothing and no job was launched again."""
    import json

    from app.gui.jobs_core import APP_JOB_FILE, AppJobState, discover_jobs

    for name, entry in (("a-bad", {"format": "lenslesscam.app_job", "name": "bad",
                                   "state": "running", "launches": [{"pid": "abc"}]}),
                        ("b-good", {"format": "lenslesscam.app_job", "name": "good",
                                    "state": "queued"})):
        (tmp_path / name).mkdir()
        (tmp_path / name / APP_JOB_FILE).write_text(json.dumps(entry))
    bad, good = discover_jobs(tmp_path)
    assert bad.state is AppJobState.FAILED_TO_START and "unreadable" in (bad.detail or "")
    assert good.name == "good" and good.state is AppJobState.QUEUED


def test_cancelling_a_queued_resume_leaves_the_run_as_it_was(tmp_path, capsys):
    """Cancel on a resume waiting in the queue marked the whole job withdrawn: no results,
    no resume, although its checkpoint and results were on disk."""
    from app.gui.jobs_core import AppJobState, cancel_job, job_view

    job = _finished_app_job(tmp_path, capsys, {
        "name": "b", "state": "queued", "action": "resume", "max_iter": 10,
        "launches": [{"action": "run", "pid": 1}]})
    assert "queued resume is withdrawn" in cancel_job(job)
    v = job_view(job)
    assert v is not None and v.state is not AppJobState.WITHDRAWN
    assert v.finish_reason == "completed" and "best" in v.results


def _sleeper() -> Any:
    """A process that stands for a job process still starting (importing, reading)."""
    import subprocess
    import sys

    return subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])


def test_cancel_stops_a_job_that_is_still_starting(tmp_path):
    """Cancel on a job shown 'starting' said 'no UDN run here (run.json not found)' and the
    job then ran in full: now its process is stopped and the job shows cancelled."""
    import json

    from app.gui.jobs_core import APP_JOB_FILE, AppJobState, JobQueue, cancel_job, job_view

    procs = []

    def spawn(args, folder, env, log):
        procs.append(_sleeper())
        return procs[-1]

    job = tmp_path / "a"
    job.mkdir()
    (job / APP_JOB_FILE).write_text(json.dumps({
        "format": "lenslesscam.app_job", "format_version": 1, "name": "a", "device": "cpu",
        "state": "queued", "action": "run"}))
    JobQueue(tmp_path, spawn=spawn).poll()
    assert job_view(job).state is AppJobState.STARTING
    msg = cancel_job(job)
    assert "cancelled while starting" in msg, msg
    assert procs[0].wait(timeout=10) != 0  # stopped by the SIGTERM
    v = job_view(job)
    assert v.state is AppJobState.WITHDRAWN and "cancelled while starting" in v.detail
    assert not v.state.cancellable


def test_cancel_stops_a_resume_that_is_still_starting(tmp_path, capsys):
    """Cancel on a resume shown 'starting' said 'the run is not running (finish reason
    cancelled)' and the resume then ran: now it is stopped and the run is as it was."""
    from app.gui.jobs_core import AppJobState, cancel_job, job_view

    proc = _sleeper()
    try:
        job = _finished_app_job(tmp_path, capsys, {
            "name": "b", "state": "launched", "action": "run",
            "launches": [{"action": "run", "pid": 1, "utc": "2000-01-01T00:00:00+00:00"},
                         {"action": "resume", "pid": proc.pid, "max_iter": 10,
                          "utc": "2999-01-01T00:00:00+00:00"}]})
        v = job_view(job)
        assert v.state is AppJobState.STARTING
        assert "cancelled while starting" in cancel_job(job)
        assert proc.wait(timeout=10) != 0
        v = job_view(job)
        assert v.state is AppJobState.FINISHED and v.finish_reason == "completed"
        assert "cancelled while starting" in v.detail and "best" in v.results
    finally:
        proc.kill()
        proc.wait()


def test_settings_with_a_bad_version_or_an_unknown_scene_start_with_defaults(tmp_path):
    """A format_version that is not a number stopped the app from starting; a saved scene
    that does not exist left the simulated camera unable to connect."""
    import json

    from app.gui.settings import SETTINGS_FORMAT, AppSettings, load_settings

    p = tmp_path / "app-settings.json"
    p.write_text(json.dumps({"format": SETTINGS_FORMAT, "format_version": "x",
                             "gain": 3.0}))
    assert load_settings(p) == AppSettings()
    assert (tmp_path / "app-settings.json.bad").exists()  # set aside, as docs/app.md says
    p.write_text(json.dumps({"format": SETTINGS_FORMAT, "format_version": 1,
                             "sim_scene": "nonexistent", "gain": 3.0}))
    s = load_settings(p)
    assert s.sim_scene == AppSettings().sim_scene and s.gain == 3.0


def test_a_newer_or_foreign_settings_file_is_kept_not_overwritten(tmp_path):
    """A settings file from a newer release (or without 'format') was read as defaults and
    overwritten with them at exit; deeply nested JSON stopped the app starting."""
    import json

    from app.gui.settings import SETTINGS_FORMAT, AppSettings, load_settings, save_settings

    p = tmp_path / "app-settings.json"
    newer = {"format": SETTINGS_FORMAT, "format_version": 2, "gain": 2.0, "new_feature": 1}
    p.write_text(json.dumps(newer))
    assert load_settings(p) == AppSettings()
    save_settings(AppSettings(), p)  # what the app does at exit
    assert json.loads((tmp_path / "app-settings.json.v2").read_text()) == newer
    p.write_text(json.dumps({"gain": 3.0}))  # no format
    assert load_settings(p) == AppSettings()
    assert json.loads((tmp_path / "app-settings.json.bad").read_text()) == {"gain": 3.0}
    p.write_text("[" * 100000 + "]" * 100000)
    assert load_settings(p) == AppSettings()


def test_a_run_that_ended_still_improving_can_be_resumed_with_more_iterations(tmp_path, capsys):
    """Its detail line said 'jobs resume ... --max-iter N', but the app's Resume was off for
    completed runs."""
    import json

    from app.gui.jobs_core import APP_JOB_FILE, job_view, queue_resume

    job = _finished_app_job(tmp_path, capsys, {
        "name": "c", "state": "launched", "launches": [{"action": "run", "pid": 1}]})
    rec = json.loads((job / "run" / "run.json").read_text())
    for improving in (False, True):
        rec["results"]["still_improving"] = improving
        (job / "run" / "run.json").write_text(json.dumps(rec))
        v = job_view(job)
        assert v is not None and v.finish_reason == "completed"
        assert v.can_resume is improving
    assert v.resume_max_iter == 6
    queue_resume(job, max_iter=v.resume_max_iter)
    assert json.loads((job / APP_JOB_FILE).read_text())["max_iter"] == 6
    # waiting for its turn it says so, with the new limit (it said "reached the iteration
    # limit" at 100 %)
    v = job_view(job)
    assert v is not None and v.detail == "resuming from iteration 3 to 6"
    assert v.max_iter == 6 and v.fraction == 0.5 and v.finish_reason is None


def _finished_app_job(tmp_path: Any, capsys: Any, entry: dict[str, Any],
                      args: tuple[str, ...] = ()) -> Any:
    """An app job folder whose run finished (3 iterations of a tiny network), ``entry`` its
    app-job.json; ``args``: more ``recon udn`` options (``--seed``, ``--truth``)."""
    import json

    import numpy as np

    from app.cli import main
    from app.gui.jobs_core import APP_JOB_FILE
    from recon.simulate import synthetic_psf

    np.save(tmp_path / "psf.npy", synthetic_psf((24, 28), seed=0))
    np.save(tmp_path / "meas.npy", np.random.default_rng(0).random((24, 28)).astype(np.float32))
    job = tmp_path / "jobs" / str(entry["name"])
    assert main(["recon", "udn", "--psf", str(tmp_path / "psf.npy"), "--meas",
                 str(tmp_path / "meas.npy"), "--iters", "3", "--scales", "2",
                 "--net-channels", "4", "--input-channels", "4", "--threads", "1", "--quiet",
                 "--out", str(job / "run"), *args]) == 0
    capsys.readouterr()
    (job / APP_JOB_FILE).write_text(json.dumps({"format": "lenslesscam.app_job", **entry}))
    return job


def test_combine_with_fista_takes_one_job_and_runs_off_the_gui_thread(tmp_path, capsys,
                                                                      qtbot):
    """Combine offers 'Average the seeds' (two or more finished jobs) and 'Average the seeds
    and FISTA-TV' (one is enough), run on a worker thread: FISTA-TV's automatic tau takes
    seconds to a minute. Before, the app had only the plain average, on the GUI thread."""
    import numpy as np

    from app.gui.jobs_panel import JobsPanel
    from recon.io import read_reconstruction

    np.save(tmp_path / "truth.npy", np.random.default_rng(1).random((24, 28)).astype(np.float32))
    entry = {"state": "launched", "launches": [{"action": "run", "pid": 1}]}
    a = _finished_app_job(tmp_path, capsys, {"name": "a", **entry},
                          ("--truth", str(tmp_path / "truth.npy")))
    b = _finished_app_job(tmp_path, capsys, {"name": "b", **entry}, ("--seed", "1"))
    panel = JobsPanel(a.parent, lambda: None, poll_ms=60_000)
    qtbot.addWidget(panel)
    try:
        panel._select_folders({a})
        assert [v.folder for v in panel.selected_all()] == [a]
        assert panel.combine_fista_action.isEnabled() and panel.combine_button.isEnabled()
        assert not panel.combine_action.isEnabled()
        assert "iterate means (mean.tif" in panel.combine_fista_action.toolTip()
        panel.combine_fista_action.trigger()
        # the trigger returned before the result: the work is on the combine queue
        assert "combining 1 job (FISTA-TV)" in panel.message.text(), panel.message.text()
        panel.combine_fista_action.trigger()  # a second one meanwhile is refused, said so
        assert "still running" in panel.message.text(), panel.message.text()
        qtbot.waitUntil(lambda: "written to" in panel.message.text()
                        or "cannot combine:" in panel.message.text(), timeout=60_000)
        msg = panel.message.text()
        assert "ensemble of 1 job (best estimates) and FISTA-TV (tau " in msg, msg
        assert "dB against the truth" in msg, msg
        # the run was shorter than average_every: its best estimate, and the message says why
        assert "not the iterate means" in msg and "fewer than its average_every 500" in msg
        out = sorted((a.parent / "ensembles").glob("*.tif"))
        assert [p.name.endswith("-x1+fista.tif") for p in out] == [True], out
        assert str(out[0]) in msg
        x, meta = read_reconstruction(out[0])
        assert meta["method"] == "udn-ensemble+fista-tv"
        assert meta["fista"]["weight"] == 0.5 and meta["fista"]["tau"] > 0
        assert [m["seed"] for m in meta["members"]] == [0]
        best_a = read_reconstruction(a / "run" / "best.tif")[0]
        assert not np.allclose(x, best_a, atol=1e-3 * float(np.abs(best_a).max()))

        panel._select_folders({a, b})
        assert panel.combine_action.isEnabled() and panel.combine_fista_action.isEnabled()
        panel.combine_action.trigger()
        assert "combining 2 jobs" in panel.message.text()
        qtbot.waitUntil(lambda: "combining" not in panel.message.text(), timeout=60_000)
        msg = panel.message.text()
        assert "ensemble of 2 jobs (best estimates) written to" in msg, msg
        x2, meta2 = read_reconstruction(sorted((a.parent / "ensembles").glob("*-x2.tif"))[0])
        assert meta2["method"] == "udn-ensemble" and "fista" not in meta2
        assert sorted(m["seed"] for m in meta2["members"]) == [0, 1]
        best_b = read_reconstruction(b / "run" / "best.tif")[0]
        np.testing.assert_allclose(x2, (best_a + best_b) / 2, rtol=1e-6, atol=1e-7)
    finally:
        panel.stop()
    assert panel._combine_queue is None  # shut down with the panel


def test_a_refused_resume_shows_why(tmp_path, capsys):
    """A refused resume leaves run.json as it was, so the panel went on showing the run
    'finished'; the refusal was only in the job's log."""
    import json
    import subprocess
    import sys

    from app.gui.jobs_core import APP_JOB_FILE, LOG, AppJobState, job_view

    job = _finished_app_job(tmp_path, capsys, {
        "name": "d", "state": "launched", "launches": [{"action": "run", "pid": 1}]})
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    entry = json.loads((job / APP_JOB_FILE).read_text())
    (job / LOG).write_text("lenslesscam jobs: error: estimated 1.2 GiB is above max_memory\n")
    for when, refused in (("2000-01-01T00:00:00+00:00", False),
                          ("2999-01-01T00:00:00+00:00", True)):
        launch = {"action": "resume", "pid": int(gone.stdout), "utc": when}
        (job / APP_JOB_FILE).write_text(json.dumps({**entry, "launches": [
            *entry["launches"], launch]}))
        v = job_view(job)
        # the finished run stays finished (a refused resume relabelled it "failed to start");
        # the refusal is in its detail
        assert v is not None and v.state is AppJobState.FINISHED, when
        assert ("the resume did not start" in (v.detail or "")) is refused, when
    assert "max_memory" in v.detail


def test_a_damaged_newer_or_unknown_queued_job_is_never_started(tmp_path):
    """A queued job whose app-job.json had 'launches' as text was started again every second
    (the launch was recorded after it and failed), and blanked the jobs table; a job of a
    newer release, or with a state this version does not know, was started."""
    import json
    import subprocess
    import sys

    from app.gui.jobs_core import APP_JOB_FILE, AppJobState, JobQueue, job_view

    spawned: list[str] = []

    def spawn(args, folder, env, log):
        spawned.append(folder.name)
        return subprocess.Popen([sys.executable, "-c", "pass"])

    base = {"format": "lenslesscam.app_job", "format_version": 1, "device": "cpu",
            "state": "queued", "action": "run"}
    jobs = {"a-text-launches": {"launches": "abc"}, "b-bad-max-iter": {"max_iter": "abc"},
            "c-newer": {"format_version": 2}, "d-unknown-state": {"state": "archived"},
            "e-good": {}}
    for name, change in jobs.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / APP_JOB_FILE).write_text(json.dumps({**base, "name": name,
                                                                **change}))
    queue = JobQueue(tmp_path, spawn=spawn)
    for _ in range(3):
        views = {v.folder.name: v for v in queue.poll()}
    assert spawned == ["e-good"], spawned
    assert len(views) == 5  # every job listed
    for name in ("a-text-launches", "b-bad-max-iter"):
        v = job_view(tmp_path / name)
        assert v is not None and v.state is AppJobState.FAILED_TO_START, name
        assert "is damaged" in (v.detail or ""), name
    assert "newer lenslesscam" in (job_view(tmp_path / "c-newer").detail or "")
    assert job_view(tmp_path / "d-unknown-state").state is AppJobState.HELD


def test_an_integral_float_format_version_is_that_version(tmp_path):
    """"format_version": 1.0 (some JSON writers put 1 so) was discarded as "not a number" and
    the file set aside as .bad."""
    import json

    from app.gui.settings import SETTINGS_FORMAT, AppSettings, load_settings

    p = tmp_path / "app-settings.json"
    p.write_text(json.dumps({"format": SETTINGS_FORMAT, "format_version": 1.0, "gain": 3.0}))
    assert load_settings(p).gain == 3.0
    assert p.exists() and not (tmp_path / "app-settings.json.bad").exists()
    p.write_text(json.dumps({"format": SETTINGS_FORMAT, "format_version": 1.5, "gain": 3.0}))
    assert load_settings(p) == AppSettings()
    assert (tmp_path / "app-settings.json.bad").exists()
    p.write_text(json.dumps({"format": SETTINGS_FORMAT, "format_version": 2.0, "gain": 3.0}))
    assert load_settings(p) == AppSettings()  # a newer version: kept aside, as for 2
    assert (tmp_path / "app-settings.json.v2").exists()


def test_a_jobs_folder_that_cannot_hold_jobs_is_named(tmp_path):
    from app.gui.jobs_core import create_job, jobs_dir_problem

    afile = tmp_path / "afile"
    afile.write_text("i am a file")
    assert "is a file, not a folder" in jobs_dir_problem(afile)
    inside = jobs_dir_problem(afile / "jobs")
    assert "cannot hold jobs" in inside and "is a file, not a folder" in inside
    assert jobs_dir_problem("/proc/lenslesscam-jobs") is not None  # root too: probed, not asked
    assert jobs_dir_problem(tmp_path) is None
    assert jobs_dir_problem(tmp_path / "new" / "jobs") is None  # made when the first job comes
    import numpy as np

    with pytest.raises(ValueError, match="leaves nothing"):
        create_job(tmp_path / "jobs", "x", np.ones((48, 64)), np.ones((48, 64)), downsample=64)
    assert not (tmp_path / "jobs").exists()


def test_a_jobs_folder_inside_a_run_folder_is_named_and_gets_nothing(tmp_path):
    """A run's folder holds only its run's files: a job written into it (inputs, job.toml,
    the app's entry) was refused only later, by ``jobs run``, after the files were there."""
    import numpy as np

    tiny_run = tmp_path / "run"
    tiny_run.mkdir()
    (tiny_run / "run.json").write_text(json.dumps({"format": "lenslesscam.udn_run",
                                                   "format_version": 1, "status": "finished"}))

    from app.gui.jobs_core import create_job, jobs_dir_problem

    before = sorted(p.relative_to(tiny_run) for p in tiny_run.rglob("*"))
    said = jobs_dir_problem(tiny_run / "jobs")
    assert said is not None and "inside the UDN run folder" in said and "\n" not in said
    with pytest.raises(ValueError, match="inside the UDN run folder"):
        create_job(tiny_run / "jobs", "x", np.ones((48, 64)), np.ones((48, 64)))
    assert sorted(p.relative_to(tiny_run) for p in tiny_run.rglob("*")) == before


def test_the_result_window_shows_the_iterate_mean_with_its_count(qtbot: Any,
                                                                  tmp_path: Any) -> None:
    """A finished run opens with four panels of one width: its average with FISTA-TV
    (with_fista.tif, the default's last step) labelled with the estimate (tau below), best,
    the mean (mean.tif) labelled with how many estimates it averages and how often, and
    final."""
    import numpy as np

    from app.gui.jobs_core import AppJobState, JobView
    from app.gui.jobs_panel import ResultDialog
    from recon.udn.jobs import run_job
    from tests.udn.conftest import tiny_problem, write_spec

    d = tmp_path / "data"
    d.mkdir()
    psf, sim = tiny_problem()
    for name, a in (("psf", psf), ("meas", sim.meas), ("mask", sim.mask), ("truth", sim.truth)):
        np.save(d / f"{name}.npy", a)
    spec = write_spec(d, stopping={"max_iter": 12, "patience": 1000},
                      output={"average_every": 4, "with_fista": True},
                      device={"threads": 1, "device": "cpu"})
    rd = tmp_path / "run"
    run_job(spec, rd)
    rec = json.loads((rd / "run.json").read_text())
    assert rec["results"]["mean"] == "mean.tif" and rec["results"]["mean_count"] == 3
    view = JobView(folder=tmp_path, name="tiny", device="cpu", state=AppJobState.FINISHED,
                   results={w: rd / f"{w}.tif" for w in ("best", "final", "mean", "with_fista")})
    dlg = ResultDialog(view)
    qtbot.addWidget(dlg)
    dlg.show()
    qtbot.waitExposed(dlg)
    assert list(dlg.panels) == ["with_fista", "best", "mean", "final"]
    tau = dlg.meta["with_fista"]["fista"]["tau"]
    assert dlg.panels["with_fista"].title.text() == "<b>mean + FISTA-TV</b>"
    assert f"FISTA-TV tau {tau:.3g}" in dlg.panels["with_fista"].footer.text()
    assert dlg.panels["mean"].title.text() == "<b>mean of 3 (every 4)</b>"
    # the same width each (a longer title made its panel wider)
    widths = {p.width() for p in dlg.panels.values()}
    assert max(widths) - min(widths) <= 2, widths
    assert dlg.meta["mean"]["estimate"] == "mean"
    # (GUI review) within the screen: 1100 px wide ran off a 1024 px screen
    avail = dlg.screen().availableGeometry()
    assert dlg.width() <= avail.width(), (dlg.width(), avail.width())


def test_the_jobs_strip_shows_five_jobs_and_one_line_of_details(qtbot: Any,
                                                                  tmp_path: Any) -> None:
    """In the strip the main window gives the panel at 1366x768 (220 px), five jobs and the
    selected one's details fit: rows a line of text high, the details one line (state,
    memory; the folder is their tooltip). They showed three rows before."""
    panel = _strip_panel(tmp_path, qtbot, [f"job-s{i}" for i in range(5)])
    qtbot.waitUntil(lambda: panel.table.rowCount() == 5, timeout=5_000)
    panel._select_folders({panel.views[0].folder})
    qtbot.waitUntil(lambda: panel.details.text().startswith("state: held"), timeout=5_000)
    assert "\n" not in panel.details.text() and "memory (peak to expect)" in panel.details.text()
    assert panel.details.toolTip() == str(panel.views[0].folder)
    t = panel.table
    last = t.rowViewportPosition(4) + t.rowHeight(4)
    assert last <= t.viewport().height(), (last, t.viewport().height())
    panel.stop()


def _long_loss_file(run: Any, rows: int) -> None:
    """Make the run's loss.csv ``rows`` rows long, in its own format (as a long run's)."""
    from recon.csvmeta import format_table
    from recon.udn.jobs import _CSV_FIELDS, FORMAT_VERSION, LOSS_FORMAT, read_loss_rows

    first = read_loss_rows(run)[0]
    table = [{**first, "iteration": str(i + 1), "loss": f"{1.0 / (i + 1):.6g}"}
             for i in range(rows)]
    (run / "loss.csv").write_text(format_table(LOSS_FORMAT, FORMAT_VERSION, [], _CSV_FIELDS,
                                               table))


def test_a_long_loss_curve_is_read_off_the_gui_thread_and_only_when_it_changed(
        tmp_path, capsys, qtbot, monkeypatch):
    """The selected job's loss.csv was parsed on the GUI thread at every poll: 200k rows
    froze the window 2-3 s each second. A short one is still read at once."""
    import threading

    from app.gui import jobs_panel as jp

    job = _finished_app_job(tmp_path, capsys, {
        "name": "a", "state": "launched", "launches": [{"action": "run", "pid": 1}]})
    threads: list[str] = []
    real = jp.read_loss

    def spy(folder):
        threads.append(threading.current_thread().name)
        return real(folder)

    monkeypatch.setattr(jp, "read_loss", spy)
    panel = jp.JobsPanel(job.parent, lambda: None, poll_ms=60_000)
    qtbot.addWidget(panel)
    try:
        panel._select_folders({job})
        assert threads == [threading.main_thread().name]  # short: read inline, shown at once
        assert len(panel.loss_curve.getData()[0]) == 3
        panel.refresh()
        assert len(threads) == 1  # unchanged: not read again
        _long_loss_file(job / "run", 20_000)
        assert (job / "run" / "loss.csv").stat().st_size > panel.LOSS_READ_INLINE_BYTES
        panel.refresh()
        qtbot.waitUntil(lambda: len(panel.loss_curve.getData()[0]) == 20_000, timeout=20_000)
        assert len(threads) == 2 and threads[1] != threading.main_thread().name
        panel.refresh()
        panel.refresh()
        assert len(threads) == 2  # read once for that file
    finally:
        panel.stop()


def test_the_message_is_one_line_stamped_and_goes_with_its_jobs_change(tmp_path, qtbot):
    """A 776-character combine message took four lines (the table kept 2.5 rows), and
    'queued …' stayed through the whole run; a click dismisses a message."""
    from PySide6.QtCore import Qt

    from app.gui.jobs_core import APP_JOB_FILE

    panel = _strip_panel(tmp_path, qtbot, ["j"])
    job = panel.views[0].folder
    try:
        h0 = panel.table.height()
        long = "ensemble written to " + "/very/long/path" * 50
        panel.message.setText(long)
        qtbot.wait(50)
        assert panel.message.isVisible() and panel.message.toolTip().endswith(long)
        assert re.match(r"\d\d:\d\d:\d\d  ensemble", panel.message.text())
        assert panel.message.height() < 2 * panel.message.fontMetrics().height()
        assert panel.table.height() >= h0 - 2 * panel.message.fontMetrics().height()
        qtbot.mouseClick(panel.message, Qt.MouseButton.LeftButton)
        assert not panel.message.isVisible() and panel.message.text() == ""
        panel.message.setText("queued j", about=job)
        panel.refresh()
        panel.refresh()
        assert "queued j" in panel.message.text()  # the job is as it was
        entry = json.loads((job / APP_JOB_FILE).read_text())
        (job / APP_JOB_FILE).write_text(json.dumps({**entry, "state": "withdrawn"}))
        panel.refresh()
        assert panel.message.text() == "" and not panel.message.isVisible()
    finally:
        panel.stop()


def test_the_newest_job_selected_at_start_is_in_view(tmp_path, qtbot):
    """With more jobs than the strip shows, the newest one, selected at start, was half
    hidden below the table's edge."""
    panel = _strip_panel(tmp_path, qtbot, [f"job-{i}" for i in range(9)])
    try:
        t = panel.table
        qtbot.waitUntil(lambda: t.rowCount() == 9, timeout=5_000)
        assert [v.name for v in panel.selected_all()] == ["job-8"]

        def shown() -> bool:
            y = t.rowViewportPosition(8)
            return y >= 0 and y + t.rowHeight(8) <= t.viewport().height()

        qtbot.waitUntil(shown, timeout=5_000)
        panel.resize(1366, 150)  # the window made shorter (to the screen): still in view
        qtbot.waitUntil(lambda: t.viewport().height() < 100, timeout=5_000)
        qtbot.waitUntil(shown, timeout=5_000)
        # scrolled away by the user: a message that comes and goes leaves the table where it is
        t.scrollToTop()
        qtbot.wait(50)
        top = t.verticalScrollBar().value()
        panel.message.setText("a message")
        qtbot.wait(100)
        panel.message.setText("")
        qtbot.wait(100)
        assert t.verticalScrollBar().value() == top and not shown()
    finally:
        panel.stop()


def _strip_panel(tmp_path: Any, qtbot: Any, names: list[str]) -> Any:
    """A jobs panel as the main window's strip holds it at 1366x768 (220 px), with a held job
    per name, created in that order."""
    import numpy as np

    from app.gui.jobs_core import create_job
    from app.gui.jobs_panel import JobsPanel

    rng = np.random.default_rng(0)
    for name in names:
        create_job(tmp_path / "jobs", name, rng.random((30, 40)), rng.random((30, 40)),
                   queue=False)
    panel = JobsPanel(tmp_path / "jobs", lambda: None, poll_ms=60_000)
    qtbot.addWidget(panel)
    panel.resize(1366, 220)
    panel.show()
    return panel
