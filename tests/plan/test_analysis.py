"""Scene analysis pieces: resolution, folds, candidate K, selection rule, shutter scaling."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.plan_cases import make_psf
from drivers.timing import SensorTiming
from recon.plan.analysis import (
    candidate_factors,
    cv_select,
    heldout_folds,
    normalised_shutter,
    psf_resolution,
    video_tv,
)
from recon.samples import tutorial_psf


def test_resolution_from_autocorrelation_width():
    sharp = psf_resolution(make_psf(48, 64, blur=1.0))
    assert sharp.factor == 1 and 2.5 < min(sharp.fwhm_y, sharp.fwhm_x) < 4.0
    wide = psf_resolution(make_psf(48, 64, blur=2.2))
    assert 6.5 < min(wide.fwhm_y, wide.fwhm_x) < 9.0 and wide.factor == 3
    # the bundled (already downsampled) DiffuserCam PSF: about 4-5 px, keep full resolution
    real = psf_resolution(tutorial_psf())
    assert 3.0 < real.fwhm_x < 6.0 and real.factor in (1, 2)


def test_resolution_is_capped_by_sensor_size():
    r = psf_resolution(make_psf(40, 40, blur=6.0), min_size=16)
    assert r.factor == 2 and "sensor size" in r.limited_by


def test_constant_psf_is_refused():
    with pytest.raises(ValueError, match="constant"):
        psf_resolution(np.ones((16, 16)))


def test_folds_partition_the_pixels():
    folds = heldout_folds((12, 10), 4, seed=3)
    total = np.sum(folds, axis=0)
    assert np.all(total == 1) and all(abs(f.sum() - 30) <= 1 for f in folds)
    with pytest.raises(ValueError):
        heldout_folds((4, 4), 1)


def test_candidate_k_and_normalised_shutter():
    timing = SensorTiming(rows=48, line_time_us=10.0, exposure_lines=13, pattern="outside-in")
    base = timing.shutter(1)
    assert base.shape[0] == 36
    ks = [-(-36 // f) for f in candidate_factors(36, 32)]
    assert ks == [1, 2, 3, 4, 6, 8, 12, 18]
    for f in (36, 9, 1):
        m = normalised_shutter(base, f)
        np.testing.assert_allclose(m.sum(axis=0), 1.0, rtol=1e-12)  # every row exposed alike
    tau, tv = video_tv(6, 1e-3)
    assert tau == pytest.approx(1e-3 / 6) and tv.weight_k == pytest.approx(0.6)


def test_cv_select_takes_the_simplest_candidate_within_tolerance():
    rng = np.random.default_rng(0)
    base = rng.random(2000)
    errors = [("a", 1, base * 1.5, {}), ("b", 2, base * 1.03, {}), ("c", 4, base, {})]
    chosen, table = cv_select(errors, rel_tol=0.05, z_max=0.0)
    assert chosen == 1 and table[2].rel == 0.0 and table[0].rel == pytest.approx(0.5)
    chosen, _ = cv_select(errors, rel_tol=0.0, z_max=0.0)
    assert chosen == 2
