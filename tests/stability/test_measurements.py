"""Extreme measurements: all zero, saturated, negative after dark subtraction, values near the
float16 range (raw counts ~6e4, PSF values ~1e-8), and scales no float32 solve can take."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from recon.admm import Admm
from recon.fista import Fista, NumericalError
from recon.io import (
    MeasurementWarning,
    check_measurement,
    clip_nonneg,
    load_measurement,
    load_psf,
    subtract_dark,
)
from recon.metrics import gain_fit, psnr
from recon.models import build_model
from recon.simulate import simulate
from recon.tv import TV
from tests.stability.helpers import blocks, psf2d, rel, sane, tiny_models

# -- all-zero measurement ---------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["2d", "2d_erasures", "video", "spectral", "depth"])
def test_all_zero_measurement_gives_exactly_zero(kind):
    model = build_model("2d", psf2d()) if kind == "2d" else tiny_models()[kind]
    b = torch.zeros(model.meas_shape)
    tv = TV(weight_k=0.5 if model.k > 1 else 0.0)
    res = Fista(model.op, b, tau=1e-2, tv=tv, max_iter=30).run()
    assert bool(torch.isfinite(res.x).all()) and float(res.x.abs().max()) == 0.0
    assert all(s.objective == 0.0 and s.residual == 0.0 for s in res.history)
    if model.k == 1:
        adm = Admm(model, b, tau=1e-2, max_iter=30).run()
        assert bool(torch.isfinite(adm.x).all()) and float(adm.x.abs().max()) == 0.0


def test_all_zero_file_is_refused_only_when_normalising(tmp_path):
    p = tmp_path / "zero.npy"
    np.save(p, np.zeros((16, 16), np.uint16))
    with pytest.raises(ValueError, match="all zero; cannot normalise"):
        load_measurement(p)
    raw = load_measurement(p, normalise=None)
    assert raw.shape == (1, 16, 16) and not raw.any()
    assert check_measurement(raw).flags == ("all_zero",)


# -- saturation -------------------------------------------------------------------------------


def test_simulated_saturation_is_flagged():
    model = build_model("2d", psf2d())
    sim = simulate(model, blocks()[None, None], saturation=0.8, noise=0.01, seed=1)
    assert sim.saturated > 0
    assert sim.params["saturated"] == sim.saturated
    assert sim.params["saturated_fraction"] == pytest.approx(sim.saturated / sim.meas.size)
    assert sim.saturated_fraction == sim.params["saturated_fraction"]
    check = check_measurement(sim.meas, full_scale=0.8)
    assert check.flagged and "saturated" in check.flags
    assert check.saturated == sim.saturated
    assert check.to_dict()["saturated_fraction"] == pytest.approx(sim.saturated_fraction)
    # the solver still gives a sane result on it
    res = Fista(model.op, torch.as_tensor(sim.meas), tau=1e-3, max_iter=50).run()
    sane(res.x)
    clean = simulate(model, blocks()[None, None], noise=0.01, seed=1)
    assert clean.saturated == 0 and clean.params["saturated"] == 0
    assert "saturated" not in check_measurement(clean.meas, full_scale=1.5).flags


def test_full_scale_raw_frames_are_flagged():
    rng = np.random.default_rng(0)
    frame = rng.integers(100, 60000, (20, 30)).astype(np.uint16)
    assert not check_measurement(frame).flagged  # uint16: full scale 65535
    frame[3, 4:9] = 65535
    check = check_measurement(frame)
    assert check.flags == ("saturated",) and check.saturated == 5
    assert check.saturated_fraction == pytest.approx(5 / 600)
    assert check.full_scale == 65535.0
    # a 12-bit camera in a uint16 container
    frame12 = rng.integers(0, 4000, (20, 30)).astype(np.uint16)
    frame12[0, 0] = 4095
    assert check_measurement(frame12).saturated == 0
    assert check_measurement(frame12, bits=12).saturated == 1
    # erased pixels are not counted
    mask = np.ones((20, 30))
    mask[3, 4:6] = 0
    assert check_measurement(frame, mask=mask).saturated == 3
    with pytest.warns(MeasurementWarning, match="5 pixels .* saturated"):
        check_measurement(frame, warn=True)
    # float data: saturation is checked only against a given full scale
    assert check_measurement(frame.astype(np.float32)).saturated == 0
    assert check_measurement(frame.astype(np.float32) / 65535, full_scale=1.0).saturated == 5


# -- negative values after dark subtraction ---------------------------------------------------


def _dark_case():
    model = build_model("2d", psf2d())
    truth = blocks()[None, None]
    sim = simulate(model, truth, noise=0.0, seed=2)
    rng = np.random.default_rng(4)
    dark = 0.05 + 0.02 * rng.standard_normal(sim.meas.shape)
    raw = sim.meas + dark + 0.02 * rng.standard_normal(sim.meas.shape)
    return model, truth, subtract_dark(raw, 0.05).astype(np.float32)


def test_negative_values_after_dark_subtraction():
    model, truth, meas = _dark_case()
    check = check_measurement(meas)
    assert "negative" in check.flags and check.negative > 0
    clipped = clip_nonneg(meas)
    assert clipped.min() == 0.0 and not check_measurement(clipped).flagged
    scores = {}
    for name, b in (("raw", meas), ("clipped", clipped)):
        bt = torch.as_tensor(b)
        res = Fista(model.op, bt, tau=3e-3, max_iter=200).run()
        sane(res.x)
        adm = Admm(model, bt, tau=3e-3, max_iter=200).run()
        sane(adm.x)
        scores[name] = psnr(truth[0, 0], gain_fit(truth[0, 0], res.x.numpy()[0, 0])[0])
    # both are real reconstructions, and clipping changes little
    assert min(scores.values()) > 15 and abs(scores["raw"] - scores["clipped"]) < 2, scores


def test_all_negative_measurement():
    model = build_model("2d", psf2d())
    b = -torch.rand(model.meas_shape) - 0.01
    res = Fista(model.op, b, tau=1e-3, max_iter=30).run()
    assert float(res.x.abs().max()) == 0.0  # A >= 0, x >= 0: zero is the best fit
    adm = Admm(model, b, tau=1e-3, max_iter=30).run()
    sane(adm.x)


def test_loader_clips_after_dark_and_refuses_an_empty_result(tmp_path):
    p = tmp_path / "m.npy"
    rng = np.random.default_rng(1)
    np.save(p, rng.integers(90, 200, (16, 16)).astype(np.uint16))
    m = load_measurement(p, dark=100)
    assert m.min() == 0.0 and m.max() == 1.0
    with pytest.raises(ValueError, match="all zero"):
        load_measurement(p, dark=1000)


# -- values near the float16 range, and beyond what float32 can hold --------------------------


def test_float16_range_values_are_normalised_on_load(tmp_path):
    rng = np.random.default_rng(2)
    counts = rng.uniform(5e4, 6.5e4, (24, 24)).astype(np.float16)  # near float16's max 65504
    np.save(tmp_path / "meas.npy", counts)
    shape = psf2d(24, 24)
    np.save(tmp_path / "psf32.npy", (shape * 1e-8 / shape.max()).astype(np.float32))
    # max 1e-4: just above float16's smallest normal (6.1e-5), its dim pixels subnormal
    np.save(tmp_path / "psf16.npy", (shape * 1e-4 / shape.max()).astype(np.float16))
    np.save(tmp_path / "psf16_sub.npy", (shape * 1e-5 / shape.max()).astype(np.float16))
    np.save(tmp_path / "psf16_lost.npy", (shape * 1e-8 / shape.max()).astype(np.float16))
    meas = load_measurement(tmp_path / "meas.npy")
    assert meas.dtype == np.float32 and np.isfinite(meas).all() and meas.max() == 1.0
    for name in ("psf32.npy", "psf16.npy"):
        psf = load_psf(tmp_path / name)
        assert psf.dtype == np.float32 and np.isfinite(psf).all()
        assert float(psf.sum()) == pytest.approx(1.0, rel=1e-5)
        res = Fista(build_model("2d", psf).op, torch.as_tensor(meas), tau=1e-3, max_iter=50).run()
        sane(res.x)
    # every value subnormal (max below float16's smallest normal): refused, with the bits kept
    with pytest.raises(ValueError, match=r"psf16_sub\.npy has values no larger than 1e-05, "
                       r"below the smallest normal float16 number .*at most 8 significant"):
        load_psf(tmp_path / "psf16_sub.npy")
    # values below float16's smallest subnormal (6e-8) were lost when the file was written
    with pytest.raises(ValueError, match="is all zero"):
        load_psf(tmp_path / "psf16_lost.npy")


def test_raw_scales_give_the_normalised_result_up_to_scale():
    """PSF values ~1e-8 and counts ~6e4 in float32: the same answer, scaled (rel. 1e-3)."""
    psf = psf2d()
    model = build_model("2d", psf)
    sim = simulate(model, blocks()[None, None], noise=0.01, seed=3)
    b = torch.as_tensor(sim.meas)
    tau = 2e-4
    a, beta = 1e-8 / float(psf.max()), 6e4
    raw = build_model("2d", psf * a)
    kw = {"max_iter": 150, "tol": 0}
    x_ref = Fista(model.op, b, tau=tau, **kw).run().x
    x_raw = Fista(raw.op, b * beta, tau=tau * a * beta, **kw).run().x
    assert rel(x_raw * (a / beta), x_ref) < 1e-3
    y_ref = Admm(model, b, tau=tau, **kw).run().x
    y_raw = Admm(raw, b * beta, tau=tau * a * beta, **kw).run().x
    assert rel(y_raw * (a / beta), y_ref) < 1e-4


def test_scales_beyond_float32_give_clear_errors():
    psf = psf2d()
    b = torch.rand(1, *psf.shape)
    with pytest.raises(ValueError, match=r"underflows.*normalise the PSF"):
        Fista(build_model("2d", psf * 1e-20).op, b)
    with pytest.raises(NumericalError, match=r"too large for torch\.float32; normalise"):
        Fista(build_model("2d", psf * 1e20).op, b)
    with pytest.raises(ValueError, match=r"measurement is too large.*normalise"):
        Fista(build_model("2d", psf).op, b * 1e30)
    # float64 takes the same extremes
    m64 = build_model("2d", psf * 1e20, dtype=torch.float64)
    sane(Fista(m64.op, b.double(), tau=0.0, max_iter=5).run().x)
