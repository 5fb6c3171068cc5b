"""UDN jobs of the app after a hostile review: the run lock says what runs, resumes pass the
limit that stopped the run, one key per device, one launch per queued job (no Qt needed)."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from app.gui import jobs_core
from app.gui.jobs_core import (
    APP_JOB_FILE,
    LOG,
    AppJobState,
    JobQueue,
    JobView,
    job_view,
    queue_resume,
)
from recon.formats import FORMAT_VERSION


class _Handle:
    """A launched job process as the queue sees it (pid, poll), without a process."""

    next_pid = 10_000_000

    def __init__(self) -> None:
        _Handle.next_pid += 1
        self.pid = _Handle.next_pid

    def poll(self) -> int | None:
        return None  # still running: the job is 'starting'


class _Spawner:
    """Records what the queue launches."""

    def __init__(self) -> None:
        self.launched: list[tuple[str, list[str]]] = []

    def __call__(self, args: list[str], folder: Path, env: dict[str, str], log: Any) -> _Handle:
        self.launched.append((folder.name, list(args)))
        return _Handle()


@pytest.fixture(autouse=True)
def _no_fake_children() -> Iterator[None]:
    yield
    for pid, proc in list(jobs_core._CHILDREN.items()):
        if isinstance(proc, _Handle):
            del jobs_core._CHILDREN[pid]


def _gone_pid() -> int:
    """The pid of a process that has ended."""
    p = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                       capture_output=True, text=True, check=True)
    return int(p.stdout)


def _entry(job: Path, **fields: Any) -> None:
    job.mkdir(parents=True, exist_ok=True)
    entry = {"format": "lenslesscam.app_job", "format_version": 1, "name": job.name,
             "device": "cpu", "state": "queued", "action": "run", "launches": [], **fields}
    (job / APP_JOB_FILE).write_text(json.dumps(entry))


def _record(job: Path, *, checkpoint: bool = True, **fields: Any) -> Path:
    """A run record (run.json) of the job's run, ``fields`` over a finished, completed run."""
    run = job / "run"
    run.mkdir(parents=True, exist_ok=True)
    rec: dict[str, Any] = {
        "format": "lenslesscam.udn_run", "format_version": FORMAT_VERSION,
        "status": "finished", "finish_reason": "completed",
        "detail": "reached the iteration limit", "pid": _gone_pid(), "host": platform.node(),
        "spec": {"job": {"name": job.name},
                 "stopping": {"max_iter": 100, "time_limit_s": None}},
        "progress": {"iteration": 100, "max_iter": 100, "elapsed_s": 4.0},
        "sessions": [{"started_utc": "2001-01-01T00:00:00+00:00"}],
        "results": {}, **fields}
    if checkpoint:
        rec.setdefault("checkpoint", {"iteration": rec["progress"]["iteration"]})
        (run / "checkpoint.pt").write_bytes(b"a checkpoint")
    (run / "run.json").write_text(json.dumps(rec))
    return run


def _launched(job: Path, *launches: dict[str, Any], **fields: Any) -> None:
    _entry(job, state="launched", launches=[
        {"action": "run", "pid": _gone_pid(), "utc": "2000-01-01T00:00:00+00:00"},
        *launches], **fields)


def test_a_stale_pid_shows_interrupted_and_the_queue_moves_on(tmp_path):
    """run.json 'running' with the pid of an unrelated live process (a reboot, a pid reused)
    showed a dead job running for ever, Resume off, Cancel saying the process is gone, and a
    new job queued for ever behind it (device busy): the run lock decides."""
    from recon.udn.jobs import job_status
    from recon.udn.rundir import RunLock

    stale, nxt = tmp_path / "a-stale", tmp_path / "b-next"
    _launched(stale)
    run = _record(stale, status="running", finish_reason=None, detail=None,
                  pid=os.getpid(),  # alive, and not the run's
                  progress={"iteration": 40, "max_iter": 100, "elapsed_s": 2.0})
    _entry(nxt)
    v = job_view(stale)
    assert v is not None and v.state is AppJobState.INTERRUPTED
    assert v.can_resume and not v.state.cancellable
    assert job_status(run).state == "interrupted"  # `jobs status` says so too
    spawn = _Spawner()
    JobQueue(tmp_path, spawn=spawn).poll()
    assert [name for name, _ in spawn.launched] == ["b-next"]
    # a process that holds the run's lock runs it, whatever pid the record names
    with RunLock(run):
        v = job_view(stale)
        assert v is not None and v.state is AppJobState.RUNNING and v.pid == os.getpid()


def test_a_run_stopped_at_its_time_limit_resumes_with_more_time(tmp_path):
    """Resume passed only --max-iter (twice the limit it had not reached); the CLI refused
    ('pass a larger --time-limit') and the finished job then read 'failed to start'."""
    job = tmp_path / "tl"
    _launched(job)
    _record(job, detail="reached the wall-time limit; the held-out error was still improving",
            spec={"stopping": {"max_iter": 100000, "time_limit_s": 18.0}},
            progress={"iteration": 50, "max_iter": 100000, "elapsed_s": 18.2},
            results={"still_improving": True, "limit_reached": "time_limit"})
    v = job_view(job)
    assert v is not None and v.can_resume
    assert v.resume_max_iter is None and v.resume_time_limit_s == 37.0  # 2 x 18.2, rounded up
    queue_resume(job, max_iter=v.resume_max_iter)  # what the panel's Resume does
    spawn = _Spawner()
    JobQueue(tmp_path, spawn=spawn).poll()
    (_, args), = spawn.launched
    assert args[:2] == ["jobs", "resume"] and "--max-iter" not in args
    assert float(args[args.index("--time-limit") + 1]) == 37.0
    # a record from before limit_reached: the detail names the limit
    _launched(job)
    _record(job, detail="reached the wall-time limit; the held-out error was still improving",
            spec={"stopping": {"max_iter": 100000, "time_limit_s": 18.0}},
            progress={"iteration": 50, "max_iter": 100000, "elapsed_s": 18.2},
            results={"still_improving": True})
    assert job_view(job).resume_time_limit_s == 37.0


def test_a_refused_resume_leaves_a_finished_job_finished_and_says_why(tmp_path):
    """The completed job's row read 'failed to start', its detail the last log lines: the
    previous run's JSON summary among them."""
    job = tmp_path / "r"
    _launched(job, {"action": "resume", "pid": _gone_pid(), "utc": "2999-01-01T00:00:00+00:00"})
    _record(job, results={"still_improving": True, "limit_reached": "max_iter"})
    (job / LOG).write_text(
        "--- 2000-01-01T00:00:00+00:00 run\n{\"finish_reason\": \"completed\"}\n"
        "--- 2999-01-01T00:00:00+00:00 resume\n"
        "lenslesscam jobs: error: the run has used 40 s: pass a larger --time-limit\n")
    v = job_view(job)
    assert v is not None and v.state is AppJobState.FINISHED and v.finish_reason == "completed"
    assert v.detail is not None and v.detail.startswith("the resume did not start: ")
    assert "pass a larger --time-limit" in v.detail and "finish_reason" not in v.detail
    assert "best" not in v.results and v.can_resume  # it may be tried again


def test_a_run_failed_before_its_first_checkpoint_can_be_resumed(tmp_path):
    """A full disk before the first checkpoint advised 'jobs resume', which starts again from
    iteration 0, but the app's Resume stayed off (it wanted checkpoint.pt)."""
    job = tmp_path / "full"
    _launched(job)
    _record(job, checkpoint=False, finish_reason="failed",
            detail="DiskFull: disk full: ...; no checkpoint had been written yet; free some "
                   "space, then 'lenslesscam jobs resume RUN'",
            progress={"iteration": 7, "max_iter": 100, "elapsed_s": 1.0})
    v = job_view(job)
    assert v is not None and v.finish_reason == "failed" and v.can_resume
    # a run whose spec was refused never ran: jobs resume refuses it, and so does the app
    _record(job, checkpoint=False, finish_reason="failed", spec=None, detail="SpecError: x")
    assert not job_view(job).can_resume


def test_auto_cuda_and_cuda0_are_one_device_for_the_queue(tmp_path, monkeypatch):
    """'auto' (stored as 'cuda') and 'cuda:0' were two keys: two jobs ran at once on one GPU."""
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert jobs_core.resolve_device_name("auto") == "cuda:0"
    for name, device in (("a", "cuda"), ("b", "cuda:0"), ("c", "auto"), ("d", "cpu")):
        _entry(tmp_path / name, device=device)
    spawn = _Spawner()
    queue = JobQueue(tmp_path, spawn=spawn)
    queue.poll()
    assert [name for name, _ in spawn.launched] == ["a", "d"]
    queue.poll()  # 'a' is starting on cuda:0: the others wait
    assert [name for name, _ in spawn.launched] == ["a", "d"]


def test_the_bar_counts_time_for_a_time_limited_run_and_is_full_when_done(tmp_path):
    """A time-limited job read 1 % throughout and after it completed."""
    from recon.udn.rundir import RunLock

    job = tmp_path / "t"
    _launched(job)
    run = _record(job, status="running", finish_reason=None, detail=None, pid=os.getpid(),
                  spec={"stopping": {"max_iter": 100000, "time_limit_s": 10.0}},
                  progress={"iteration": 50, "max_iter": 100000, "elapsed_s": 5.0})
    with RunLock(run):
        v = job_view(job)
        assert v is not None and v.state is AppJobState.RUNNING
        assert v.fraction == pytest.approx(0.5)
    _record(job, detail="reached the wall-time limit",
            spec={"stopping": {"max_iter": 100000, "time_limit_s": 10.0}},
            progress={"iteration": 100, "max_iter": 100000, "elapsed_s": 10.01})
    v = job_view(job)
    assert v is not None and v.state is AppJobState.FINISHED and v.fraction == 1.0


def test_combine_in_a_worker_thread_uses_the_thread_policy(tmp_path, monkeypatch):
    """The app's 'Average the seeds and FISTA-TV' ran at torch's default thread count (30-67 s
    against 1.7 s for the CLI under load): the policy of `lenslesscam jobs combine` applies."""
    import torch

    import recon.threads
    import recon.udn.ensemble
    from recon.threads import ThreadChoice

    seen: list[int] = []
    monkeypatch.setattr(recon.threads, "choose_threads", lambda requested=None, **kw:
                        ThreadChoice(threads=1, cores=2, load=0.0, source="auto"))
    monkeypatch.setattr(recon.udn.ensemble, "combine_runs",
                        lambda runs, out, with_fista=False: seen.append(torch.get_num_threads()))
    views = [JobView(folder=tmp_path / "j", name="j", device="cpu",
                     state=AppJobState.FINISHED, results={"best": tmp_path / "best.tif"})]
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        worker = threading.Thread(  # as the panel's combine worker runs it
            target=lambda: jobs_core.combine_jobs(views, tmp_path, with_fista=True))
        worker.start()
        worker.join()
        assert seen == [1]
        assert torch.get_num_threads() == 2  # given back
    finally:
        torch.set_num_threads(before)


def test_with_fista_skipped_by_a_cancel_is_said_in_the_detail(tmp_path):
    """Cancel during the FISTA-TV at the end: 'completed' without with_fista.tif, the reason
    only in run.json."""
    job = tmp_path / "wf"
    _launched(job)
    note = "with_fista.tif not written: cancelled during FISTA-TV"
    _record(job, results={"with_fista_note": note})
    v = job_view(job)
    assert v is not None and v.finish_reason == "completed"
    assert v.detail == f"reached the iteration limit; {note}"


def test_a_withdrawn_job_can_be_queued_again(tmp_path):
    """A job cancelled while queued could be neither queued again nor removed."""
    job = tmp_path / "w"
    _entry(job, state="withdrawn")
    v = job_view(job)
    assert v is not None and v.state is AppJobState.WITHDRAWN and v.can_resume
    queue_resume(job, max_iter=v.resume_max_iter)
    assert job_view(job).state is AppJobState.QUEUED
    spawn = _Spawner()
    JobQueue(tmp_path, spawn=spawn).poll()
    (_, args), = spawn.launched
    assert args[:2] == ["jobs", "run"]  # its run never began: run, not resume


def test_two_windows_launch_a_queued_job_once(tmp_path, monkeypatch):
    """Two windows on one jobs folder both read a job queued and both launched it."""
    _entry(tmp_path / "q")
    spawn_a, spawn_b = _Spawner(), _Spawner()
    a, b = JobQueue(tmp_path, spawn=spawn_a), JobQueue(tmp_path, spawn=spawn_b)
    real = jobs_core.discover_jobs
    calls = {"n": 0}

    def discover_then_other_window_polls(jobs_dir: Any) -> Any:
        views = real(jobs_dir)
        calls["n"] += 1
        if calls["n"] == 1:  # window a has read the job queued; window b polls now
            b.poll()
        return views

    monkeypatch.setattr(jobs_core, "discover_jobs", discover_then_other_window_polls)
    a.poll()
    assert len(spawn_a.launched) + len(spawn_b.launched) == 1
    entry = json.loads((tmp_path / "q" / APP_JOB_FILE).read_text())
    assert entry["state"] == "launched" and len(entry["launches"]) == 1


def test_the_panel_says_a_withdrawn_job_is_queued_again(tmp_path, qtbot):
    """The panel's message for Resume of a withdrawn job said "resume of w queued" (nothing
    resumed: it runs from the start), and a resume with more time named no time."""
    from app.gui.jobs_panel import JobsPanel

    _entry(tmp_path / "w", state="withdrawn")
    spawn = _Spawner()
    panel = JobsPanel(tmp_path, lambda: None, poll_ms=60_000, spawn=spawn)
    qtbot.addWidget(panel)
    try:
        panel.refresh()
        panel.table.selectRow(0)
        panel.resume_selected()
        assert "w queued again (it was withdrawn before it ran)" in panel.message.text()
        (_, args), = spawn.launched  # queued, then launched to run from the start
        assert args[:2] == ["jobs", "run"]
    finally:
        panel.stop()
