"""FISTA's Fourier preconditioning (recon.fista): a safe step, a faster start, an unbiased end."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import recon.fista as fista_mod
from recon.fista import Fista, _GramP, fourier_preconditioner
from recon.models import build_model
from recon.simulate import simulate, synthetic_psf


def _case(n: int = 24, erasure: float = 0.0, noise: float = 0.0, seed: int = 3):
    psf = synthetic_psf((n, n), seed=seed)
    rng = np.random.default_rng(seed)
    scene = np.zeros((n, n))
    scene[n // 4: 3 * n // 4, n // 5: n // 2] = 1.0
    scene[n // 3: n // 2, n // 2: 4 * n // 5] = 0.5
    scene += 0.2 * rng.random((n, n))
    sim = simulate(build_model("2d", psf, dtype=torch.float64), scene[None, None],
                   erasure=erasure, noise=noise, seed=seed)
    model = build_model("2d", psf, mask=sim.mask, dtype=torch.float64)
    return model, torch.as_tensor(sim.meas, dtype=torch.float64)


def _dense(op, n_in):
    eye = torch.eye(n_in, dtype=torch.float64)
    return torch.stack([op.apply(e.reshape(op.in_shape)).reshape(-1) for e in eye], dim=1)


def test_the_preconditioner_is_a_contraction_and_its_step_is_exactly_safe():
    """P is symmetric with eigenvalues in (0, 1]; L_P is lambda_max(A P A^T) (+2 %), from a
    dense eigendecomposition; and it is well below ||A||^2 for a non-negative PSF."""
    model, _ = _case(12, erasure=0.3)
    op = model.op
    prec, lip = fourier_preconditioner(op, 0.1)
    n = int(np.prod(op.in_shape))
    pm = _dense(prec, n)
    torch.testing.assert_close(pm, pm.T, rtol=0, atol=1e-12)
    ev = torch.linalg.eigvalsh(pm)
    assert float(ev.min()) > 0.0 and float(ev.max()) <= 1.0 + 1e-12
    am = _dense(op, n)
    top = float(torch.linalg.eigvalsh(am @ pm @ am.T).max())
    assert lip == pytest.approx(1.02 * top, rel=1e-6)
    assert op.lipschitz() > 2.0 * lip  # the step grows (4-fold at this kappa)
    assert lip == pytest.approx(1.02 * float(torch.linalg.matrix_norm(
        _dense(_GramP(op, prec), int(np.prod(op.out_shape))), ord=2)), rel=1e-6)


def test_preconditioned_start_lowers_the_objective_faster_where_tv_is_weak():
    model, b = _case(32)
    tau, iters = 1e-6, 150
    runs = {}
    for pre in ("auto", "off"):
        s = Fista(model.op, b, tau=tau, max_iter=iters, tol=0.0, precondition=pre)
        s.run()
        runs[pre] = s
    assert runs["auto"].params["precondition"] == 0.1
    assert runs["off"].params["precondition"] is None
    assert runs["auto"].params["preconditioned_iterations"] == iters  # it never stalled
    assert runs["auto"].objective < 0.9 * runs["off"].objective


def test_plain_steps_at_the_end_remove_the_bias_of_the_preconditioned_phase(monkeypatch):
    """Both settings converge to the same minimiser: the preconditioned phase ends when its
    objective stalls, plain steps follow. The preconditioned iteration alone (no switch) ends
    measurably elsewhere (its Euclidean prox is not P's)."""
    model, b = _case(20, erasure=0.5, noise=0.01)
    tau = 3e-3

    def run(pre, **kw):
        s = Fista(model.op, b, tau=tau, max_iter=6000, tol=1e-9, prox_iters=30,
                  precondition=pre, **kw)
        s.run()
        return s

    plain = run("off")
    pre = run(0.1)
    assert 0 < pre.params["preconditioned_iterations"] < 6000
    scale = float(torch.linalg.vector_norm(plain.x))
    gap = float(torch.linalg.vector_norm(pre.x - plain.x)) / scale
    monkeypatch.setattr(fista_mod, "STALL_WINDOW", 10**9)
    only = Fista(model.op, b, tau=tau, max_iter=6000, tol=0.0, prox_iters=30, precondition=0.1)
    only.run()  # never switches: the preconditioned iteration alone
    assert only.params["preconditioned_iterations"] == 6000
    biased = float(torch.linalg.vector_norm(only.x - plain.x)) / scale
    assert gap < 1e-3
    assert biased > 10 * gap


def test_auto_is_off_where_it_cannot_or_need_not_apply():
    model, b = _case(16)
    assert Fista(model.op, b, tau=1e-4, max_iter=500).params["precondition"] == 0.1
    assert Fista(model.op, b, tau=1e-4, max_iter=0).params["precondition"] is None
    assert Fista(model.op, b, tau=1e-4, max_iter=500,
                 restart="monotone").params["precondition"] is None
    assert Fista(model.op, b, tau=1e-4, max_iter=500,
                 precondition="off").params["precondition"] is None
    # a PSF with a flat spectrum (a delta): no frequency dominates, nothing to gain
    delta = np.zeros((8, 8))
    delta[4, 4] = 1.0
    flat = build_model("2d", delta, dtype=torch.float64)
    bf = torch.rand(flat.meas_shape, dtype=torch.float64)
    assert Fista(flat.op, bf, tau=1e-4, max_iter=500).params["precondition"] is None
    depth = build_model("depth", np.random.default_rng(0).random((3, 8, 8)),
                        dtype=torch.float64)
    bd = torch.rand(depth.meas_shape, dtype=torch.float64)
    assert Fista(depth.op, bd, tau=1e-4, max_iter=500).params["precondition"] is None
    with pytest.raises(ValueError, match="2D convolution"):
        Fista(depth.op, bd, tau=1e-4, max_iter=500, precondition=0.1)
    # a warm start (near the minimiser already) and a field larger than the sensor (where the
    # phase did lasting damage) stay plain under "auto"; an explicit kappa is obeyed
    assert Fista(model.op, b, tau=1e-4, max_iter=500,
                 x0=torch.zeros(model.scene_shape, dtype=torch.float64)
                 ).params["precondition"] is None
    wide = build_model("2d", synthetic_psf((16, 16), seed=3), field=(32, 32),
                       dtype=torch.float64)
    bw = torch.rand(wide.meas_shape, dtype=torch.float64)
    assert Fista(wide.op, bw, tau=1e-4, max_iter=500).params["precondition"] is None
    assert Fista(wide.op, bw, tau=1e-4, max_iter=500,
                 precondition=0.1).params["precondition"] == 0.1
    for bad in (0.0, 1.5, float("nan"), "fast", True):
        with pytest.raises(ValueError, match="precondition"):
            Fista(model.op, b, tau=1e-4, max_iter=500, precondition=bad)


def test_a_divergence_in_the_preconditioned_phase_ends_it():
    model, b = _case(16)
    s = Fista(model.op, b, tau=1e-6, max_iter=500, tol=0.0)
    assert s.params["precondition"] == 0.1
    s.L /= 200.0  # a step far too long for the preconditioned gradient
    it = 0
    while not s.guard_resets:
        it = s.step().iteration
    assert s.guard_resets == 1
    assert s.params["preconditioned_iterations"] < it
    assert s.L == pytest.approx(model.op.lipschitz())
    s.run()
    assert np.isfinite(s.objective)


def test_a_rising_objective_ends_the_preconditioned_phase(monkeypatch):
    """A small object on a dark field keeps x >= 0 active: there the Euclidean projection can
    turn a preconditioned step uphill. The phase ends as soon as a step would raise the
    objective 10 % above its lowest (the step is dropped), and the run ends as well as plain
    steps; without that rule it ends far worse."""
    from benchmarks.plan_cases import object_capture

    cap, _ = object_capture(48, 64, seed=0)
    mask = (np.random.default_rng(0).random(cap.meas.shape[-2:]) < 0.5).astype(np.float32)
    model = build_model("2d", cap.psf, mask=mask)
    b = torch.as_tensor(cap.meas.astype(np.float32) * mask).reshape(model.meas_shape)

    def final(pre):
        s = Fista(model.op, b, tau=1e-4, max_iter=150, tol=0.0, precondition=pre)
        s.run()
        return s

    plain, pre = final("off"), final(0.01)
    assert pre.guard_resets >= 1 and pre.params["preconditioned_iterations"] < 20
    assert pre.objective <= 1.01 * plain.objective
    monkeypatch.setattr(fista_mod, "PREC_RISE", 1e9)
    assert final(0.01).objective > 1.1 * plain.objective


def test_the_phase_is_reported_as_it_runs_and_never_outlasts_max_iter():
    model, b = _case(16)
    s = Fista(model.op, b, tau=1e-6, max_iter=500, tol=0.0)
    for _ in range(20):
        s.step()
    p = s.params
    assert p["preconditioned_iterations"] == 20
    assert p["lipschitz"] == pytest.approx(model.op.lipschitz())
    assert p["lipschitz_preconditioned"] == pytest.approx(s.L) and s.L < p["lipschitz"]
    # a relative change below tol on the last allowed iteration ends the run there
    short = Fista(model.op, b, tau=1e-6, max_iter=2, tol=1e9)
    result = short.run()
    assert result.iterations == 2 and short.done


def test_a_tiny_level_is_computed_or_refused_in_one_line():
    """kappa 1e-20 (a number in (0, 1]) stopped FISTA with ZeroDivisionError: the power
    iteration on A P A^T, whose norm is about kappa ||A||^2, underflowed float32 to 0."""
    psf = synthetic_psf((24, 32), seed=1)
    model = build_model("2d", psf)  # float32
    b = model.apply(torch.ones(model.scene_shape))
    lip = fourier_preconditioner(model.op, 1e-20)[1]
    assert 0.0 < lip < model.op.lipschitz()
    res = Fista(model.op, b, tau=1e-3, max_iter=60, precondition=1e-20).run()
    assert bool(torch.isfinite(res.x).all()) and float(res.x.max()) > 0
    with pytest.raises(ValueError, match=r"precondition level \(kappa\) 1e-300 is too small "
                                         r"for torch\.float32"):
        Fista(model.op, b, precondition=1e-300)
