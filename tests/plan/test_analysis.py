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
from recon.samples import dlmd_pair_paths, tutorial_psf


def test_resolution_from_autocorrelation_width():
    sharp = psf_resolution(make_psf(48, 64, blur=1.0))
    assert sharp.factor == 1 and 2.5 < min(sharp.fwhm_y, sharp.fwhm_x) < 4.0
    wide = psf_resolution(make_psf(48, 64, blur=2.2))
    # a Gaussian blur of sigma 2.2 has an autocorrelation 7.3 px wide; on a 48x64 frame the
    # envelope's removal (sigma 6 px) trims its tails a little
    assert 5.5 < min(wide.fwhm_y, wide.fwhm_x) < 8.5 and wide.factor == 3
    # the bundled (already downsampled) DiffuserCam PSF: about 4-5 px, keep full resolution
    real = psf_resolution(tutorial_psf())
    assert 3.0 < real.fwhm_x < 6.0 and real.factor in (1, 2)


def test_resolution_ignores_the_psf_envelope():
    """Vignetting or a padded grid changes the caustic's extent, not the detail it resolves."""
    yy, xx = np.mgrid[:120, :160]
    caustic = make_psf(120, 160, blur=1.0)
    vignetted = caustic * np.exp(-(((yy - 60) / 45.0) ** 2 + ((xx - 80) / 60.0) ** 2))
    padded = np.zeros((240, 320))
    padded[60:180, 80:240] = vignetted
    plain = psf_resolution(caustic)
    for psf in (vignetted, padded):
        r = psf_resolution(psf)
        assert r.factor == plain.factor == 1, r
        assert abs(min(r.fwhm_y, r.fwhm_x) - min(plain.fwhm_y, plain.fwhm_x)) < 1.0
    # the real MirFlickr PSF at 1/4 scale (134x240 padded grid): caustics about 3-5 px wide;
    # without the envelope's removal the peak measured 12.6 x 18.2 px (downsample 6)
    bgr = np.load(dlmd_pair_paths()["psf"]).astype(np.float64)
    real = psf_resolution(bgr.transpose(2, 0, 1), sensor=(67, 120))
    assert real.factor == 1 and min(real.fwhm_y, real.fwhm_x) < 4.0, real


def test_resolution_is_capped_by_sensor_size():
    r = psf_resolution(make_psf(40, 40, blur=6.0), min_size=16)
    assert r.factor == 2 and "sensor size" in r.limited_by
    # a PSF on a padded grid: the cap is the sensor's (40x40 here), not the grid's (80x80)
    padded = np.zeros((80, 80))
    padded[20:60, 20:60] = make_psf(40, 40, blur=6.0)
    assert psf_resolution(padded, min_size=16).factor > 2
    assert psf_resolution(padded, min_size=16, sensor=(40, 40)).factor == 2


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


def test_make_plan_caps_the_downsampling_on_the_real_sensor():
    """A padded-grid PSF with the full field: the plan's grid is the padded one (64x64), but
    the sensor is 32x32; the factor keeps 16 px of the sensor, not of the grid."""
    from recon.plan import make_plan

    psf = make_psf(64, 64, blur=6.0)
    meas = np.random.default_rng(0).random((64, 64)).astype(np.float32)
    loose = make_plan(psf, meas, field=(64, 64), probe=False)
    assert loose.downsample > 2
    capped = make_plan(psf, meas, field=(64, 64), sensor=(32, 32), probe=False)
    assert capped.downsample == 2 and "sensor size" in capped.reasons["downsample"]
