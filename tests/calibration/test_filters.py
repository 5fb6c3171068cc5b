"""Filter cubes: load MAT/NPY/TIFF, validate against the sensor, normalise, save."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.io
import tifffile

from calibration.filters import load_filter_cube, validate_filter_cube
from recon.calibfile import load_filter_cube_file
from recon.models import build_model


def _cube(k: int = 6, h: int = 16, w: int = 20) -> np.ndarray:
    return np.random.default_rng(0).uniform(0.0, 4.0, (k, h, w)).astype(np.float32)


@pytest.mark.parametrize("kind", ["npy", "mat", "tif"])
def test_load_validate_normalise_save(kind, tmp_path):
    cube = _cube()
    path = tmp_path / f"cube.{kind}"
    if kind == "npy":
        np.save(path, cube)
    elif kind == "mat":
        scipy.io.savemat(path, {"mask": np.moveaxis(cube, 0, -1)})  # (H, W, K) as in MATLAB
    else:
        tifffile.imwrite(path, cube)
    fc = load_filter_cube(
        path,
        (16, 20),
        key="mask" if kind == "mat" else None,
        wavelengths_nm=[450, 500, 550, 600, 650, 700],
    )
    assert fc.cube.shape == (6, 16, 20) and fc.cube.dtype == np.float32
    assert float(fc.cube.max()) == pytest.approx(1.0)
    assert np.allclose(fc.cube, cube / cube.max(), atol=1e-6)
    saved = fc.save(tmp_path / "out.tif")
    data, meta = load_filter_cube_file(saved.path)
    assert np.array_equal(data, fc.cube)
    assert meta["normalisation"]["mode"] == "max" and meta["wavelengths_nm"][0] == 450
    build_model("spectral", np.ones((16, 20)) / 320, filters=data)  # usable as M_k


def test_downsampled_cube(tmp_path):
    big = np.repeat(np.repeat(_cube(), 2, axis=1), 2, axis=2)
    np.save(tmp_path / "big.npy", big)
    fc = load_filter_cube(tmp_path / "big.npy", (16, 20), downsample=2)
    assert fc.cube.shape == (6, 16, 20)
    # a factor that does not fit the sensor is said so (it said "has bands of (10, 1)")
    with pytest.raises(ValueError, match=r"is not the 16x20 sensor at 3x: its bands must be "
                                         r"48x60"):
        load_filter_cube(tmp_path / "big.npy", (16, 20), downsample=3)


def test_validation_names_the_problem():
    cube = _cube()
    with pytest.raises(ValueError, match="does not match the 16x21 sensor"):
        validate_filter_cube(cube, (16, 21))
    bad = cube.copy()
    bad[1, 2, 3] = np.nan
    bad[2, 2, 3] = np.inf
    with pytest.raises(ValueError, match="2 NaN or infinite"):
        validate_filter_cube(bad, (16, 20))
    neg = cube.copy()
    neg[0, 0, 0] = -0.5
    with pytest.raises(ValueError, match="negative transmissions"):
        validate_filter_cube(neg, (16, 20))
    empty = cube.copy()
    empty[3] = 0
    with pytest.raises(ValueError, match=r"bands \[3\] are all zero"):
        validate_filter_cube(empty, (16, 20))
    with pytest.raises(ValueError, match="3 axes"):
        validate_filter_cube(np.ones((2, 2, 16, 20)), (16, 20))
    # a cube that fits both layouts is not guessed: the caller says which
    square = np.random.default_rng(0).random((4, 4, 4)) + 0.1
    with pytest.raises(ValueError, match=r"as \(K, H, W\) and as \(H, W, K\)"):
        validate_filter_cube(square, (4, 4))
    assert validate_filter_cube(square, (4, 4), layout="hwk").shape == (4, 4, 4)


def test_unnormalised_cube_must_be_in_range(tmp_path):
    np.save(tmp_path / "c.npy", _cube())
    with pytest.raises(ValueError, match="above 1"):
        load_filter_cube(tmp_path / "c.npy", (16, 20), normalise="none")
    np.save(tmp_path / "ok.npy", _cube() / 8)
    fc = load_filter_cube(tmp_path / "ok.npy", (16, 20), normalise="none")
    assert fc.metadata["normalisation"]["factor"] == 1.0
