"""The calibration file formats in recon.calibfile: round trips and refusals."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import tifffile

from recon.calibfile import (
    load_calibration,
    load_psf_calibration,
    save_pixel_maps,
    save_psf_calibration,
    save_psf_stack,
    save_shutter,
)
from recon.formats import FORMAT_VERSION, FormatError

PSF_META = {
    "camera": {"backend": "sim"},
    "exposure_us": 100.0,
    "gain": 1.0,
    "frames_averaged": 4,
    "dark_level": 100.0,
    "timing": None,
    "quality": {"peak_adu": 1.0},
}


def _psf() -> np.ndarray:
    return np.random.default_rng(0).random((12, 10)).astype(np.float32)


def test_psf_round_trip_and_metadata(tmp_path):
    path = save_psf_calibration(tmp_path / "p.tif", _psf(), {**PSF_META, "note": np.float32(2)})
    psf, meta = load_psf_calibration(path)
    assert np.array_equal(psf, _psf())
    assert meta["format"] == "lenslesscam.psf-calibration"
    assert meta["format_version"] == FORMAT_VERSION and meta["kind"] == "psf"
    assert meta["date"] and meta["software_version"] and meta["provenance"]["versions"]
    assert meta["note"] == 2.0 and meta["shape"] == [12, 10]


def test_writers_check_their_input(tmp_path):
    meta = dict(PSF_META)
    del meta["quality"]
    with pytest.raises(ValueError, match="lacks quality"):
        save_psf_calibration(tmp_path / "p.tif", _psf(), meta)
    with pytest.raises(ValueError, match="reserved"):
        save_psf_calibration(tmp_path / "p.tif", _psf(), {**PSF_META, "format": "x"})
    with pytest.raises(ValueError, match="NaN"):
        save_psf_calibration(tmp_path / "p.tif", np.full((4, 4), np.nan), PSF_META)
    with pytest.raises(ValueError, match="negative"):
        save_psf_calibration(tmp_path / "p.tif", -_psf(), PSF_META)
    with pytest.raises(ValueError, match=r"\.tif"):
        save_psf_calibration(tmp_path / "p.png", _psf(), PSF_META)
    with pytest.raises(ValueError, match="one entry per plane"):
        save_psf_stack(
            tmp_path / "s.tif",
            np.ones((2, 4, 4)),
            {"camera": {}, "positions": ["a"], "planes": [{}], "timing": None},
        )
    with pytest.raises(ValueError, match="0 \\(bad\\) or 1"):
        z = np.zeros((4, 4))
        save_pixel_maps(
            tmp_path / "m.npz",
            mask=z + 0.5,
            dark_mean=z,
            dark_std=z,
            hot=z,
            dead=z,
            metadata={"camera": {}, "exposure_us": 1, "frames_averaged": 1, "thresholds": {}},
        )
    assert list(tmp_path.iterdir()) == []  # nothing half-written


def test_foreign_and_corrupt_files_are_refused(tmp_path):
    tifffile.imwrite(tmp_path / "foreign.tif", _psf())
    with pytest.raises(FormatError, match="not a lenslesscam calibration"):
        load_calibration(tmp_path / "foreign.tif")
    tifffile.imwrite(tmp_path / "other.tif", _psf(), description=json.dumps({"format": "x"}))
    with pytest.raises(FormatError, match="format 'x'"):
        load_calibration(tmp_path / "other.tif")
    np.savez(tmp_path / "plain.npz", a=np.ones(3))
    with pytest.raises(FormatError, match="no metadata"):
        load_calibration(tmp_path / "plain.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(FormatError, match="cannot read"):
        load_calibration(tmp_path / "junk.npz")
    with pytest.raises(FileNotFoundError):
        load_calibration(tmp_path / "missing.tif")
    with pytest.raises(FormatError, match=r"\.tif/\.tiff or \.npz"):
        (tmp_path / "x.txt").write_text("x")
        load_calibration(tmp_path / "x.txt")

    # a PSF whose pixels changed after writing
    path = save_psf_calibration(tmp_path / "p.tif", _psf(), PSF_META)
    with tifffile.TiffFile(path) as tf:
        desc = tf.pages.first.description
    tifffile.imwrite(tmp_path / "tampered.tif", _psf() + 1, description=desc, metadata=None)
    with pytest.raises(FormatError, match="hash"):
        load_calibration(tmp_path / "tampered.tif")
    # a newer format version
    meta = json.loads(desc)
    meta["format_version"] = FORMAT_VERSION + 1
    tifffile.imwrite(tmp_path / "newer.tif", _psf(), description=json.dumps(meta), metadata=None)
    with pytest.raises(FormatError, match="not supported"):
        load_calibration(tmp_path / "newer.tif")
    # the wrong kind
    with pytest.raises(FormatError, match="expected a shutter"):
        load_calibration(path, expect="shutter")


def test_shutter_npz_round_trip_and_tamper(tmp_path):
    m = np.random.default_rng(1).random((5, 8)).astype(np.float32)
    meta = {"timing": {"rows": 8}, "bin_lines": 2, "row_factor": 1, "method": "timing"}
    path = save_shutter(tmp_path / "s.npz", m, meta, {"delays_us": np.arange(3.0)})
    cal = load_calibration(path)
    assert cal.kind == "shutter" and np.array_equal(cal.data, m)
    assert np.array_equal(cal.arrays["delays_us"], np.arange(3.0))
    # rewrite the archive with a changed array but the old metadata
    with zipfile.ZipFile(path) as z:
        members = {n: z.read(n) for n in z.namelist()}
    bad = tmp_path / "bad.npz"
    np.savez(bad, shutter=m * 2, delays_us=np.arange(3.0), metadata=np.load(path)["metadata"])
    with pytest.raises(FormatError, match="hash"):
        load_calibration(bad)
    assert "metadata.npy" in members


def test_depth_stack_round_trip(tmp_path: Path):
    stack = np.random.default_rng(2).random((3, 6, 7)).astype(np.float32)
    meta = {"camera": {}, "positions": ["a", "b", "c"], "planes": [{}, {}, {}], "timing": None}
    cal = load_calibration(save_psf_stack(tmp_path / "s.tif", stack, meta))
    assert cal.kind == "psf-stack" and np.array_equal(cal.data, stack)
