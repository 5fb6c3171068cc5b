"""``jobs cancel`` and ``batch cancel`` agree: a run or batch that is not running is not an
error (exit 0, one line ending "nothing to cancel"); a folder that holds none is (exit 2)."""

from __future__ import annotations

import json
import platform
import subprocess
import sys
from pathlib import Path

import pytest

from app.batch.state import STATE_FORMAT
from app.cli import main as cli_main
from recon.udn.jobs import run_job
from tests.udn.conftest import write_spec


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_jobs_cancel_of_a_finished_run_is_not_an_error(
    tiny_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """It exited 2 with "error: ... the run is not running" (batch cancel exited 0)."""
    out = tmp_path / "run"
    assert run_job(write_spec(tiny_data, stopping={"max_iter": 3}), out).iterations == 3
    capsys.readouterr()
    assert cli_main(["jobs", "cancel", str(out)]) == 0
    cap = capsys.readouterr()
    lines = cap.out.strip().splitlines()
    assert len(lines) == 1 and cap.err == ""
    assert "not running (finish reason completed)" in lines[0]
    assert lines[0].endswith("nothing to cancel")
    assert not (out / "CANCEL").exists()
    # no run there at all is still an error
    assert cli_main(["jobs", "cancel", str(tmp_path / "nothing")]) == 2
    assert "no UDN run here" in capsys.readouterr().err


def _batch(root: Path, status: str, pid: int) -> Path:
    root.mkdir()
    (root / "state.json").write_text(json.dumps(
        {"format": STATE_FORMAT, "status": status, "pid": pid, "host": platform.node(),
         "items": {}}), encoding="utf-8")
    return root


@pytest.mark.parametrize("status", ["finished", "cancelled", "running"])
def test_batch_cancel_of_a_batch_that_is_not_running_is_not_an_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], status: str
) -> None:
    """A 'running' batch whose driver is gone (killed) is not running either: cancel wrote a
    CANCEL file and said "cancellation requested" to nobody."""
    root = _batch(tmp_path / "b", status, _dead_pid())
    assert cli_main(["batch", "cancel", str(root)]) == 0
    cap = capsys.readouterr()
    lines = cap.out.strip().splitlines()
    assert len(lines) == 1 and cap.err == ""
    assert "not running" in lines[0] and lines[0].endswith("nothing to cancel")
    assert ("interrupted" if status == "running" else f"status {status}") in lines[0]
    assert not (root / "CANCEL").exists()
    assert cli_main(["batch", "cancel", str(tmp_path / "nothing")]) == 2
    assert "not a batch folder" in capsys.readouterr().err
