"""``lenslesscam devices`` and ``lenslesscam snap`` through ``app.cli.main``."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
import tifffile

import app.cli
from app.commands.devices import parse_duration_us

pytestmark = pytest.mark.timeout(60)


@pytest.fixture(autouse=True)
def only_device_commands(monkeypatch: pytest.MonkeyPatch) -> None:
    """Register just this module's subcommands (the others are tested on their own)."""
    monkeypatch.setattr(app.cli, "COMMAND_MODULES", ("app.commands.devices",))


def test_devices_lists_cameras_producers_and_ports(
    capsys: pytest.CaptureFixture[str], tlsimu_cti: Path
) -> None:
    assert app.cli.main(["devices", "--producer", str(tlsimu_cti)]) == 0
    out = capsys.readouterr().out
    assert "Cameras:" in out and "Serial ports:" in out and "GenTL producers:" in out
    assert "sim " in out and "TLSimuMono" in out and "Viky" in out
    assert app.cli.main(["devices", "--json", "--producer", str(tlsimu_cti)]) == 0
    data = json.loads(capsys.readouterr().out)
    specs = [c["spec"] for c in data["cameras"]]
    assert specs[0] == "sim" and "genicam:0" in specs
    assert str(tlsimu_cti) in data["gentl_producers"]
    assert isinstance(data["serial_ports"], list)


def _read_tiff(path: Path) -> tuple[np.ndarray, dict[str, object]]:
    with tifffile.TiffFile(path) as tf:
        page = tf.pages[0]
        return page.asarray(), json.loads(page.description)


def test_snap_sim_saves_frame_and_metadata(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "f.tif"
    rc = app.cli.main(["snap", "--camera", "sim", "--exposure", "10ms", "--out", str(out)])
    assert rc == 0
    printed = capsys.readouterr().out
    pixels, meta = _read_tiff(out)
    assert pixels.shape == (64, 80) and pixels.dtype == np.uint16
    assert "saved" in printed and "64x80 (HxW)" in printed  # rows first, as everywhere
    assert pixels.max() > 200  # the demo scene, not a dark frame
    assert meta["format"] == "lenslesscam-frame" and meta["exposure_us"] == 10_000.0
    assert meta["backend"] == "sim" and meta["timing"]["exposure_lines"] == 1000
    assert meta["sensor"] == [64, 80]  # the whole sensor, rows first
    assert meta["black_level"] == 100.0  # the simulated camera's dark offset: --dark auto's
    assert "provenance" in meta
    assert not [p for p in tmp_path.iterdir() if p.name != "f.tif"]  # no temp file left


def test_snap_genicam_and_v4l2(tmp_path: Path, tlsimu_cti: Path, png_sequence: str) -> None:
    out = tmp_path / "g.tif"
    argv = ["snap", "--camera", "genicam:0", "--producer", str(tlsimu_cti), "--out", str(out)]
    assert app.cli.main(argv) == 0
    pixels, meta = _read_tiff(out)
    assert meta["backend"] == "genicam" and meta["exposure_us"] is None
    assert pixels.dtype == np.uint8
    out2 = tmp_path / "v.tif"
    assert app.cli.main(["snap", "--camera", f"v4l2:{png_sequence}", "--out", str(out2)]) == 0
    pixels, meta = _read_tiff(out2)
    assert meta["backend"] == "v4l2" and pixels.dtype == np.uint16


def test_snap_errors_are_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], viky_cti: Path
) -> None:
    out = str(tmp_path / "x.tif")
    argv = ["snap", "--camera", "genicam:0", "--producer", str(viky_cti), "--exposure", "1ms"]
    assert app.cli.main([*argv, "--out", out]) == 2
    err = capsys.readouterr().err
    assert "feature 'exposure' is not available" in err and "Traceback" not in err
    assert app.cli.main(["snap", "--camera", "webcam", "--out", out]) == 2
    assert "unknown camera spec" in capsys.readouterr().err
    assert not Path(out).exists()


def test_parse_duration() -> None:
    assert parse_duration_us("10ms") == 10_000.0
    assert parse_duration_us("250us") == 250.0
    assert parse_duration_us("0.5s") == 500_000.0
    assert parse_duration_us("40") == 40.0
    for bad in ("ten ms", "-1ms", "0", "5 min"):
        with pytest.raises(argparse.ArgumentTypeError):
            parse_duration_us(bad)


def test_the_real_cli_registers_devices_and_snap(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.undo()  # the full command list, as installed
    parser = app.cli.build_parser()
    ns = parser.parse_args(["snap", "--camera", "sim", "--exposure", "2ms", "--out", "x.tif"])
    assert ns.func.__module__ == "app.commands.devices" and ns.exposure == 2000.0
    assert parser.parse_args(["devices", "--json"]).func.__module__ == "app.commands.devices"


@pytest.mark.parametrize("command", ["devices", "snap"])
def test_bad_producer_path_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str
) -> None:
    """An explicit --producer that is missing, or holds no .cti, is an error naming it."""
    not_cti = tmp_path / "notes.txt"
    not_cti.write_text("x")
    extra = ["--camera", "genicam:0", "--out", str(tmp_path / "f.tif")] if command == "snap" else []
    for bad, says in (
        (tmp_path / "missing.cti", "does not exist"),
        (not_cti, "is not a .cti producer"),
        (tmp_path, "holds no .cti file"),
    ):
        assert app.cli.main([command, *extra, "--producer", str(bad)]) == 2
        err = capsys.readouterr().err
        assert str(bad) in err and says in err and "Traceback" not in err
    assert not (tmp_path / "f.tif").exists()


@pytest.mark.parametrize("content", [b"", b"not a library at all\n"])
def test_a_cti_that_is_not_a_shared_library_is_refused_or_skipped(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch,
    tlsimu_cti: Path, content: bytes,
) -> None:
    """Any file named *.cti was listed and accepted as a GenTL producer."""
    fake = tmp_path / "fake" / "x.cti"
    fake.parent.mkdir()
    fake.write_bytes(content)
    says = "empty file" if not content else "not a shared library"
    # named explicitly (the file, or a folder holding only it): refused, one line
    for bad in (fake, fake.parent):
        assert app.cli.main(["devices", "--producer", str(bad)]) == 2
        err = capsys.readouterr().err
        assert str(bad) in err and says in err and "Traceback" not in err
        assert len(err.strip().splitlines()) == 1
    # found on the search path next to a real producer: skipped with its reason
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "empty-cache"))
    monkeypatch.delenv("LENSLESSCAM_GENTL_PATH", raising=False)
    monkeypatch.setenv("GENICAM_GENTL64_PATH", str(fake.parent))
    assert app.cli.main(["devices", "--producer", str(tlsimu_cti)]) == 0
    out = capsys.readouterr().out
    producers = out.split("GenTL producers:")[1].split("Serial ports:")[0]
    assert str(tlsimu_cti) in producers and "TLSimuMono" in out
    listed = [ln.strip() for ln in producers.splitlines() if ln.strip()]
    assert str(fake) not in listed
    assert any(str(fake) in ln and "skipped" in ln and says in ln for ln in listed)
    assert app.cli.main(["devices", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert str(fake) not in data["gentl_producers"]
    assert [str(fake) in ln for ln in data["gentl_skipped"]] == [True]


def test_a_camera_that_cannot_open_is_one_line(tmp_path: Path,
                                               capfd: pytest.CaptureFixture[str]) -> None:
    """OpenCV printed its own '[ WARN...]' line before the error."""
    assert app.cli.main(["snap", "--camera", "v4l2:/dev/null", "--out",
                         str(tmp_path / "v.tif")]) == 2
    err = capfd.readouterr().err
    assert err.strip().splitlines() == ["lenslesscam snap: error: cannot open v4l2 file "
                                        "'/dev/null'"]



def test_snap_refuses_a_non_tiff_name_and_a_missing_light_state(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--out x.png wrote a TIFF under a PNG name; a missing --light-state was taken silently."""
    assert app.cli.main(["snap", "--camera", "sim", "--out", str(tmp_path / "x.png")]) == 2
    assert "name it .tif" in capsys.readouterr().err
    assert app.cli.main(["snap", "--camera", "sim", "--light-state", str(tmp_path / "no.json"),
                         "--out", str(tmp_path / "x.tif")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


# --------------------------------------------------------------------------------------------
# the camera's own files are inputs; one reading of the spec; which camera it was


def _tiff_sequence(folder: Path, n: int = 3) -> list[Path]:
    folder.mkdir()
    files = []
    for i in range(n):
        f = folder / f"{i:04d}.tif"
        tifffile.imwrite(f, np.full((8, 10), 100 * (i + 1), dtype=np.uint16))
        files.append(f)
    return files


def test_snap_never_writes_over_a_frame_of_the_camera_sequence(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--camera 'v4l2:tseq/%04d.tif' --out tseq/0000.tif --overwrite replaced the first frame
    of the recording with a snapshot of it; --sim-psf X --out X was already refused."""
    files = _tiff_sequence(tmp_path / "tseq")
    before = [f.read_bytes() for f in files]
    pattern = str(tmp_path / "tseq" / "%04d.tif")
    (tmp_path / "link.tif").symlink_to(files[1])
    (tmp_path / "hard.tif").hardlink_to(files[2])
    for out in (files[0], files[2], tmp_path / "tseq" / "0007.tif", tmp_path / "link.tif",
                tmp_path / "hard.tif"):
        argv = ["snap", "--camera", f"v4l2:{pattern}", "--out", str(out), "--overwrite"]
        assert app.cli.main(argv) == 2
        err = capsys.readouterr().err
        assert err.strip().splitlines() == [
            f"lenslesscam snap: error: refusing to write {out}: it is the input --camera "
            f"v4l2:{pattern} of this command (choose another output name)"], err
    assert [f.read_bytes() for f in files] == before
    assert not (tmp_path / "tseq" / "0007.tif").exists()
    # another name is written, and the camera read the sequence
    out = tmp_path / "snap.tif"
    assert app.cli.main(["snap", "--camera", f"v4l2:{pattern}", "--out", str(out)]) == 0
    assert _read_tiff(out)[0].max() == 100
    capsys.readouterr()


def test_snap_never_writes_over_the_camera_video(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], ffv1_video: str) -> None:
    """A recorded video (here FFV1 in a file named .tif, the only name snap writes) became one
    TIFF frame with --out VIDEO --overwrite."""
    import shutil

    video = tmp_path / "recording.tif"
    shutil.copyfile(ffv1_video, video)
    before = video.read_bytes()
    argv = ["snap", "--camera", f" v4l2:{video} ", "--out", str(video), "--overwrite"]
    assert app.cli.main(argv) == 2
    err = capsys.readouterr().err
    assert f"refusing to write {video}: it is the input --camera v4l2:{video}" in err
    assert video.read_bytes() == before


def test_check_camera_command_outputs_takes_the_camera_files_as_inputs(tmp_path: Path) -> None:
    from app.commands.devices import check_camera_command_outputs

    video = tmp_path / "vid.mkv"
    video.write_bytes(b"not really a video")
    args = argparse.Namespace(camera=f"v4l2:{video}", overwrite=True)
    with pytest.raises(FileExistsError, match="it is the input --camera v4l2:"):
        check_camera_command_outputs(args, [str(video)])
    check_camera_command_outputs(args, [str(tmp_path / "other.tif")])
    for camera in ("sim", "v4l2:0", "v4l2:/dev/video3", "genicam:1"):  # no file read
        check_camera_command_outputs(argparse.Namespace(camera=camera, overwrite=True),
                                     [str(video)])


def test_a_camera_spec_with_spaces_is_the_same_camera(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """'sim ' opened a default SimulatedCamera (no scene, --sim-* ignored): _snap compared the
    spec unstripped while open_camera stripped it."""
    for spec in ("sim ", " sim", " SIM "):
        out = tmp_path / f"{spec.replace(' ', '_')}.tif"
        argv = ["snap", "--camera", spec, "--sim-size", "32x40", "--out", str(out)]
        assert app.cli.main(argv) == 0, spec
        capsys.readouterr()
        pixels, _meta = _read_tiff(out)
        assert pixels.shape == (32, 40), spec  # --sim-size was taken
        assert pixels.max() > 200, spec  # the demo scene, not a dark default camera


def test_sim_size_has_one_limit(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--sim-size 1x1 passed the 'at least 1x1' check, then the camera said 'at least 2x1'."""
    for size in ("1x1", "0x5", "1x80"):
        assert app.cli.main(["snap", "--sim-size", size, "--out", str(tmp_path / "f.tif")]) == 2
        err = capsys.readouterr().err.strip()
        assert err == (f"lenslesscam snap: error: --sim-size must be at least 2x1 pixels "
                       f"(HxW), got '{size}'")
    assert app.cli.main(["snap", "--sim-size", "2x1", "--out", str(tmp_path / "f.tif")]) == 0
    capsys.readouterr()


def test_snap_says_which_camera_it_was(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                       tlsimu_cti: Path) -> None:
    """genicam:N is a position in a list: the output named no device."""
    out = tmp_path / "g.tif"
    argv = ["snap", "--camera", "genicam:0", "--producer", str(tlsimu_cti), "--out", str(out)]
    assert app.cli.main(argv) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[-1].startswith("camera: genicam camera 0")
    assert "TLSimu" in lines[-1]


def test_calibrate_takes_producer_and_counts_genicam_cameras_as_devices_does(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch,
    tlsimu_cti: Path,
) -> None:
    """``genicam:N`` is the N-th camera of ``devices --producer CTI`` in every command.

    Before, ``calibrate`` had no ``--producer``: a camera of an extra producer could not be
    calibrated, and genicam:0 was another camera there than in ``snap --producer``.
    """
    from recon.calibfile import load_calibration

    monkeypatch.setattr(app.cli, "COMMAND_MODULES",
                        ("app.commands.devices", "app.commands.calibrate"))
    assert app.cli.main(["devices", "--json", "--producer", str(tlsimu_cti)]) == 0
    first = json.loads(capsys.readouterr().out)["cameras"][1]
    assert first["spec"] == "genicam:0"
    out = tmp_path / "d.npz"
    argv = ["calibrate", "darks", "--camera", "genicam:0", "--producer", str(tlsimu_cti),
            "--frames", "2", "--no-prompt", "--out", str(out)]
    assert app.cli.main(argv) == 0, capsys.readouterr().err
    model = load_calibration(out).metadata["camera"]["model"]
    assert model in first["description"] and model.startswith("TLSimu")
    # given where it would be ignored, it is refused in one line, in both commands
    for cmd, name in ((["calibrate", "darks", "--no-prompt"], "x.npz"), (["snap"], "x.tif")):
        rc = app.cli.main([*cmd, "--camera", "sim", "--producer", str(tlsimu_cti),
                           "--out", str(tmp_path / name)])
        err = capsys.readouterr().err
        assert rc == 2 and "--producer applies to --camera genicam" in err, err
        assert "Traceback" not in err
    assert not list(tmp_path.glob("x.*"))


def test_a_drivers_log_warning_is_one_prefixed_line_of_the_command(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Our packages' log warnings print as the command's own warnings do.

    Before, Python printed them bare (no handler): "v4l2:...: colour frames are reduced to
    grey ..." (or, in calibrate, "could not switch the point source off: ...") under the
    command's prefixed lines.
    """
    import cv2

    for i in range(2):  # a colour recording read by the V4L2/OpenCV path, reduced to grey
        img = np.zeros((12, 16, 3), np.uint8)
        img[..., 2] = 200 + i
        assert cv2.imwrite(str(tmp_path / f"{i:04d}.png"), img)
    out = tmp_path / "f.tif"
    argv = ["snap", "--camera", f"v4l2:{tmp_path}/%04d.png", "--out", str(out)]
    assert app.cli.main(argv) == 0
    said = [ln for ln in capsys.readouterr().err.splitlines() if "reduced to grey" in ln]
    assert len(said) == 1 and said[0].startswith("lenslesscam: warning: v4l2 file "), said
    assert out.exists()
    import logging

    # the command's handler is gone after it: nothing is printed twice in a second command
    assert not [h for n in ("app", "drivers", "recon", "calibration")
                for h in logging.getLogger(n).handlers]
