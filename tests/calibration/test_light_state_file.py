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
