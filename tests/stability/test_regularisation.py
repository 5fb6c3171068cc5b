"""tau at its extremes: tau = 0 is non-negative least squares; a huge tau gives a constant.

For a huge tau FISTA uses the exact constant prox when a dual certificate proves it
(recon.fista.constant_prox); before that fix the inexact inner TV solver made every step fail
and the run stalled at x = 0 (objective far above the best constant's).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import nnls

from recon.admm import Admm
from recon.fista import Fista, constant_prox
from recon.models import build_model
from recon.simulate import simulate
from recon.tv import TV, TVProx
from tests.stability.helpers import (
    blocks,
    dense,
    non_increasing,
    objective,
    psf2d,
    sane,
    tiny_models,
)


def test_tau_zero_is_nonnegative_least_squares():
    h, w = 12, 10
    model = build_model("2d", psf2d(h, w, seed=2), dtype=torch.float64)
    sim = simulate(model, blocks(h, w)[None, None], noise=0.02, seed=1)
    b = torch.as_tensor(sim.meas, dtype=torch.float64)
    _, rnorm = nnls(dense(model).numpy(), b.numpy().ravel(), maxiter=5000)
    f_opt = 0.5 * rnorm**2
    res = Fista(model.op, b, tau=0.0, max_iter=2000, tol=0, restart="monotone").run()
    sane(res.x)
    assert non_increasing([s.objective for s in res.history])
    assert res.history[-1].objective == pytest.approx(f_opt, rel=1e-4)
    adm = Admm(model, b, tau=0.0, max_iter=1000, tol=0).run()
    sane(adm.x)
    assert f_opt <= objective(model, adm.x, b, 0.0) <= 1.1 * f_opt
    # float32 gets there too, to its precision
    m32 = build_model("2d", psf2d(h, w, seed=2))
    r32 = Fista(m32.op, b.float(), tau=0.0, max_iter=2000, tol=0).run()
    sane(r32.x)
    assert r32.history[-1].objective == pytest.approx(f_opt, rel=1e-2)


def _best_constant(model, b):
    a1 = model.apply(torch.ones(model.scene_shape, dtype=model.op.dtype))
    return max(float((a1 * b).sum() / (a1 * a1).sum()), 0.0)


@pytest.mark.parametrize("tau", [10.0, 1e4, 1e12])
def test_huge_tau_gives_the_best_constant(tau):
    model = build_model("2d", psf2d())
    sim = simulate(model, np.random.default_rng(0).random(model.scene_shape), noise=0.01, seed=3)
    b = torch.as_tensor(sim.meas)
    c = _best_constant(model, b)
    res = Fista(model.op, b, tau=tau, max_iter=300, tol=0, restart="monotone").run()
    sane(res.x)
    assert non_increasing([s.objective for s in res.history])
    mean = float(res.x.mean())
    assert float(res.x.max() - res.x.min()) <= 1e-6 * mean  # constant on the field
    assert mean == pytest.approx(c, rel=1e-3)
    # ADMM (fixed penalties) approaches the same constant more slowly
    adm = Admm(model, b, tau=tau, max_iter=300, tol=0).run()
    sane(adm.x)
    assert float(adm.x.mean()) == pytest.approx(c, rel=1e-2)
    assert float(adm.x.max() - adm.x.min()) <= 0.2 * float(adm.x.mean())


def test_huge_tau_with_tv_along_k_is_constant_over_k():
    model = tiny_models()["video"]
    b = torch.as_tensor(np.random.default_rng(1).random(model.meas_shape), dtype=torch.float32)
    res = Fista(model.op, b, tau=1e6, tv=TV(weight_k=0.5), max_iter=200, tol=0).run()
    sane(res.x)
    assert float(res.x.max() - res.x.min()) <= 1e-6 * float(res.x.mean())
    assert float(res.x.mean()) == pytest.approx(_best_constant(model, b), rel=1e-3)
    # without the k term each frame is constant on its own
    per_frame = Fista(model.op, b, tau=1e6, tv=TV(), max_iter=200, tol=0).run().x
    spread = per_frame.amax(dim=(2, 3)) - per_frame.amin(dim=(2, 3))
    assert float(spread.max()) <= 1e-6 * float(per_frame.mean())


@pytest.mark.parametrize("isotropic", [True, False])
def test_constant_prox_agrees_with_a_long_inner_solve(isotropic):
    tv = TV(isotropic=isotropic)
    z = torch.as_tensor(np.random.default_rng(3).random((2, 1, 9, 7)), dtype=torch.float64)
    assert constant_prox(tv, z, 1e-3) is None  # small gamma: the cheap test rejects it
    gamma = 40.0  # well above what the certificate needs for this z
    x = constant_prox(tv, z, gamma)
    assert x is not None and x.dtype == z.dtype
    assert torch.allclose(x, z.mean(dim=(2, 3), keepdim=True).expand_as(z))
    slow = TVProx(tv)(z, gamma, iters=3000)
    assert torch.allclose(slow, x, atol=1e-6)
    # with non-negativity, a negative mean becomes 0 (also exact)
    assert float(constant_prox(tv, z - 5.0, 1e3).abs().max()) == 0.0
    assert float(constant_prox(tv, z - 5.0, 1e3, nonneg=False).max()) < 0
