"""The app as a real process: SIGTERM closes it cleanly and stops its child processes; a machine
without Qt's X11 libraries gets the install command instead of an abort."""

from __future__ import annotations

import os
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from tests.udn.jobrunner import ServerChild

pytestmark = pytest.mark.gui


def _children(pid: int) -> list[int]:
    """Child processes of ``pid`` (Linux /proc)."""
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(x) for x in (task / "children").read_text().split()]
        except OSError:
            continue
    return out


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def _wait_for(cond: Callable[[], Any], timeout_s: float, what: str) -> Any:
    """Poll ``cond`` until it is truthy (returns its value) or fail after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = cond()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux /proc")
def test_sigterm_closes_the_app_and_stops_the_point_source_process(tmp_path: Path,
                                                                  job_server: Any) -> None:
    # `lenslesscam app` in a real process, forked from the fork server (torch imported once)
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen", OMP_NUM_THREADS="1",
               LENSLESSCAM_CONFIG_DIR=str(tmp_path / "config"),
               LENSLESSCAM_JOBS_DIR=str(tmp_path / "jobs"))
    pid, log = job_server.start(["app", "--camera", "sim", "--light-port", "sim",
                                 "--reset-settings"], env, tmp_path / "app.log")
    proc = ServerChild(job_server, pid)
    source: list[int] = []
    try:
        source = _wait_for(
            lambda: [c for c in _children(proc.pid) if "drivers.pointsource_sim" in _cmdline(c)]
            or proc.poll() is not None,
            60.0, "the simulated point-source process")
        assert proc.poll() is None, log.read_text(errors="replace")
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
        out = log.read_text(errors="replace")
        assert proc.returncode == 0, out
        assert "SIGTERM: closing the app" in out
        _wait_for(lambda: not any(_alive(p) for p in source), 10.0,
                  "the point-source process to end")
        assert (tmp_path / "config" / "app-settings.json").exists()  # a clean close
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)
        for p in source:
            if _alive(p):
                os.kill(p, signal.SIGKILL)


def test_missing_x11_libraries_print_the_install_command(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import ctypes.util

    from app.cli import main
    from app.commands import gui

    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("QT_QPA_PLATFORM", raising=False)
    monkeypatch.setenv("DISPLAY", ":99")
    real = ctypes.util.find_library
    monkeypatch.setattr(ctypes.util, "find_library",
                        lambda name: None if name == "xcb-icccm" else real(name))
    assert gui.missing_xcb_packages() == [p for lib, p in gui.XCB_LIBRARIES.items()
                                          if lib == "xcb-icccm" or real(lib) is None]
    assert main(["app"]) == 2
    err = capsys.readouterr().err
    assert "libxcb-icccm4" in err
    assert "sudo apt-get install -y libxcb-cursor0 libxcb-icccm4 libxcb-keysyms1" in err
    # with the libraries but no display: said in one line, no Qt abort
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: f"lib{name}.so")
    monkeypatch.delenv("DISPLAY")
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert main(["app"]) == 2
    assert "no display" in capsys.readouterr().err
    # another platform plugin (offscreen, wayland) does not need them
    monkeypatch.setenv("QT_QPA_PLATFORM", "offscreen")
    assert not gui.uses_xcb()
