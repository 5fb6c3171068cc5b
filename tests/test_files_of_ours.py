"""Files of ours read as inputs keep their checks: a newer format version or pixels that fail
their hash are refused in one line, whichever command reads them.

Found by a hostile review: a PSF calibration TIFF, a pixel-maps ``.npz`` given as ``--dark``
and a reconstruction TIFF given to ``metrics`` were read as plain images when their metadata
said a newer version (or their pixels no longer matched their hash), and used silently.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import tifffile

from recon.calibfile import save_pixel_maps, save_psf_calibration
from recon.io import save_reconstruction
from tests.clirun import run_cli

H, W = 16, 20
PSF_META = {"camera": {"backend": "sim"}, "exposure_us": 100.0, "gain": 1.0,
            "frames_averaged": 4, "dark_level": 100.0, "timing": None,
            "quality": {"peak_adu": 1.0}}


def _tiff_meta(path, **changes):
    """A copy of a TIFF of ours with its metadata changed (pixels kept)."""
    with tifffile.TiffFile(path) as tf:
        meta = json.loads(tf.pages.first.description)
        data = tf.asarray()
    meta.update(changes)
    return data, meta


def _write(path, data, meta):
    tifffile.imwrite(path, data, description=json.dumps(meta))


@pytest.fixture
def inputs(tmp_path):
    rng = np.random.default_rng(0)
    psf = (rng.random((H, W)) ** 8).astype(np.float32)
    save_psf_calibration(tmp_path / "psf.tif", psf, PSF_META)
    data, meta = _tiff_meta(tmp_path / "psf.tif", format_version=9)
    _write(tmp_path / "psf_v9.tif", data, meta)
    data, meta = _tiff_meta(tmp_path / "psf.tif")
    _write(tmp_path / "psf_bad.tif", data[::-1].copy(), meta)  # rows changed, metadata kept
    np.save(tmp_path / "meas.npy", 100 + 50 * rng.random((H, W)).astype(np.float32))
    z = np.zeros((H, W), np.float32)
    pm = {"mask": z + 1, "dark_mean": z + 100, "dark_std": z + 1, "hot": z, "dead": z,
          "metadata": {"camera": {}, "exposure_us": 1, "frames_averaged": 1, "thresholds": {}}}
    save_pixel_maps(tmp_path / "pm.npz", **pm)
    with np.load(tmp_path / "pm.npz") as f:
        arrays = {k: f[k] for k in f.files}
    meta = json.loads(str(arrays["metadata"]))
    np.savez(tmp_path / "pm_v9.npz", **{**arrays, "metadata": np.array(json.dumps(
        {**meta, "format_version": 9}))})
    np.savez(tmp_path / "pm_bad.npz", **{**arrays, "dark_mean": arrays["dark_mean"] + 7})
    return tmp_path


def _one_line(code, err):
    assert code == 2, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    return lines[0]


@pytest.mark.parametrize(("name", "words"), [
    ("psf_v9.tif", "format_version 9 is not supported by this release"),
    ("psf_bad.tif", "does not match its hash; the file is corrupt"),
])
def test_a_newer_or_corrupt_psf_calibration_is_refused_by_every_reader(inputs, capsys, name,
                                                                        words):
    d = inputs
    code, _, err = run_cli(capsys, "recon", "fista", "--psf", d / "psf.tif", "--meas",
                           d / "meas.npy", "--dark", "100", "--tau", "1e-3", "--iters", "3",
                           "--out", d / "ok.tif")
    assert code == 0, err  # the file as written reads
    for argv in (["recon", "fista", "--meas", d / "meas.npy", "--dark", "100", "--tau",
                  "1e-3", "--iters", "3", "--out", d / "x.tif"],
                 ["simulate", "--scene", "sample:im408", "--out", d / "sim"],
                 ["plan", "--meas", d / "meas.npy", "--no-probe", "--out", d / "p.json"]):
        code, _, err = run_cli(capsys, *argv, "--psf", d / name)
        line = _one_line(code, err)
        assert name in line and words in line, line
    assert not (d / "x.tif").exists() and not (d / "sim").exists()
    from recon.readers import load_psf_any

    with pytest.raises(ValueError, match=words):
        load_psf_any(d / name)  # the app's PSF loader


@pytest.mark.parametrize(("name", "words"), [
    ("pm_v9.npz", "format_version 9 is not supported by this release"),
    ("pm_bad.npz", "array 'dark_mean' does not match its hash"),
])
def test_a_newer_or_corrupt_pixel_maps_file_as_dark_is_refused(inputs, capsys, name, words):
    d = inputs
    code, _, err = run_cli(capsys, "recon", "fista", "--psf", d / "psf.tif", "--meas",
                           d / "meas.npy", "--dark", d / "pm.npz", "--tau", "1e-3",
                           "--iters", "3", "--out", d / "ok.tif")
    assert code == 0, err
    code, _, err = run_cli(capsys, "recon", "fista", "--psf", d / "psf.tif", "--meas",
                           d / "meas.npy", "--dark", d / name, "--tau", "1e-3", "--iters", "3",
                           "--out", d / "x.tif")
    line = _one_line(code, err)
    assert name in line and words in line, line


def test_metrics_refuses_a_newer_or_corrupt_reconstruction(tmp_path, capsys):
    x = np.random.default_rng(0).random((1, 1, H, W)).astype(np.float32)
    save_reconstruction(tmp_path / "r.tif", x, {}, kind="image")
    np.save(tmp_path / "truth.npy", x[0, 0])
    code, out, err = run_cli(capsys, "metrics", "--ref", tmp_path / "truth.npy", "--est",
                             tmp_path / "r.tif")
    assert code == 0, err
    data, meta = _tiff_meta(tmp_path / "r.tif", format_version=9)
    _write(tmp_path / "r9.tif", data, meta)
    data, meta = _tiff_meta(tmp_path / "r.tif")
    _write(tmp_path / "rbad.tif", np.ones_like(data), meta)
    for name, words in (("r9.tif", "format_version 9 is not supported by this release"),
                        ("rbad.tif", "data hash does not match its metadata")):
        code, _, err = run_cli(capsys, "metrics", "--ref", tmp_path / "truth.npy", "--est",
                               tmp_path / name)
        line = _one_line(code, err)
        assert words in line, line
    # a plain TIFF of no format of ours is still an image to score
    tifffile.imwrite(tmp_path / "plain.tif", x[0, 0])
    code, out, err = run_cli(capsys, "metrics", "--ref", tmp_path / "truth.npy", "--est",
                             tmp_path / "plain.tif")
    assert code == 0, err
    assert json.loads(out)["mse"] == 0.0
