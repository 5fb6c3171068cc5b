"""Run folders under faults (issue 15): the lock, verified checkpoints with a fallback, a lost
checkpoint, a full disk, temporary files of killed writes, damaged records and specs."""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from app.cli import main as cli_main
from recon.atomic import atomic_write
from recon.formats import FormatError
from recon.udn import jobs as jobs_mod
from recon.udn import rundir
from recon.udn.jobs import (
    DiskFull,
    FinishReason,
    JobState,
    RunFolderBusy,
    job_status,
    load_checkpoint,
    read_loss_rows,
    read_record,
    resume_job,
    run_job,
)
from recon.udn.rundir import RESERVE_BYTES, RunLock, load_latest_checkpoint
from tests.udn.conftest import write_spec
from tests.udn.jobrunner import JobServer

SMALL = {"stopping": {"max_iter": 8}, "output": {"checkpoint_every": 4, "preview_every": 4}}


def record(run_dir: Path) -> dict:
    return json.loads((run_dir / "run.json").read_text())


def one_line_error(argv: list[str], capsys) -> str:
    rc = cli_main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = [ln for ln in err.strip().splitlines() if "note:" not in ln]
    assert len(lines) == 1, err  # one line, no traceback
    return lines[0]


def small_run(tiny_data: Path, out: Path, **sections) -> None:
    spec = write_spec(tiny_data, **{**SMALL, **sections})
    assert run_job(spec, out).finish_reason == FinishReason.COMPLETED


def temp_names(out: Path) -> list[str]:
    return [p.name for p in [*out.iterdir(), *(out / "previews").iterdir()]
            if p.name.startswith(".") and ".tmp" in p.name]


def wait_for(cond, what: str, timeout: float = 90.0) -> None:
    t0 = time.monotonic()
    while not cond():
        assert time.monotonic() - t0 < timeout, f"timed out waiting for {what}"
        time.sleep(0.02)


# --------------------------------------------------------------------------------------------
# The lock
# --------------------------------------------------------------------------------------------


def test_the_lock_refuses_a_second_writer_in_one_process(tiny_data, tmp_path):
    out = tmp_path / "run"
    with RunLock(out):
        with pytest.raises(RunFolderBusy, match=f"pid {os.getpid()}"):
            RunLock(out).acquire()
        with pytest.raises(RunFolderBusy, match="in use"):
            run_job(write_spec(tiny_data, **SMALL), out)
        assert not (out / "run.json").exists()  # refused before writing anything
        assert (out / "run.lock").stat().st_size == RESERVE_BYTES  # the disk-full reserve
    with RunLock(out):
        pass  # free again
    assert (out / "run.lock").stat().st_size == 0


def test_a_refused_writer_waits_for_the_holder_line(tmp_path, monkeypatch):
    """The holder writes its line just after taking the lock; a process refused in between
    waits for that line instead of naming no one (a race seen in CI), and takes the lock if
    the holder was releasing it."""
    import fcntl

    import recon.udn.rundir as rundir

    out = tmp_path / "run"
    out.mkdir()
    fd = os.open(out / "run.lock", os.O_RDWR | os.O_CREAT)
    fcntl.flock(fd, fcntl.LOCK_EX)  # locked, nothing written yet
    monkeypatch.setattr(rundir, "HOLDER_WAIT_S", 60.0)  # never the limit on a loaded machine
    monkeypatch.setattr(rundir, "PROBE_GRACE_S", 0.0)  # the polls counted are the wait's own
    real_sleep = rundir.time.sleep
    polls = {"n": 0}

    def holder_writes_late(dt):  # the holder writes its line during the third poll
        polls["n"] += 1
        if polls["n"] == 3:
            os.pwrite(fd, b"pid 4242 on bench since now\n", 0)
        real_sleep(dt)

    monkeypatch.setattr(rundir.time, "sleep", holder_writes_late)
    try:
        with pytest.raises(RunFolderBusy, match=r"in use \(pid 4242 on bench"):
            RunLock(out).acquire()
        assert polls["n"] == 3
        os.ftruncate(fd, 0)  # a holder that never writes: named generically, after the wait
        monkeypatch.setattr(rundir, "HOLDER_WAIT_S", 0.05)
        monkeypatch.setattr(rundir.time, "sleep", real_sleep)
        with pytest.raises(RunFolderBusy, match=r"in use \(another process\)"):
            RunLock(out).acquire()

        def holder_releases(dt):  # releasing: the file is empty, then the lock is free
            fcntl.flock(fd, fcntl.LOCK_UN)
            real_sleep(dt)

        monkeypatch.setattr(rundir, "HOLDER_WAIT_S", 60.0)
        monkeypatch.setattr(rundir.time, "sleep", holder_releases)
        lock = RunLock(out).acquire()  # taken once free, not refused
        assert lock.held
        lock.release()
    finally:
        os.close(fd)


def test_two_resumes_at_once_one_runs_the_other_refuses(tiny_data, tmp_path):
    out = tmp_path / "run"
    small_run(tiny_data, out)
    marks = tmp_path / "marks"
    marks.mkdir()
    with JobServer(tmp_path / "logs") as srv:
        started = []
        for name in ("a", "b"):  # whoever gets the folder stalls after iteration 10
            env = {"LENSLESSCAM_TEST_STALL_AT": "10", "LENSLESSCAM_TEST_MARK": str(marks / name)}
            started.append((name, *srv.start(["jobs", "resume", out, "--max-iter", "20",
                                              "--quiet"], env)))
        wait_for(lambda: any((marks / n).exists() for n, _, _ in started), "a resume to run")
        (holder, hpid, _), = [s for s in started if (marks / s[0]).exists()]
        (_, opid, olog), = [s for s in started if s[0] != holder]
        assert srv.wait(opid, timeout=90) == 2  # the other one refused and ended
        lines = olog.read_text().strip().splitlines()
        assert len(lines) == 1, lines
        assert f"{out} is in use (pid {hpid} on" in lines[0]
        assert job_status(out).state == JobState.RUNNING
        assert srv.kill(hpid) == -9
    # the kernel released the lock of the killed process: the run can be resumed
    with RunLock(out):
        pass
    assert cli_main(["jobs", "resume", str(out), "--max-iter", "20", "--quiet"]) == 0
    rec = record(out)
    # the run, the killed resume, the last resume; the refused one left no trace
    assert len(rec["sessions"]) == 3 and rec["resumes"] == 2
    assert rec["sessions"][1]["pid"] == hpid and rec["sessions"][2]["start_iteration"] == 8


# --------------------------------------------------------------------------------------------
# Checkpoints: verified, the previous one kept, a fallback, a loss that needs --restart
# --------------------------------------------------------------------------------------------


def test_truncated_checkpoint_falls_back_to_the_previous_one(tiny_data, tmp_path, capsys):
    out = tmp_path / "run"
    small_run(tiny_data, out)  # checkpoints at 4 and 8
    assert load_checkpoint(out / "checkpoint.prev.pt")["iteration"] == 4
    hashes = json.loads((out / "checkpoints.json").read_text())
    assert [e["iteration"] for e in hashes["checkpoints"]][:2] == [8, 4]
    data = (out / "checkpoint.pt").read_bytes()
    (out / "checkpoint.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(FormatError) as info:
        load_checkpoint(out / "checkpoint.pt")
    assert "truncated or corrupt checkpoint" in str(info.value)
    assert "\n" not in str(info.value)  # never again a multi-line PytorchStreamReader error
    rc = cli_main(["jobs", "resume", str(out), "--max-iter", "10", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert ("note: resumed from checkpoint.prev.pt (iteration 4) because checkpoint.pt does "
            "not match its recorded hash") in err
    rec = record(out)
    assert rec["sessions"][-1]["start_iteration"] == 4
    assert rec["sessions"][-1]["resumed_from"]["path"] == "checkpoint.prev.pt"
    assert rec["sessions"][-1]["resumed_from"]["verified"] is True
    assert any("resumed from checkpoint.prev.pt" in n for n in rec["notes"])
    # the note travels on in the checkpoints of the resumed run
    assert any("checkpoint.prev.pt" in n for n in
               load_checkpoint(out / "checkpoint.pt")["state"]["notes"])


def _as_newer(out: Path, name: str) -> None:
    """Rewrite checkpoint ``name`` as a newer release would: format_version 5, its hash and
    size recorded in checkpoints.json."""
    import hashlib

    import torch

    ck = torch.load(out / name, map_location="cpu", weights_only=True)
    old_sha = hashlib.sha256((out / name).read_bytes()).hexdigest()
    ck["format_version"] = 5
    torch.save(ck, out / name)
    new_sha = hashlib.sha256((out / name).read_bytes()).hexdigest()
    hashes = json.loads((out / "checkpoints.json").read_text())
    for e in hashes["checkpoints"]:
        if e["sha256"] == old_sha:
            e["sha256"] = new_sha
    (out / "checkpoints.json").write_text(json.dumps(hashes))


@pytest.mark.parametrize("names", [("checkpoint.pt",), ("checkpoint.pt", "checkpoint.prev.pt")])
def test_a_newer_releases_checkpoint_is_refused_never_passed_over(tiny_data, tmp_path, capsys,
                                                                 names):
    """A checkpoint of a newer format version was taken for a damaged one: the resume went on
    from the previous checkpoint and overwrote the newer one; with both newer it advised
    --restart, which overwrote both."""
    out = tmp_path / "run"
    small_run(tiny_data, out)
    for name in names:
        _as_newer(out, name)
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    for extra in ([], ["--restart"]):
        line = one_line_error(["jobs", "resume", out, "--max-iter", "12", *extra], capsys)
        assert "checkpoint version 5 was written by a newer lenslesscam" in line, line
        assert "--restart" not in line and "resume the run with that release" in line
        assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before


def test_a_newer_checkpoints_json_is_refused_not_rewritten(tiny_data, tmp_path, capsys):
    out = tmp_path / "run"
    small_run(tiny_data, out)
    hashes = json.loads((out / "checkpoints.json").read_text())
    hashes["format_version"] = 4
    (out / "checkpoints.json").write_text(json.dumps(hashes))
    before = (out / "checkpoints.json").read_bytes()
    line = one_line_error(["jobs", "resume", out, "--max-iter", "12"], capsys)
    assert "checkpoints.json: format_version 4 was written by a newer lenslesscam" in line
    assert (out / "checkpoints.json").read_bytes() == before


def test_a_corrupt_byte_is_caught_by_the_hash(tiny_data, tmp_path):
    out = tmp_path / "run"
    small_run(tiny_data, out)
    data = bytearray((out / "checkpoint.pt").read_bytes())
    data[len(data) // 3] ^= 0xFF  # one flipped byte that torch may not notice
    (out / "checkpoint.pt").write_bytes(bytes(data))
    ck, info, problems = load_latest_checkpoint(out)
    assert ck is not None and info["path"] == "checkpoint.prev.pt" and ck["iteration"] == 4
    assert problems and "checkpoint.pt" in problems[0]


def test_a_checkpoint_that_reads_back_wrong_is_refused(tiny_data, tmp_path, monkeypatch):
    write = rundir._write_bytes

    def flip(fh, data):  # the second checkpoint reaches the disk with one byte changed
        flip.n += 1
        write(fh, data if flip.n < 2 else data[:100] + bytes([data[100] ^ 1]) + data[101:])

    flip.n = 0
    monkeypatch.setattr(rundir, "_write_bytes", flip)
    out = tmp_path / "run"
    with pytest.raises(jobs_mod.CheckpointError, match="differ from those written"):
        run_job(write_spec(tiny_data, **SMALL), out)
    rec = record(out)
    assert rec["finish_reason"] == "failed" and rec["error"]["type"] == "CheckpointError"
    assert "last good checkpoint (iteration 4) is kept" in rec["error"]["message"]
    assert load_checkpoint(out / "checkpoint.pt")["iteration"] == 4
    assert temp_names(out) == []


def test_a_deleted_checkpoint_needs_restart(tiny_data, tmp_path, capsys):
    out = tmp_path / "run"
    small_run(tiny_data, out)
    (out / "checkpoint.pt").unlink()
    (out / "checkpoint.prev.pt").unlink()
    before = record(out)
    line = one_line_error(["jobs", "resume", out, "--max-iter", "10"], capsys)
    assert "no usable checkpoint (checkpoint.pt is missing)" in line
    assert "reached iteration 8" in line and "--restart" in line
    assert record(out) == before  # a refusal leaves the record as it was
    rc = cli_main(["jobs", "resume", str(out), "--max-iter", "10", "--restart", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "note: restarted from iteration 0 (--restart)" in err
    rec = record(out)
    assert rec["sessions"][-1]["start_iteration"] == 0 and rec["progress"]["iteration"] == 10
    assert any(n.startswith("restarted from iteration 0 (--restart)") for n in rec["notes"])
    assert len(read_loss_rows(out)) == 10  # no old ones


def test_a_run_stopped_before_its_first_checkpoint_says_it_started_again(tiny_data, tmp_path):
    out = tmp_path / "run"
    small_run(tiny_data, out)
    for name in ("checkpoint.pt", "checkpoint.prev.pt", "checkpoints.json"):
        (out / name).unlink()
    rec = record(out)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    del rec["checkpoint"]  # as if killed at iteration 3, before its first checkpoint
    rec.update(status="running", finish_reason=None, pid=dead.pid)
    rec["progress"]["iteration"] = 3
    (out / "run.json").write_text(json.dumps(rec))
    seen = []
    outcome = resume_job(out, notice=seen.append)
    assert outcome.iterations == 8
    note = ("resumed without a checkpoint (none was written before the run stopped at "
            "iteration 3): started again from iteration 0")
    assert seen == [note]
    rec = record(out)
    assert note in rec["notes"]  # kept in the record, not overwritten by the runner's notes
    assert rec["sessions"][-1]["notes"] == [note]


# --------------------------------------------------------------------------------------------
# A full disk
# --------------------------------------------------------------------------------------------


class FullDisk:
    """Writes in the run folder fail with ENOSPC once ``full``; freeing the lock's reserve
    makes room again (as on a real disk)."""

    def __init__(self, monkeypatch, run_dir: Path) -> None:
        self.full = False
        self.run_dir = run_dir
        self.freed = 0
        real_write = jobs_mod.atomic_write_json
        real_bytes = jobs_mod.atomic_write_bytes
        real_release = RunLock.release_reserve

        def guard(path) -> None:
            if self.full:
                # an interrupted write leaves its temporary file to be removed by the writer
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

        def write_json(path, obj):
            guard(path)
            return real_write(path, obj)

        def write_bytes(path, data):
            guard(path)
            return real_bytes(path, data)

        def png(path, chw):
            if self.full:
                atomic_write(path, lambda p: (p.write_bytes(b"\0" * 10), guard(path)))
            return real_png(path, chw)

        def release(lock):
            self.freed += 1
            self.full = False
            real_release(lock)

        real_png = jobs_mod._write_png
        monkeypatch.setattr(jobs_mod, "atomic_write_json", write_json)
        monkeypatch.setattr(jobs_mod, "atomic_write_bytes", write_bytes)
        monkeypatch.setattr(jobs_mod, "_write_png", png)
        monkeypatch.setattr(RunLock, "release_reserve", release)


def test_disk_full_names_the_folder_and_the_record_says_failed(tiny_data, tmp_path,
                                                                monkeypatch, capsys):
    out = tmp_path / "run"
    disk = FullDisk(monkeypatch, out)
    spec = write_spec(tiny_data, stopping={"max_iter": 30},
                      output={"checkpoint_every": 4, "preview_every": 6,
                              "status_seconds": 3600.0})

    def fill(step):  # the disk fills up after iteration 5: the preview of 6 fails mid-write
        if step.iteration == 5:
            disk.full = True
            assert (out / "run.lock").stat().st_size == RESERVE_BYTES

    with pytest.raises(DiskFull) as info:
        run_job(spec, out, progress=fill)
    msg = str(info.value)
    assert "\n" not in msg
    assert msg.startswith(f"disk full: no space left on the device of {out} while writing "
                          "iter_0000006.png; ")
    assert "the last good checkpoint (iteration 4) is kept" in msg and "jobs resume" in msg
    assert disk.freed >= 1  # the reserve made room for the record
    rec = record(out)
    assert rec["status"] == JobState.FINISHED and rec["finish_reason"] == FinishReason.FAILED
    assert rec["error"] == {"type": "DiskFull", "message": msg}
    assert rec["checkpoint"]["iteration"] == 4
    assert temp_names(out) == []  # no partial file left
    assert not (out / "previews" / "iter_0000006.png").exists()
    # with space again the run continues from the last good checkpoint
    monkeypatch.undo()
    assert cli_main(["jobs", "resume", str(out), "--quiet"]) == 0
    assert record(out)["sessions"][-1]["start_iteration"] == 4
    capsys.readouterr()


def test_disk_full_in_the_cli_is_one_line(tiny_data, tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    disk = FullDisk(monkeypatch, out)
    disk.full = True  # full from the start: even job.toml cannot be written
    line = one_line_error(["jobs", "run", write_spec(tiny_data, **SMALL), "--out", out], capsys)
    assert f"disk full: no space left on the device of {out} while writing job.toml" in line
    assert record(out)["error"]["type"] == "DiskFull"


# --------------------------------------------------------------------------------------------
# Leftovers of killed writes; damaged records and specs
# --------------------------------------------------------------------------------------------


def test_a_resume_refused_before_its_first_iteration_leaves_the_run_as_it_was(
        tiny_data, tmp_path, capsys, monkeypatch):
    """A resume refused at start-up (memory limit, a device this machine lacks, a loss.csv it
    cannot read) wrote loss.csv with no rows and marked the completed run failed, with the
    refused --max-iter saved in its spec."""
    out = tmp_path / "run"
    small_run(tiny_data, out)
    before = {name: (out / name).read_bytes() for name in ("run.json", "loss.csv")}
    assert len(read_loss_rows(out)) == 8
    line = one_line_error(["jobs", "resume", out, "--max-iter", "100", "--max-memory", "1KB"],
                          capsys)
    assert "max_memory" in line, line
    assert {n: (out / n).read_bytes() for n in before} == before
    # a run begun on a GPU, resumed on a machine without one
    rec = record(out)
    rec["spec"]["device"]["device"] = "cuda:7"
    (out / "run.json").write_text(json.dumps(rec))
    gpu = {n: (out / n).read_bytes() for n in before}
    line = one_line_error(["jobs", "resume", out, "--max-iter", "100"], capsys)
    assert "cuda" in line, line
    assert {n: (out / n).read_bytes() for n in before} == gpu
    (out / "run.json").write_bytes(before["run.json"])
    # a damaged loss.csv: the resume names the line and changes nothing
    damaged = before["loss.csv"].replace(b"\n5,", b"\nfive,", 1)
    assert damaged != before["loss.csv"]
    (out / "loss.csv").write_bytes(damaged)
    line = one_line_error(["jobs", "resume", out, "--max-iter", "100"], capsys)
    assert "loss.csv" in line and "iteration" in line, line
    assert (out / "loss.csv").read_bytes() == damaged
    assert (out / "run.json").read_bytes() == before["run.json"]
    rec = record(out)
    assert rec["finish_reason"] == FinishReason.COMPLETED
    assert rec["spec"]["stopping"]["max_iter"] == 8
    # a failure in the first step (torch.compile, out of memory, Ctrl-C) after the record was
    # written as running: it is put back
    (out / "loss.csv").write_bytes(before["loss.csv"])
    from recon.udn.runner import UDNRunner

    def first_step_fails(self, *args, **kwargs):
        raise KeyboardInterrupt
        yield  # a generator, like the real one

    monkeypatch.setattr(UDNRunner, "steps", first_step_fails)
    with pytest.raises(KeyboardInterrupt):
        resume_job(out, max_iter=100)
    assert {n: (out / n).read_bytes() for n in before} == before


def test_a_short_loss_row_is_named_and_a_lost_history_is_noted(tiny_data, tmp_path, capsys):
    """A row cut short was kept with empty fields, and a deleted loss.csv let the history
    restart mid-run without a word."""
    out = tmp_path / "run"
    small_run(tiny_data, out)
    text = (out / "loss.csv").read_text()
    lines = text.splitlines(keepends=True)
    cut = next(i for i, ln in enumerate(lines) if ln.startswith("5,"))
    (out / "loss.csv").write_text("".join([*lines[:cut], "5,0.1\n", *lines[cut + 1:]]))
    line = one_line_error(["jobs", "resume", out, "--max-iter", "12"], capsys)
    assert f"line {cut + 1}: fewer fields than the header's 8 (a damaged row)" in line, line
    (out / "loss.csv").unlink()
    assert cli_main(["jobs", "resume", str(out), "--max-iter", "12", "--quiet"]) == 0
    capsys.readouterr()
    assert any("loss.csv was missing at the resume: the loss history restarts at iteration 9"
               in n for n in record(out)["notes"]), record(out)["notes"]
    assert int(read_loss_rows(out)[0]["iteration"]) == 9


def test_a_gap_in_a_repaired_loss_csv_is_noted(tiny_data, tmp_path, capsys):
    """After a cut-off loss.csv was repaired as told (the damaged row deleted), the resume left
    the rows after it missing without a word."""
    out = tmp_path / "run"
    small_run(tiny_data, out)  # rows 1-8, checkpoint at 8
    lines = (out / "loss.csv").read_text().splitlines(keepends=True)
    keep = [ln for ln in lines if ln[:2] not in ("4,", "6,", "7,", "8,")]
    (out / "loss.csv").write_text("".join(keep))
    assert cli_main(["jobs", "resume", str(out), "--max-iter", "10", "--quiet"]) == 0
    err = capsys.readouterr().err
    words = ("loss.csv lacks the rows of iterations 4, 6-8 (4 rows): the loss history has a gap "
             "there")
    assert f"lenslesscam jobs resume: note: {words}" in err, err
    assert words in record(out)["notes"]
    # said once: a later resume does not repeat it
    assert cli_main(["jobs", "resume", str(out), "--max-iter", "12", "--quiet"]) == 0
    assert "lacks the rows" not in capsys.readouterr().err
    assert record(out)["notes"].count(words) == 1


def test_a_lost_loss_csv_is_printed_at_the_resume(tiny_data, tmp_path, capsys):
    """The note that loss.csv was missing went into run.json only; the resume prints it (one
    line on stderr, as its other notes)."""
    out = tmp_path / "run"
    small_run(tiny_data, out)
    (out / "loss.csv").unlink()
    assert cli_main(["jobs", "resume", str(out), "--max-iter", "12", "--quiet"]) == 0
    err = capsys.readouterr().err
    words = "loss.csv was missing at the resume: the loss history restarts at iteration 9"
    assert [ln for ln in err.splitlines() if words in ln] == [
        f"lenslesscam jobs resume: note: {words}"], err
    assert sum(words in n for n in record(out)["notes"]) == 1
    # an empty one too; a resume with its history says nothing of it
    (out / "loss.csv").write_text("")
    assert cli_main(["jobs", "resume", str(out), "--max-iter", "14", "--quiet"]) == 0
    assert "loss.csv was empty at the resume" in capsys.readouterr().err
    assert cli_main(["jobs", "resume", str(out), "--max-iter", "16", "--quiet"]) == 0
    assert "loss.csv" not in capsys.readouterr().err


def test_a_resume_with_a_time_limit_already_spent_is_refused(tiny_data, tmp_path, capsys):
    """It ran one iteration and reported 'completed' again, suggesting --time-limit 2, 4, ...
    (a --max-iter below the iteration reached is refused; so is this now)."""
    out = tmp_path / "run"
    small_run(tiny_data, out)
    before = (out / "run.json").read_bytes()
    line = one_line_error(["jobs", "resume", out, "--max-iter", "100", "--time-limit",
                           "0.000001"], capsys)
    assert "s of iterations and its time limit is 1e-06 s: pass a larger --time-limit" in line
    assert (out / "run.json").read_bytes() == before


def test_an_edited_job_toml_is_noted_at_the_resume(tiny_data, tmp_path, capsys):
    """A resume runs the spec in run.json; an edit of the run's job.toml was ignored silently."""
    out = tmp_path / "run"
    small_run(tiny_data, out)
    assert resume_job(out, max_iter=10).finish_reason == FinishReason.COMPLETED
    assert not any("was edited" in n for n in record(out)["notes"])
    spec = out / "job.toml"
    spec.write_text(spec.read_text() + "\n# lr = 0.5 would be better\n")
    assert cli_main(["jobs", "resume", str(out), "--max-iter", "12"]) == 0
    err = capsys.readouterr().err
    words = "job.toml was edited after the run started; a resume keeps the spec"
    assert words in err, err
    assert any(words in n for n in record(out)["notes"])


def test_another_runs_checkpoint_is_refused(tiny_data, tmp_path, capsys):
    """A checkpoint copied from another run of the same settings took the run back to that
    run's iteration without a word."""
    import shutil

    a, b = tmp_path / "a", tmp_path / "b"
    small_run(tiny_data, a)
    small_run(tiny_data, b, stopping={"max_iter": 4})
    before = (a / "run.json").read_bytes()
    for name in ("checkpoint.pt", "checkpoint.prev.pt", "checkpoints.json"):
        if (b / name).exists():
            shutil.copy(b / name, a / name)
    line = one_line_error(["jobs", "resume", a, "--max-iter", "12"], capsys)
    assert "is a checkpoint of another run" in line and "--restart" in line, line
    assert (a / "run.json").read_bytes() == before
    assert record(a)["run_id"] != record(b)["run_id"]


# the old rule's double dark, on purpose: said by a warning each time the problem is loaded
@pytest.mark.filterwarnings("ignore:PSF file .* is a calibrated PSF, dark-subtracted already")
def test_a_run_begun_before_the_calibrated_psf_rule_resumes_as_it_began(tiny_data, tmp_path):
    """A calibrated PSF no longer takes data.dark; a run begun before (its PSF's array hash made
    with the dark taken off) was refused on resume: 'data.psf changed (hash H -> H)'."""
    import numpy as np

    from recon.calibfile import save_psf_calibration

    psf = np.load(tiny_data / "psf.npy").reshape(np.load(tiny_data / "psf.npy").shape[-2:])
    save_psf_calibration(tiny_data / "cal.tif", 1000 * psf, {
        "camera": {}, "exposure_us": 1.0, "gain": 1.0, "frames_averaged": 1,
        "dark_level": 0.0, "timing": None, "quality": {}})
    out = tmp_path / "run"
    # what the old rule did: the measurement's dark taken off the PSF too
    small_run(tiny_data, out, data={"psf": "cal.tif", "dark": 0.01, "psf_dark": 0.01})
    rec = record(out)
    del rec["run_id"]  # a record of the version before
    rec["spec"]["data"]["psf_dark"] = None
    (out / "run.json").write_text(json.dumps(rec))
    assert resume_job(out, max_iter=10).finish_reason == FinishReason.COMPLETED
    assert any("goes on that way (psf_dark = dark)" in n for n in record(out)["notes"])


def test_temporary_files_of_killed_writes_are_cleaned_at_the_next_start(tiny_data, tmp_path):
    out = tmp_path / "run"
    small_run(tiny_data, out)
    (out / ".checkpoint.pt.k1l2d.tmp").write_bytes(b"\0" * 1000)
    (out / "previews" / ".iter_0000012.x7y.tmp.png").write_bytes(b"\0" * 10)
    keep = out / "previews" / "notes.tmp.txt"  # not a temporary file of ours
    keep.write_text("mine")
    resume_job(out, max_iter=10)
    assert temp_names(out) == [] and keep.exists()
    rec = record(out)
    assert ("removed 2 temporary file(s) left by a write that was interrupted: "
            ".checkpoint.pt.k1l2d.tmp, previews/.iter_0000012.x7y.tmp.png") in rec["notes"]


@pytest.mark.parametrize(("field", "value", "words"), [
    ("progress.iteration", "12x", "should be an integer, got '12x'"),
    ("format_version", "one", "should be an integer, got 'one'"),
    ("checkpoint", 7, "should be a table or null, got 7"),
    ("status", "runing", "is 'runing'; expected one of queued, starting, running"),
])
def test_a_damaged_run_record_field_is_named(tiny_data, tmp_path, capsys, field, value, words):
    out = tmp_path / "run"
    small_run(tiny_data, out)
    rec = record(out)
    head, _, tail = field.partition(".")
    if tail:
        rec[head][tail] = value
    else:
        rec[head] = value
    (out / "run.json").write_text(json.dumps(rec))
    for argv in (["jobs", "status", out], ["jobs", "resume", out, "--max-iter", "9"]):
        line = one_line_error(argv, capsys)
        assert str(out / "run.json") in line and f"'{field}'" in line and words in line
    with pytest.raises(FormatError):
        read_record(out)


def test_a_run_record_that_is_not_utf8_is_named(tiny_data, tmp_path, capsys):
    out = tmp_path / "run"
    small_run(tiny_data, out)
    (out / "run.json").write_bytes(b'{"format": "\xff"}')
    line = one_line_error(["jobs", "status", out], capsys)
    assert str(out / "run.json") in line and "not UTF-8" in line


def test_a_spec_that_is_not_utf8_is_named(tiny_data, tmp_path, capsys):
    spec = tiny_data / "latin1.toml"
    spec.write_bytes('[job]\nname = "caf\u00e9"\n'.encode("latin-1"))
    line = one_line_error(["jobs", "run", spec, "--out", tmp_path / "run"], capsys)
    assert str(spec) in line and "not UTF-8 text (byte 0xe9 at offset" in line
    assert not (tmp_path / "run").exists()


def test_states_and_finish_reasons_are_enums(tiny_data, tmp_path):
    out = tmp_path / "run"
    small_run(tiny_data, out)
    st = job_status(out)
    assert st.state is JobState.FINISHED and st.finish_reason is FinishReason.COMPLETED
    assert record(out)["status"] == "finished" == JobState.FINISHED
    assert f"{JobState.RUNNING}" == "running" and JobState("interrupted").active is False
    assert FinishReason.CANCELLED.resumable and not FinishReason.COMPLETED.resumable
