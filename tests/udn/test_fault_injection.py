"""Issue 15, "shown by" 2: a UDN job SIGKILLed at 20 random moments and resumed each time.

The moments: during start-up, at random points between iterations (previews, the loss history
and the record are written there), and inside checkpoint writes (half the file written; written
and verified but not yet in place; the newest one linked as the previous one). Each child is a
real process forked by :class:`tests.udn.jobrunner.JobServer` (which imported torch once), so
the test takes seconds per kill, not the interpreter's start-up time.

Checked: after every kill the run's lock is free; every resume continues from the newest
verified checkpoint (never from an older one, never from a damaged one); the final estimates,
weights, optimiser state and loss history equal those of an uninterrupted run bit for bit; no
temporary file is left.
"""

from __future__ import annotations

import json
import random
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from recon.atomic import is_temp_name
from recon.io import read_reconstruction
from recon.udn.jobs import load_checkpoint, read_loss_rows
from recon.udn.rundir import RunLock, load_latest_checkpoint
from tests.udn.conftest import write_spec
from tests.udn.jobrunner import MARK_ENV, PAUSE_ENV, JobServer

MAX_ITER = 120
EVERY = 8  # checkpoint interval
KINDS = ["startup"] * 2 + ["iteration"] * 8 + ["write"] * 4 + ["rotate"] * 3 + ["replace"] * 3


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _progress(out: Path, pid: int) -> int:
    """The iteration that process ``pid`` has recorded (0 before it wrote the record)."""
    try:
        rec = json.loads((out / "run.json").read_text())
        return int(rec["progress"]["iteration"]) if rec["pid"] == pid else 0
    except (OSError, ValueError, KeyError, TypeError):
        return 0


def _temp_files(out: Path) -> list[str]:
    return [p.name for d in (out, out / "previews") if d.is_dir() for p in d.iterdir()
            if is_temp_name(p.name)]


def _wait(cond, pid: int, log: Path, what: str, timeout: float = 120.0) -> None:
    t0 = time.monotonic()
    while not cond():
        assert _alive(pid), f"the job ended before {what}: {log.read_text()[-2000:]}"
        assert time.monotonic() - t0 < timeout, f"timed out waiting for {what}"
        time.sleep(0.01)


@pytest.mark.slow
def test_sigkill_at_20_random_moments_then_resume_is_bit_for_bit(tiny_data, tmp_path):
    rng = random.Random(1515)
    kinds = list(KINDS)
    rng.shuffle(kinds)
    spec = write_spec(tiny_data, stopping={"max_iter": MAX_ITER},
                      optimizer={"snapshot_every": 7},
                      output={"checkpoint_every": EVERY, "preview_every": 5,
                              "status_seconds": 0.0})
    out = tmp_path / "killed"
    marks = tmp_path / "marks"
    marks.mkdir()
    expected_start: dict[int, int] = {}  # pid -> the iteration its session must start from
    temp_after_write_kills = 0
    with JobServer(tmp_path / "logs") as srv:
        for k, kind in enumerate(kinds):
            if (out / "run.json").exists():
                argv = ["jobs", "resume", str(out), "--quiet"]
            else:  # killed before the run record existed: start it again
                argv = ["jobs", "run", str(spec), "--out", str(out), "--quiet"]
            _, info, problems = load_latest_checkpoint(out)
            start_at = int(info.get("iteration", 0))
            assert problems in ([], ["checkpoint.pt is missing"]) or not out.exists(), problems
            env = {}
            mark = marks / f"kill_{k:02d}"
            if kind == "iteration" and start_at + 10 >= MAX_ITER:
                kind = "write"  # too close to the end for a kill between iterations
            if kind in ("write", "rotate", "replace"):
                # the NTH checkpoint write of the session (the final one included)
                nth = 1 if start_at + EVERY >= MAX_ITER else rng.randint(1, 2)
                env = {PAUSE_ENV: f"{kind}:{nth}", MARK_ENV: str(mark)}
            pid, log = srv.start(argv, env)
            expected_start[pid] = start_at
            if kind == "startup":
                time.sleep(rng.uniform(0.0, 0.4))
            elif kind == "iteration":
                target = min(start_at + rng.randint(1, 6), MAX_ITER - 10)
                _wait(lambda t=target, p=pid: _progress(out, p) >= t, pid, log,
                      f"iteration {target}")
                time.sleep(rng.uniform(0.0, 0.03))
            else:
                _wait(mark.exists, pid, log, f"the checkpoint {kind} pause")
            assert srv.kill(pid) == -9, log.read_text()[-2000:]
            with RunLock(out):  # the kernel released the killed process's lock
                pass
            if kind == "write":
                temp_after_write_kills += bool(_temp_files(out))
            # a checkpoint the record reported as written is never lost
            recorded = (json.loads((out / "run.json").read_text()).get("checkpoint") or {}
                        if (out / "run.json").exists() else {})
            _, now, _ = load_latest_checkpoint(out)
            assert now.get("iteration", 0) >= recorded.get("iteration", 0)
        pid, log = srv.start(["jobs", "resume", str(out), "--quiet"])
        _, info, _ = load_latest_checkpoint(out)
        expected_start[pid] = int(info.get("iteration", 0))
        assert srv.wait(pid, timeout=300) == 0, log.read_text()[-2000:]
        whole = tmp_path / "whole"  # the same job without interruption
        pid, log = srv.start(["jobs", "run", str(spec), "--out", str(whole), "--quiet"])
        assert srv.wait(pid, timeout=300) == 0, log.read_text()[-2000:]
    assert temp_after_write_kills >= 1  # kills in the middle of writes did leave some

    rec = json.loads((out / "run.json").read_text())
    assert rec["finish_reason"] == "completed" and rec["progress"]["iteration"] == MAX_ITER
    sessions = [s for s in rec["sessions"] if s["pid"] in expected_start]
    assert len(sessions) >= 17, len(sessions)  # all but the start-up kills wrote the record
    for s in sessions:  # each continued from the newest verified checkpoint
        assert s["start_iteration"] == expected_start[s["pid"]], s
        if s["start_iteration"] > 0:
            assert s["resumed_from"]["path"] == "checkpoint.pt", s
            assert s["resumed_from"]["verified"] is True, s
    assert not any(n.startswith("resumed from") for n in rec["notes"])  # no fallback needed
    assert any(n.startswith("removed ") and "temporary file" in n for n in rec["notes"])
    assert _temp_files(out) == []

    for name in ("final.tif", "best.tif"):
        a, _ = read_reconstruction(whole / name)
        b, _ = read_reconstruction(out / name)
        np.testing.assert_array_equal(a, b)  # bit for bit
    sa = load_checkpoint(whole / "checkpoint.pt")["state"]
    sb = load_checkpoint(out / "checkpoint.pt")["state"]
    assert sa["iteration"] == sb["iteration"] == MAX_ITER
    for key in sa["G"]:
        assert torch.equal(sa["G"][key], sb["G"][key]), key
    for key in ("ema", "best", "heldout"):
        assert torch.equal(sa[key], sb[key]), key
    for ka, kb in zip(sa["opt"]["state"].values(), sb["opt"]["state"].values(), strict=True):
        assert all(torch.equal(ka[x], kb[x]) for x in ka)
    ra, rb = (read_loss_rows(p) for p in (whole, out))
    np.testing.assert_array_equal([int(r["iteration"]) for r in ra], np.arange(1, MAX_ITER + 1))
    # the same history, no gaps
    assert [r["loss"] for r in ra] == [r["loss"] for r in rb]
