"""``lenslesscam metrics`` between two reconstructions: their geometries must agree.

Two lenslesscam reconstructions of equal array shape can cover different scene points (the
sensor field at downsample 1 and the 2x field at downsample 2; two regions of one field):
metrics printed a PSNR for them without a word. It now compares what their metadata say
(scene field, total downsampling, region, colour, row flip, channel order) and refuses a
difference in one line, unless --ref-as-is asks for the comparison as stored.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.clirun import run_cli as _run


@pytest.fixture()
def files(tmp_path):
    import torch

    from recon.models import build_model
    from recon.simulate import synthetic_psf
    from tests.scenes import blocks_scene

    h, w = 24, 32
    psf = synthetic_psf((h, w), seed=2)
    scene = blocks_scene(2 * h, 2 * w, seed=1).astype(np.float32)
    full = build_model("2d", psf, field=(2 * h, 2 * w)).apply(
        torch.as_tensor(scene[None, None])).numpy()
    np.save(tmp_path / "psf.npy", psf)
    np.save(tmp_path / "meas.npy", np.ascontiguousarray(full[0]))
    return tmp_path


def _recon(capsys, d, out, *extra, method="auto"):
    args = ["recon", method, "--psf", d / "psf.npy", "--meas", d / "meas.npy", "--tau", "1e-3"]
    if method == "auto":
        args += ["--set", "iterations=10", "--quiet"]
    else:
        args += ["--iters", "10"]
    code, _, err = _run(capsys, *args, *extra, "--out", d / out)
    assert code == 0, err
    return d / out


def test_reconstructions_of_other_geometry_are_refused_with_the_difference(files, capsys):
    # the same 24x32 array: the sensor field at downsample 1, the 2x field at downsample 2
    sensor = _recon(capsys, files, "sensor.tif", method="fista")
    full = _recon(capsys, files, "full.tif", "--field", "full", "--set", "downsample=2",
                  "--set", "region=[0,0,48,64]")
    code, out, err = _run(capsys, "metrics", "--ref", sensor, "--est", full)
    assert code == 2 and out == ""
    line = err.strip()
    assert "\n" not in line and "different geometry" in line
    assert "scene field 24x32 vs 48x64" in line and "downsampling 1 vs 2" in line
    # asked for, it is compared as stored, and the JSON says what differs
    code, out, err = _run(capsys, "metrics", "--ref", sensor, "--est", full, "--ref-as-is")
    assert code == 0, err
    report = json.loads(out)
    assert "downsampling 1 vs 2" in report["geometry_differs"] and "psnr" in report


def test_two_recon_auto_regions_of_one_field_are_refused(files, capsys):
    a = _recon(capsys, files, "a.tif", "--set", "region=[0,0,12,16]")
    b = _recon(capsys, files, "b.tif", "--set", "region=[12,16,12,16]")
    code, _, err = _run(capsys, "metrics", "--ref", a, "--est", b)
    assert code == 2
    assert "region (full-resolution px of the field) 12x16 at (0, 0) vs 12x16 at (12, 16)" in err
    assert "scene field" not in err and "downsampling" not in err  # only what differs


def test_reconstructions_of_the_same_geometry_are_scored(files, capsys):
    """recon fista at downsample 2 and recon auto with the plan's downsample 2: the same
    pixels (the loader's and the plan's downsampling multiply), so no refusal."""
    fista = _recon(capsys, files, "f.tif", "--downsample", "2", method="fista")
    auto = _recon(capsys, files, "a.tif", "--set", "downsample=2")
    from app.commands.metrics import _geometry
    from recon.io import read_reconstruction

    geo_f = _geometry(read_reconstruction(fista)[1])
    geo_a = _geometry(read_reconstruction(auto)[1])
    assert geo_f == geo_a == {"field": [24, 32], "downsample": 2, "region": [0, 0, 24, 32],
                              "color": "gray", "flip_rows": False}
    code, out, err = _run(capsys, "metrics", "--ref", fista, "--est", auto)
    assert code == 0, err
    assert "geometry_differs" not in json.loads(out)


def test_a_row_flip_or_channel_order_is_a_difference_too(tmp_path, capsys):
    from recon.io import save_reconstruction

    x = np.random.default_rng(0).random((3, 1, 8, 10)).astype(np.float32)
    pre = {"downsample": 1, "color": "rgb", "channel_order": "rgb", "flip_rows": False,
           "field": [8, 10]}
    save_reconstruction(tmp_path / "a.tif", x, {"preprocessing": pre}, kind="image")
    save_reconstruction(tmp_path / "b.tif", x, {"preprocessing": {
        **pre, "channel_order": "bgr", "flip_rows": True}}, kind="image")
    code, _, err = _run(capsys, "metrics", "--ref", tmp_path / "a.tif", "--est",
                        tmp_path / "b.tif")
    assert code == 2
    assert "rows flipped False vs True" in err and "channel order rgb vs bgr" in err
    # a file whose metadata does not record its field is compared as before
    save_reconstruction(tmp_path / "c.tif", x, {}, kind="image")
    code, out, err = _run(capsys, "metrics", "--ref", tmp_path / "a.tif", "--est",
                          tmp_path / "c.tif")
    assert code == 0, err
    assert json.loads(out)["mse"] == 0.0


def test_a_remainder_the_downsampling_drops_is_no_difference(tmp_path, capsys):
    """A 26x34 frame at downsample 4: recon fista records the 24x32 it covers, recon auto the
    26x34 field; both results are the same 6x8 grid and are compared, not refused."""
    import torch

    from recon.models import build_model
    from recon.simulate import synthetic_psf
    from tests.scenes import blocks_scene

    h, w = 26, 34
    psf = synthetic_psf((h, w), seed=2)
    b = build_model("2d", psf).apply(torch.as_tensor(
        blocks_scene(h, w, seed=1).astype(np.float32)[None, None])).numpy()[0]
    np.save(tmp_path / "psf.npy", psf)
    np.save(tmp_path / "meas.npy", b)
    import warnings

    from recon.checks import MeasurementWarning

    with warnings.catch_warnings():  # said on stderr, not raised (pytest's filter: error)
        warnings.simplefilter("default", MeasurementWarning)
        code, _, err = _run(capsys, "recon", "fista", "--psf", tmp_path / "psf.npy", "--meas",
                            tmp_path / "meas.npy", "--tau", "1e-3", "--iters", "10",
                            "--downsample", "4", "--out", tmp_path / "f.tif")
    assert code == 0, err
    assert "downsampling 4x drops the last 2 rows and 2 columns of the 26x34" in err
    fista = tmp_path / "f.tif"
    with warnings.catch_warnings():  # recon auto says it too (was silent)
        warnings.simplefilter("default", MeasurementWarning)
        code, _, err = _run(capsys, "recon", "auto", "--psf", tmp_path / "psf.npy", "--meas",
                            tmp_path / "meas.npy", "--tau", "1e-3", "--set", "iterations=10",
                            "--quiet", "--set", "downsample=4", "--out", tmp_path / "a.tif")
    assert code == 0, err
    assert "downsampling 4x drops the last 2 rows and 2 columns of the 26x34" in err
    auto = tmp_path / "a.tif"
    code, out, err = _run(capsys, "metrics", "--ref", fista, "--est", auto)
    assert code == 0, err
    assert "geometry_differs" not in json.loads(out)
