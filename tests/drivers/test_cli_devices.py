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
