"""TV prox: FGP matches an independent long solve; TV values; weighted 3D."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from recon.tv import TV, TVProx


def _chambolle_pock_prox(z, gamma, tv, nonneg, iters=20000):
    """Independent reference: accelerated primal-dual (Chambolle-Pock alg. 2) for the same prox.

    min_x 0.5||x - z||^2 + i(x >= 0) + gamma * TV(x) with K = D (weighted differences).
    """
    x = z.clone()
    xbar = x.clone()
    p = [torch.zeros_like(z) for _ in tv.grad(z)]
    lip = tv.lipschitz
    tau_, sigma = 1.0 / np.sqrt(lip), 1.0 / np.sqrt(lip)
    for _ in range(iters):
        g = tv.grad(xbar)
        p = [pi + sigma * gi for pi, gi in zip(p, g, strict=False)]
        # prox of (gamma TV)^* = projection onto the gamma-ball
        scaled = [pi / gamma for pi in p]
        tv.project(scaled)
        p = [gamma * s for s in scaled]
        x_old = x
        v = x - tau_ * tv.grad_adj(p)
        x = (v + tau_ * z) / (1.0 + tau_)
        if nonneg:
            x = x.clamp(min=0.0)
        theta = 1.0 / np.sqrt(1.0 + 2.0 * tau_)  # strong convexity 1
        tau_, sigma = theta * tau_, sigma / theta
        xbar = x + theta * (x - x_old)
    return x


@pytest.mark.parametrize(
    ("tv", "shape", "nonneg"),
    [
        (TV(isotropic=True), (1, 1, 7, 6), True),
        (TV(isotropic=False), (1, 1, 7, 6), True),
        (TV(isotropic=True), (2, 1, 5, 5), False),
        (TV(isotropic=False, weight_k=0.5), (1, 4, 5, 6), True),
        (TV(isotropic=True, weight_k=2.0), (1, 3, 5, 4), True),
    ],
)
def test_fgp_matches_exact_prox(tv, shape, nonneg):
    g = torch.Generator().manual_seed(0)
    z = torch.randn(shape, generator=g, dtype=torch.float64)
    gamma = 0.3
    prox = TVProx(tv, nonneg=nonneg)
    fgp = prox(z, gamma, iters=3000)
    # Certificate: the duality gap at the dual p bounds the distance to the exact prox,
    # ||x - x*||^2 <= 2 gap (the objective is 1-strongly convex).
    p = prox._p
    gap = gamma * tv.value(fgp) - gamma * sum(
        float((pi * gi).sum()) for pi, gi in zip(p, tv.grad(fgp), strict=False)
    )
    assert -1e-12 <= gap < 1e-10
    # An independent solver (accelerated primal-dual, slower: about 1e-4 after 20000 steps).
    ref = _chambolle_pock_prox(z, gamma, tv, nonneg)
    assert float((fgp - ref).abs().max()) < 1e-3
    longer = TVProx(tv, nonneg=nonneg)(z, gamma, iters=10000)
    assert float((fgp - longer).abs().max()) < 1e-8

    def obj(x):
        return 0.5 * float(((x - z) ** 2).sum()) + gamma * tv.value(x)

    assert obj(fgp) <= obj(ref) + 1e-7
    if nonneg:
        assert float(fgp.min()) >= 0.0


def test_warm_start_converges_over_calls():
    z = torch.randn((1, 1, 16, 16), generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    tv = TV()
    exact = TVProx(tv)(z, 0.2, iters=3000)
    warm = TVProx(tv)
    errs = []
    for _ in range(40):
        x = warm(z, 0.2, iters=5)
        errs.append(float((x - exact).abs().max()))
    assert errs[-1] < 1e-3 < errs[0]


def test_tv_values():
    x = torch.zeros((1, 1, 4, 4), dtype=torch.float64)
    x[..., 2:, :] = 1.0  # one horizontal edge of length 4
    assert TV(isotropic=False).value(x) == pytest.approx(4.0)
    assert TV(isotropic=True).value(x) == pytest.approx(4.0)
    d = torch.zeros((1, 1, 3, 3), dtype=torch.float64)
    d[..., 0, 0] = 1.0  # a corner pixel: differences in both directions at (0,0)
    assert TV(isotropic=True).value(d) == pytest.approx(np.sqrt(2.0))
    assert TV(isotropic=False).value(d) == pytest.approx(2.0)
    v = torch.zeros((1, 3, 2, 2), dtype=torch.float64)
    v[:, 1] = 1.0  # frame 1 differs from its neighbours: two jumps of 4 pixels along k
    assert TV(weight_k=0.5).value(v) == pytest.approx(0.5 * 8)
    assert TV(weight_k=0.0).value(v) == pytest.approx(0.0)


def test_grad_adjoint():
    tv = TV(weight_k=1.5)
    g = torch.Generator().manual_seed(3)
    x = torch.randn((2, 3, 5, 4), generator=g, dtype=torch.float64)
    p = [torch.randn((2, 3, 5, 4), generator=g, dtype=torch.float64) for _ in range(3)]
    lhs = sum(float((a * b).sum()) for a, b in zip(tv.grad(x), p, strict=False))
    rhs = float((x * tv.grad_adj(p)).sum())
    assert abs(lhs - rhs) < 1e-10 * max(1.0, abs(lhs))


def test_zero_gamma_is_projection():
    z = torch.tensor([[[[-1.0, 2.0], [3.0, -4.0]]]])
    np.testing.assert_array_equal(TVProx(TV())(z, 0.0).numpy(), z.clamp(min=0).numpy())


def test_huge_gamma_gives_constant():
    z = torch.rand((1, 1, 8, 8), generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    x = TVProx(TV(), nonneg=True)(z, 1e6, iters=2000)
    assert float(x.max() - x.min()) < 1e-3
    assert float(x.mean()) == pytest.approx(float(z.mean()), abs=1e-3)
