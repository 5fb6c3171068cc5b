"""Erased pixels (mask 0) hold no data: whatever a file holds there must not set the
measurement's scale nor count in the residual. A hot pixel at 1000 that ``calibrate darks``
masks made the measurement's maximum, so the measured pixels were scaled to about 1e-3 and
FISTA's residual read 0.999 (17.1 -> 11.5 dB on a simulated case, no warning)."""

from __future__ import annotations

import numpy as np
import pytest

from recon.problem import ProblemSpec, load_problem
from recon.simulate import synthetic_psf


@pytest.fixture
def files(tmp_path):
    rng = np.random.default_rng(3)
    np.save(tmp_path / "psf.npy", synthetic_psf((24, 32), seed=1))
    meas = (0.2 + 0.5 * rng.random((24, 32))).astype(np.float32)
    erased = [(5, 7), (10, 10), (11, 10), (10, 11), (11, 11)]
    mask = np.ones((24, 32), np.float32)
    for yx in erased:
        mask[yx] = 0
    np.save(tmp_path / "mask.npy", mask)
    coarse = np.ones((12, 16), np.float32)
    coarse[2, 3] = coarse[5, 5] = 0  # over every erased sensor pixel
    np.save(tmp_path / "coarse_mask.npy", coarse)
    for name, value in (("cold", 0.0), ("hot", 1000.0)):
        m = meas.copy()
        for yx in erased:
            m[yx] = value
        np.save(tmp_path / f"{name}.npy", m)
    return tmp_path


@pytest.mark.parametrize(("mask", "ds"), [("mask", 1), ("mask", 2), ("coarse_mask", 2)])
def test_what_erased_pixels_hold_changes_nothing(files, mask, ds):
    def load(name):
        spec = ProblemSpec(psf=str(files / "psf.npy"), meas=str(files / f"{name}.npy"),
                           mask=str(files / f"{mask}.npy"), downsample=ds, dark=0.0)
        return load_problem(spec)

    cold, hot = load("cold"), load("hot")
    m = cold.mask > 0
    assert m.sum() < m.size  # erased pixels there are
    assert float(hot.meas.max()) == pytest.approx(float(cold.meas.max()))  # the scale
    np.testing.assert_allclose(hot.meas[:, m], cold.meas[:, m], rtol=1e-6)
    assert not np.any(hot.meas[:, ~m])  # erased: 0
