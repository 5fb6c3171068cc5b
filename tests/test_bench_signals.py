"""``lenslesscam bench`` stopped by SIGTERM: its ``finally`` clean-ups run, no process is left.

Failed on the code before: no benchmark installed the CLI's SIGTERM handler, so ``bench preview
--loads 1`` died at once and its busy load process ran on with PPID 1 at 100 % CPU.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.procs import HAS_PROC, alive, children_of

ROOT = Path(__file__).resolve().parents[1]


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


@pytest.mark.skipif(not HAS_PROC, reason="reads /proc")
def test_sigterm_during_bench_preview_leaves_no_load_process() -> None:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    proc = subprocess.Popen(
        [sys.executable, "-m", "app.cli", "bench", "preview", "--loads", "1", "--seconds", "30",
         "--warmup", "0.2", "--configs", "8x1", "--target-fps", "0"],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    loads: list[int] = []
    try:
        deadline = time.monotonic() + 120
        while not loads and time.monotonic() < deadline and proc.poll() is None:
            loads = [pid for pid, _ in children_of(proc.pid) if "getppid" in _cmdline(pid)
                     or "while True" in _cmdline(pid)]
            time.sleep(0.1)
        assert loads, f"no load process started: {proc.communicate(timeout=30)}"
        proc.send_signal(signal.SIGTERM)
        _out, err = proc.communicate(timeout=60)
        end = time.monotonic() + 10
        while any(alive(p) for p in loads) and time.monotonic() < end:
            time.sleep(0.1)
        assert not [p for p in loads if alive(p)], "a load process outlived the benchmark"
        assert proc.returncode == 130, err  # stopped through the Ctrl-C path
        assert "interrupted" in err and "Traceback" not in err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for p in loads:
            if alive(p):
                os.kill(p, signal.SIGKILL)


@pytest.mark.skipif(not HAS_PROC, reason="reads /proc")
def test_a_load_process_ends_when_its_parent_is_killed() -> None:
    """SIGKILL runs no clean-up: the load process itself notices its parent is gone."""
    code = ("import sys\nsys.path.insert(0, sys.argv[1])\nfrom benchmarks.bench_preview import "
            "busy_processes\nimport time\nwith busy_processes(1) as pids:\n    print(pids[0], "
            "flush=True)\n    time.sleep(60)\n")
    parent = subprocess.Popen([sys.executable, "-c", code, str(ROOT)], stdout=subprocess.PIPE,
                              text=True)
    child = 0
    try:
        assert parent.stdout is not None
        child = int(parent.stdout.readline())
        assert alive(child)
        parent.kill()
        parent.wait()
        end = time.monotonic() + 10
        while alive(child) and time.monotonic() < end:
            time.sleep(0.05)
        assert not alive(child)
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()
        parent.stdout.close()
        if child and alive(child):
            os.kill(child, signal.SIGKILL)
