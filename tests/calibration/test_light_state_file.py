"""``snap --light-state FILE``: the file must be a simulated source's light-state file."""

from __future__ import annotations

import json

import pytest

from app.cli import main
from drivers.lightstate import LIGHT_STATE_FORMAT, LightMode, LightState, write_light_state


def test_check_light_state_file_takes_only_what_the_firmware_writes(tmp_path):
    from drivers.lightstate import check_light_state_file

    good = tmp_path / "state.json"
    write_light_state(good, LightState(mode=LightMode.ON, intensity=0.5))
    assert check_light_state_file(good).intensity == 0.5
    cases = {
        "not-text.bin": (b"\x00\xff\x10binary", "(it is not text)"),
        "not-json.json": (b"mode: on", "(not JSON"),
        "other.json": (json.dumps({"format": "something-else"}).encode(),
                       "(format 'something-else', expected 'lenslesscam-light-state')"),
        "list.json": (b"[1, 2]", "(format None"),
        "newer.json": (json.dumps({**LightState().to_dict(), "format_version": 99}).encode(),
                       "light-state format_version 99 is not one this release reads"),
        "no-mode.json": (json.dumps({"format": LIGHT_STATE_FORMAT, "format_version": 1}).encode(),
                         "(bad or missing field"),
    }
    for name, (content, says) in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ValueError) as info:
            check_light_state_file(tmp_path / name)
        text = str(info.value)
        assert str(tmp_path / name) in text and says in text and "\n" not in text, text
    with pytest.raises(ValueError, match="not a regular file"):
        check_light_state_file(tmp_path)
    with pytest.raises(FileNotFoundError, match="no such file"):
        check_light_state_file(tmp_path / "missing.json")


def test_snap_refuses_a_file_that_is_not_a_light_state(tmp_path, capsys):
    """Any existing file was taken as --light-state (and read as a dark source)."""
    other = tmp_path / "settings.json"
    other.write_text(json.dumps({"exposure": 10}))
    out = tmp_path / "f.tif"
    assert main(["snap", "--camera", "sim", "--light-state", str(other), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"lenslesscam snap: error: --light-state {other} is not a light-state file of "
                   "a simulated point source (format None, expected 'lenslesscam-light-state')")
    assert not out.exists()
    state = tmp_path / "light-state.json"
    write_light_state(state, LightState(mode=LightMode.ON, intensity=1.0))
    assert main(["snap", "--camera", "sim", "--light-state", str(state), "--out", str(out)]) == 0
    assert out.exists()
    capsys.readouterr()


# --------------------------------------------------------------------------------------------
# a state file whose writer is gone reads as dark


def _gone_pid() -> int:
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()  # exited and reaped: its pid exists no more
    return proc.pid


def test_a_state_whose_writer_is_gone_reads_dark(tmp_path):
    """The firmware's pid was recorded but never checked: a simulator killed with the light on
    lit the simulated camera for ever."""
    import os
    import subprocess
    import sys
    import time

    from drivers.lightstate import read_light_state, writer_running

    lit = LightState(mode=LightMode.ON, intensity=1.0)
    path = tmp_path / "state.json"
    write_light_state(path, lit)
    record = json.loads(path.read_text())
    assert record["pid"] == os.getpid() and isinstance(record["host"], str)
    assert read_light_state(path).lit  # written by this running process

    def with_record(**changes):
        path.write_text(json.dumps({**record, **changes}))
        return read_light_state(path)

    gone = with_record(pid=_gone_pid())
    assert not gone.lit and not gone.available
    assert with_record(pid=_gone_pid(), host="another-host").lit  # not checkable from here
    assert with_record(pid=None).lit  # no writer recorded: as before
    # a zombie (killed, not reaped yet) is gone too
    zombie = subprocess.Popen([sys.executable, "-c", "pass"])
    try:
        deadline = time.monotonic() + 10.0
        while writer_running({"pid": zombie.pid}) and time.monotonic() < deadline:
            time.sleep(0.05)  # until it has exited (and, not waited for, is a zombie)
        assert not with_record(pid=zombie.pid).lit
    finally:
        zombie.wait()
    # a pid used again by another process: the recorded start time differs
    from drivers.lightstate import _start_time

    parent = os.getppid()
    started = _start_time(parent)
    if started is not None:  # Linux /proc
        assert with_record(pid=parent, pid_start=started).lit
        assert not with_record(pid=parent, pid_start=started + 1).lit


def test_the_camera_goes_dark_when_the_firmware_is_killed(tmp_path, capsys, firmware, source):
    """kill -9 of the simulator, then snap --light-state: the frame was still lit."""
    from drivers.lightstate import LightStateFile

    source.set_intensity(1.0)
    source.on()
    watched = LightStateFile(firmware.state_path)
    assert watched.light_state().lit
    lit_out, dark_out = tmp_path / "lit.tif", tmp_path / "dark.tif"
    argv = ["snap", "--camera", "sim", "--light-state", str(firmware.state_path),
            "--sim-flux", "5e6", "--exposure", "1ms"]
    assert main([*argv, "--out", str(lit_out)]) == 0
    assert capsys.readouterr().err == ""
    source.close()
    firmware.kill()  # SIGKILL: no chance to write 'off'
    assert json.loads(firmware.state_path.read_text())["mode"] == "on"  # left behind
    state = watched.light_state()  # the file did not change: its writer is checked anyway
    assert not state.lit and not state.available
    assert main([*argv, "--out", str(dark_out)]) == 0
    err = capsys.readouterr().err.strip()
    assert err == (f"lenslesscam: warning: --light-state {firmware.state_path}: the simulated "
                   "source that wrote it is no longer running; its light reads as off")
    import tifffile

    lit, dark = tifffile.imread(lit_out), tifffile.imread(dark_out)
    assert lit.max() > 2 * dark.max()
