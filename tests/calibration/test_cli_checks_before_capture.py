"""``lenslesscam calibrate``: what can be checked is checked before any capture.

The output's suffix, the camera's own files as inputs, strobe times at the resolution the
driver sends; and the point source's port opened by one process at a time, its open errors
said once.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import tifffile

from app.cli import main
from drivers.lightsource import SerialPointSource


@pytest.fixture
def no_capture(monkeypatch):
    """Fail the test if a calibrate command opens a camera or starts the simulated source."""
    import drivers.pointsource_sim
    import drivers.registry

    def captured(*_a, **_k):
        raise AssertionError("a device was opened before the refusal")

    monkeypatch.setattr(drivers.registry, "open_camera", captured)
    monkeypatch.setattr(drivers.pointsource_sim, "spawn_simulated_source", captured)


@pytest.mark.parametrize(("argv", "name", "says"), [
    (["darks", "--no-prompt"], "darks.tif", "a pixel-maps calibration is saved as .npz"),
    (["psf", "--source", "sim"], "x.npz", "a psf calibration is saved as .tif or .tiff"),
    (["depth", "--source", "sim", "--positions", "1,2", "--no-prompt"], "x.npz",
     "a psf-stack calibration is saved as .tif or .tiff"),
    (["shutter"], "x.tif", "a shutter calibration is saved as .npz"),
    (["shutter", "--source", "sim"], "x.TIFF", "a shutter calibration is saved as .npz"),
])
def test_a_wrong_suffix_is_refused_before_any_capture(tmp_path, capsys, no_capture, argv,
                                                      name, says):
    """--out darks.tif was refused by the file writer, after all the frames were taken."""
    out = tmp_path / name
    assert main(["calibrate", *argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"lenslesscam calibrate: error: {out}: {says}"
    assert not list(tmp_path.iterdir())


def test_the_suffix_rule_is_the_writers_rule(tmp_path):
    """One function: the refusal before the capture is the writers' own."""
    from recon.calibfile import check_calibration_suffix, save_shutter

    with pytest.raises(ValueError) as early:
        check_calibration_suffix(tmp_path / "s.tif", "shutter")
    with pytest.raises(ValueError) as late:
        save_shutter(tmp_path / "s.tif", np.ones((2, 3)), {})
    assert str(early.value) == str(late.value)
    assert check_calibration_suffix(tmp_path / "p.TIFF", "psf") == tmp_path / "p.TIFF"


def _tiff_sequence(folder):
    folder.mkdir()
    for i in range(3):
        tifffile.imwrite(folder / f"{i:04d}.tif", np.full((64, 80), 100 + i, dtype=np.uint16))
    return str(folder / "%04d.tif")


def test_calibrate_never_writes_over_the_camera_files(tmp_path, capsys, no_capture):
    """A file camera's recording is an input of the command, as --sim-psf is."""
    pattern = _tiff_sequence(tmp_path / "seq")
    frame = tmp_path / "seq" / "0001.tif"
    before = frame.read_bytes()
    argv = ["calibrate", "psf", "--camera", f"v4l2:{pattern}", "--source", "sim",
            "--out", str(frame), "--overwrite"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"lenslesscam calibrate: error: refusing to write {frame}: it is the input "
                   f"--camera v4l2:{pattern} of this command (choose another output name)")
    assert frame.read_bytes() == before
    # a video (any name: here one a shutter file would have)
    video = tmp_path / "recording.npz"
    shutil.copyfile(frame, video)
    argv = ["calibrate", "shutter", "--camera", f"v4l2:{video}", "--out", str(video),
            "--overwrite"]
    assert main(argv) == 2
    assert (f"refusing to write {video}: it is the input --camera v4l2:{video}"
            in capsys.readouterr().err)


def test_a_pulse_below_the_source_resolution_is_refused_before_any_capture(
        tmp_path, capsys, no_capture):
    """--pulse 0.04us was sent as 0.0 and the firmware's refusal blamed the hardware
    ("Check the point source: power, cable and port")."""
    for option in ("--pulse", "--step"):
        out = tmp_path / "sh.npz"
        assert main(["calibrate", "shutter", "--source", "sim", option, "0.04us",
                     "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert err == (f"lenslesscam calibrate: error: {option} 0.04us: the point source times "
                       "its pulses in steps of 0.1 us; use 0.1us or more")
        assert "power, cable" not in err
    assert not list(tmp_path.iterdir())


def test_a_strobe_time_is_rounded_to_what_is_sent_and_said(capsys):
    from app.commands.calibrate import _strobe_time

    assert _strobe_time("0.1us", "--pulse") == 0.1
    assert _strobe_time("2ms", "--pulse") == 2000.0
    assert capsys.readouterr().err == ""
    assert _strobe_time("0.26us", "--pulse") == 0.3
    assert capsys.readouterr().err == ("lenslesscam: warning: --pulse 0.26us is rounded to "
                                       "0.3 us, the point source's 0.1 us resolution\n")


def test_a_point_source_in_use_is_refused_in_one_line(tmp_path, capsys, firmware):
    """A second opener took the first one's replies: calibrate corrupted a running session."""
    out = tmp_path / "maps.npz"
    with SerialPointSource(firmware.port, timeout_s=2.0) as held:
        argv = ["calibrate", "darks", "--source", firmware.port, "--frames", "1", "--settle",
                "0", "--out", str(out)]
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err == (f"lenslesscam calibrate: error: port {firmware.port} is in use by "
                       "another process (close the other connection to the point source "
                       "first)")
        assert held.status().identity  # the holder is undisturbed
    assert not out.exists()


def test_a_point_source_that_does_not_open_is_said_once(tmp_path, capsys):
    """'cannot open the point source on X: cannot open point source on X: [Errno 2] could not
    open port X: [Errno 2] No such file or directory: 'X''."""
    port = tmp_path / "no-such-tty"
    argv = ["calibrate", "darks", "--source", str(port), "--frames", "1", "--out",
            str(tmp_path / "maps.npz")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"lenslesscam calibrate: error: cannot open the point source on {port}: "
                   "No such file or directory")
