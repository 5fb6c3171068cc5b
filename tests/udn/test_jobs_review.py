"""UDN run folders after a hostile review: the lock says whether a run is alive, a probe of
it never refuses a writer, a run whose folder was deleted stops without making it again."""

from __future__ import annotations

import fcntl
import json
import os
import platform
import shutil
import subprocess
import sys

import pytest

from recon.formats import FORMAT_VERSION
from recon.udn import rundir
from recon.udn.jobs import JobError, format_status, job_status, run_job
from recon.udn.rundir import RunLock, lock_is_held
from tests.udn.conftest import write_spec


def _running_record(run, pid: int) -> None:
    run.mkdir(parents=True, exist_ok=True)
    (run / "run.json").write_text(json.dumps({
        "format": "lenslesscam.udn_run", "format_version": FORMAT_VERSION,
        "status": "running", "pid": pid, "host": platform.node(),
        "progress": {"iteration": 12, "max_iter": 100}}))


def test_jobs_status_asks_the_lock_not_a_pid_that_may_be_reused(tmp_path):
    """A run.json 'running' whose pid is another live process's (after a reboot) read
    'running (pid N)' for ever."""
    run = tmp_path / "run"
    _running_record(run, os.getpid())  # alive, but no one holds the run's lock
    st = job_status(run)
    assert st.state == "interrupted" and "jobs resume" in format_status(st)
    with RunLock(run):  # a process working on the run: running, with the holder's pid
        gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                              capture_output=True, text=True, check=True)
        _running_record(run, int(gone.stdout))  # the record's pid is a dead one
        st = job_status(run)
        assert st.state == "running" and st.pid == os.getpid()


def test_a_status_probe_does_not_refuse_a_writer_that_starts_then(tmp_path, monkeypatch):
    """A probe (jobs status, the app's poll) holds the lock for an instant; a writer that
    tried just then read the dead holder's line left in run.lock and was refused."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "run.lock").write_text("pid 4242 on bench since then\n")  # a crashed holder's line
    probe = os.open(run / "run.lock", os.O_RDONLY)
    fcntl.flock(probe, fcntl.LOCK_SH)  # the probe, caught holding it
    real_sleep = rundir.time.sleep

    def probe_ends(dt: float) -> None:
        fcntl.flock(probe, fcntl.LOCK_UN)
        real_sleep(dt)

    monkeypatch.setattr(rundir.time, "sleep", probe_ends)
    try:
        lock = RunLock(run).acquire()  # not refused
        assert lock.held and lock_is_held(run)
        lock.release()
    finally:
        os.close(probe)


@pytest.mark.parametrize("how", ["deleted", "moved"])
def test_a_run_whose_folder_is_removed_stops_and_makes_nothing_again(tiny_data, tmp_path, how):
    """Deleting a running job's folder left a run no one saw, which made JOB/run/ again with
    its next write (atomic writes make parent folders)."""
    out = tmp_path / "job" / "run"
    spec = write_spec(tiny_data, stopping={"max_iter": 400},
                      output={"checkpoint_every": 5, "preview_every": 5,
                              "status_seconds": 0.0})
    seen: list[int] = []

    def remove(step) -> None:
        seen.append(step.iteration)
        if step.iteration == 3:
            if how == "deleted":
                shutil.rmtree(out.parent)
            else:
                out.parent.rename(tmp_path / "elsewhere")

    with pytest.raises(JobError, match="deleted or moved while the run wrote it"):
        run_job(spec, out, progress=remove)
    assert seen == [1, 2, 3]  # it stopped at its first write after
    assert not out.exists() and not out.parent.exists()
    if how == "moved":  # the moved folder is left as it was at the move
        moved = json.loads((tmp_path / "elsewhere" / "run" / "run.json").read_text())
        assert moved["status"] == "running"
