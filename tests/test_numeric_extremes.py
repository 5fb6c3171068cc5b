"""Numerics at the extremes, from a hostile review (each failed before its fix).

- ``--tau 1e-300`` crashed FISTA with a traceback ("value cannot be converted to type float
  without overflow"), ``--tau 1e-40`` ended in "NaN/inf values appeared in the TV prox", and
  ADMM's ``--tau 1e-300`` in NaN (its threshold rounded to 0 in float32, then 1 - thr / 0): a
  TV weight below what the dtype can act on is 0.
- The dark level was subtracted after the cast to float32: a 0..200 signal on a 1e9 pedestal
  (uint32) came back as 4 levels with 32-count errors.
- The monotone restart doubled the inner TV iterations with no cap (3072 per step on 64x64).
- A float32 measurement below about 1e-19 made the objective underflow to 0: a wrong result
  labelled converged, through the Python API.
- ``recon admm --tau 1e300`` blamed rho ("use a rho nearer the default 0.01") at the default rho.
"""

from __future__ import annotations

import numpy as np
import pytest
import tifffile
import torch

from app.cli import main
from recon.admm import Admm
from recon.fista import PROX_ITERS_CAP, Fista
from recon.models import build_model
from recon.readers import load_measurement
from recon.simulate import synthetic_psf


@pytest.fixture
def case(tmp_path):
    psf = synthetic_psf((32, 40), n_points=12, seed=1)
    rng = np.random.default_rng(0)
    scene = np.zeros((1, 1, 32, 40), np.float32)
    scene[..., 8:24, 10:30] = rng.random((16, 20))
    with torch.no_grad():
        b = build_model("2d", psf).apply(torch.from_numpy(scene)).numpy().reshape(32, 40)
    np.save(tmp_path / "psf.npy", psf)
    np.save(tmp_path / "meas.npy", (b / b.max()).astype(np.float32))
    return tmp_path, psf, b


@pytest.mark.parametrize("method", ["fista", "admm"])
def test_a_negligible_tau_is_zero_tau(case, method, capsys):
    d, _, _ = case
    out = {}
    for tau in ("1e-30", "1e-40", "1e-300"):
        rc = main(["--threads", "1", "recon", method, "--psf", str(d / "psf.npy"), "--meas",
                   str(d / "meas.npy"), "--tau", tau, "--iters", "30", "--out",
                   str(d / f"{method}-{tau}.tif")])
        err = capsys.readouterr().err
        assert rc == 0, err
        assert "Traceback" not in err and "NaN" not in err
        out[tau] = tifffile.imread(d / f"{method}-{tau}.tif")
        assert np.isfinite(out[tau]).all()
    # 1e-30 runs the TV prox, whose every change is far below float32's resolution there
    # (tau 0 takes other branches: no TV prox, other stops)
    np.testing.assert_allclose(out["1e-40"], out["1e-30"], rtol=0, atol=1e-5)
    np.testing.assert_allclose(out["1e-300"], out["1e-30"], rtol=0, atol=1e-5)


def test_the_dark_level_is_subtracted_before_the_cast_to_float32(tmp_path):
    rng = np.random.default_rng(0)
    signal = np.round(200 * rng.random((32, 40))).astype(np.uint32)
    np.save(tmp_path / "m.npy", signal + np.uint32(10**9))
    got = load_measurement(tmp_path / "m.npy", dark=1e9, normalise=None)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got[0], signal.astype(np.float32))
    # a dark frame of the same pedestal, as a file
    np.save(tmp_path / "dark.npy", np.full((32, 40), 10**9, np.uint32))
    got = load_measurement(tmp_path / "m.npy", dark=tmp_path / "dark.npy", normalise=None)
    np.testing.assert_array_equal(got[0], signal.astype(np.float32))


def test_the_monotone_restart_keeps_the_inner_iterations_capped():
    rng = np.random.default_rng(0)
    psf = (rng.random((64, 64)) ** 6).astype(np.float32)
    psf /= psf.sum()
    x = np.zeros((1, 1, 64, 64), np.float32)
    x[..., 8:44, 8:44] = 1
    m = build_model("2d", psf)
    with torch.no_grad():
        b = m.apply(torch.from_numpy(x))
    b = b + 0.01 * torch.from_numpy(rng.standard_normal(tuple(b.shape)).astype(np.float32))
    s = Fista(m.op, b, tau=1e-2, max_iter=600, tol=0, restart="monotone")
    seen = [s.prox_iters for _ in s.steps()]
    assert max(seen) <= max(PROX_ITERS_CAP, seen[0]), max(seen)


def test_a_measurement_too_small_for_float32_is_refused(case):
    _, psf, b = case
    m = build_model("2d", psf)
    tiny = torch.from_numpy((b / b.max() * 1e-25).astype(np.float32))[None]
    with pytest.raises(ValueError, match=r"the measurement is too small for torch\.float32 "
                                         r"\(max \|b\| = 1e-25: its squares underflow\)"):
        Fista(m.op, tiny, tau=1e-3, max_iter=10)
    Fista(m.op, tiny * 1e7, tau=1e-3, max_iter=2).run()  # 1e-18: its squares hold


def test_admm_names_tau_when_tau_is_out_of_range(case):
    _, psf, b = case
    m = build_model("2d", psf)
    meas = torch.from_numpy((b / b.max()).astype(np.float32))[None]
    with pytest.raises(ValueError, match=r"^tau 1e\+300 over ADMM's penalty .* give a tau of "
                                         r"at most 1"):
        Admm(m, meas, tau=1e300, max_iter=2)


def test_a_stack_folder_is_read_in_the_order_of_its_numbers(tmp_path):
    """(spectral/depth review) psf0 ... psf10 in a folder loaded as 0, 1, 10, 2, ...: planes
    swapped with no word (PSNR 20.6 -> 18.8 dB on a lit-plane case)."""
    from recon.readers import load_psf_stack

    for k in range(12):
        plane = np.zeros((16, 16), np.float32)
        plane[k, k] = 1.0 + k  # plane k lit at (k, k)
        np.save(tmp_path / f"psf{k}.npy", plane)
    stack = load_psf_stack(tmp_path, normalise=None)
    assert [int(np.argmax(stack[k].max(axis=1))) for k in range(12)] == list(range(12))


def test_a_psf_stack_of_ours_given_as_one_psf_is_refused(tmp_path):
    """(spectral/depth review) calibrate depth's 3-plane file given to --psf was mixed into one
    PSF as R, G, B with a warning to "give one file per frame"."""
    import json

    from recon.calibfile import PSF_STACK_FORMAT
    from recon.readers import load_psf

    stack = np.random.default_rng(0).random((3, 16, 16)).astype(np.float32)
    tifffile.imwrite(tmp_path / "stack.tif", stack, photometric="minisblack",
                     description=json.dumps({"format": PSF_STACK_FORMAT, "format_version": 1}))
    with pytest.raises(ValueError, match=r"stack\.tif is a stack of PSFs \(a depth "
                                         r"calibration\): give it as --psf-stack"):
        load_psf(tmp_path / "stack.tif")
