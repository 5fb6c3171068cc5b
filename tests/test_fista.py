"""FISTA-TV: correctness against a dense solve, monotone objective, stops, NaN, cancellation."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from recon.fista import Fista
from recon.models import build_model
from recon.simulate import simulate, synthetic_psf
from recon.stepwise import NumericalError, StopReason
from recon.tv import TV
from tests.scenes import blocks_scene


def _scene(h, w, seed=0):
    return blocks_scene(h, w, seed, count=4)


def _psnr(ref, est):
    g = float((ref * est).sum() / max((est * est).sum(), 1e-30))
    mse = float(((ref - g * est) ** 2).mean())
    return 10 * math.log10(float(ref.max() - ref.min()) ** 2 / mse)


def test_least_squares_limit_matches_dense_solve():
    """tau = 0 and no constraint: FISTA converges to the least-squares solution."""
    rng = np.random.default_rng(0)
    psf = rng.random((6, 5)) + 0.1
    m = build_model("2d", psf, dtype=torch.float64)
    n = int(np.prod(m.scene_shape))
    eye = torch.eye(n, dtype=torch.float64).reshape(n, *m.scene_shape)
    mat = torch.stack([m.apply(e).reshape(-1) for e in eye], dim=1)
    b = torch.as_tensor(rng.random(m.meas_shape))
    x_ls = torch.linalg.lstsq(mat, b.reshape(-1, 1)).solution.reshape(m.scene_shape)
    solver = Fista(m.op, b, tau=0.0, nonneg=False, max_iter=20000, tol=1e-14, restart=True)
    res = solver.run()
    r_ls = float(torch.linalg.vector_norm(mat @ x_ls.reshape(-1) - b.reshape(-1)))
    r_f = float(torch.linalg.vector_norm(m.apply(res.x) - b))
    assert r_f <= r_ls * (1 + 1e-6) + 1e-9


def test_recovers_scene_and_objective_never_increases():
    psf = synthetic_psf((32, 40), seed=1)
    m = build_model("2d", psf, mask=None)
    truth = _scene(32, 40)[None, None]
    sim = simulate(m, truth, noise=0.01, seed=3)
    solver = Fista(m.op, torch.as_tensor(sim.meas), tau=2e-4, max_iter=300, tol=0,
                   restart="monotone")  # the monotone rule: objectives never increase
    objs = [s.objective for s in solver.steps()]
    assert all(b <= a for a, b in itertools.pairwise(objs))
    assert solver.x.dtype == torch.float32
    psnr = _psnr(truth[0, 0], solver.x.numpy()[0, 0])
    zero_fill = _psnr(truth[0, 0], np.full(truth.shape[-2:], truth.mean()))
    assert psnr > zero_fill + 10 and psnr > 24, psnr


@pytest.mark.parametrize("kind", ["2d_erasures", "video", "spectral", "depth"])
def test_monotone_and_stable_on_masked_models(kind):
    rng = np.random.default_rng(5)
    h, w = 24, 20
    psf = synthetic_psf((h, w), seed=2)
    if kind == "2d_erasures":
        m = build_model("2d", psf, mask=(rng.random((h, w)) > 0.9).astype(np.float32))
    elif kind == "video":
        from drivers.timing import SensorTiming

        sh = SensorTiming(rows=h, line_time_us=1, exposure_lines=4, pattern="outside-in").shutter(2)
        m = build_model("video", psf, shutter=sh)
    elif kind == "spectral":
        m = build_model("spectral", psf, filters=rng.random((5, h, w)))
    else:
        m = build_model("depth", np.stack([synthetic_psf((h, w), seed=s) for s in range(3)]))
    b = torch.as_tensor(rng.random(m.meas_shape), dtype=torch.float32)
    solver = Fista(m.op, b, tau=1e-3, tv=TV(weight_k=0.5), max_iter=400, tol=0,
                   restart="monotone")
    objs = [s.objective for s in solver.steps()]
    assert all(math.isfinite(o) for o in objs)
    assert all(b2 <= a for a, b2 in itertools.pairwise(objs))
    assert objs[-1] < objs[0]


def test_stops_on_relative_change_and_warm_start():
    psf = synthetic_psf((16, 16), seed=4)
    m = build_model("2d", psf)
    b = torch.as_tensor(simulate(m, _scene(16, 16)[None, None]).meas)
    first = Fista(m.op, b, tau=1e-3, max_iter=5000, tol=1e-4).run()
    assert first.reason is StopReason.CONVERGED and first.iterations < 5000
    warm = Fista(m.op, b, tau=1e-3, max_iter=5000, tol=1e-4, x0=first.x).run()
    assert warm.iterations < first.iterations / 3


def test_cancel_and_generator_stop():
    m = build_model("2d", synthetic_psf((16, 16)))
    b = torch.rand(m.meas_shape)
    calls = []
    res = Fista(m.op, b, max_iter=100, tol=0).run(
        callback=calls.append, cancel=lambda: len(calls) >= 3
    )
    assert res.reason is StopReason.CANCELLED and res.iterations == 3
    gen = Fista(m.op, b, max_iter=100, tol=0)
    it = gen.steps()
    steps = [next(it) for _ in range(4)]
    assert [s.iteration for s in steps] == [1, 2, 3, 4] and gen.iteration == 4
    assert all(s.elapsed_s >= 0 and s.residual >= 0 for s in steps)


def test_all_zero_measurement_gives_zero():
    m = build_model("2d", synthetic_psf((16, 16)))
    res = Fista(m.op, torch.zeros(m.meas_shape), tau=1e-2, max_iter=20).run()
    assert torch.isfinite(res.x).all() and float(res.x.abs().max()) == 0.0


def test_nan_is_reported_with_its_place():
    m = build_model("2d", synthetic_psf((16, 16)))
    b = torch.rand(m.meas_shape)
    bad = b.clone()
    bad[0, 3, 3] = float("nan")
    with pytest.raises(NumericalError, match="measurement"):
        Fista(m.op, bad)
    solver = Fista(m.op, b, max_iter=50, tol=0)
    solver.step()
    orig = m.op.apply

    def poisoned(x):
        y = orig(x)
        y[0, 0, 0] = float("inf")
        return y

    m.op.apply = poisoned
    with pytest.raises(NumericalError, match="forward model A x at iteration 2"):
        solver.step()


def test_input_validation():
    m = build_model("2d", synthetic_psf((8, 8)))
    with pytest.raises(ValueError, match="shape"):
        Fista(m.op, torch.zeros((1, 9, 8)))
    with pytest.raises(ValueError, match="tau"):
        Fista(m.op, torch.zeros(m.meas_shape), tau=-1)
    with pytest.raises(ValueError, match="warm start"):
        Fista(m.op, torch.zeros(m.meas_shape), x0=torch.zeros((1, 1, 3, 3)))
