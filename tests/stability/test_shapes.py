"""Extreme operators and shapes: a single-hot-pixel PSF (a shifted identity), odd non-square
sensors (37 x 53), and tiny 8 x 8 images."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from drivers.timing import SensorTiming
from recon.admm import Admm
from recon.fista import Fista
from recon.memory import check_fits, estimate_model_memory
from recon.models import build_model
from recon.tv import TV
from tests.stability.helpers import blocks, non_increasing, rel, sane


@pytest.mark.parametrize("hot", [(16, 20), (3, 5), (31, 0)])
def test_single_hot_pixel_psf_is_a_shifted_identity(hot):
    h, w = 32, 40
    psf = np.zeros((h, w), np.float32)
    psf[hot] = 1.0
    model = build_model("2d", psf)
    assert model.op.norm() == pytest.approx(1.0, abs=1e-5)
    truth = torch.as_tensor(blocks(h, w)[None, None], dtype=torch.float32)
    b = model.apply(truth)
    # the sensor sees the scene shifted by (hot - centre); the rest falls off the sensor
    dy, dx = hot[0] - h // 2, hot[1] - w // 2
    expect = torch.zeros_like(b)
    ys, xs = slice(max(dy, 0), h + min(dy, 0)), slice(max(dx, 0), w + min(dx, 0))
    yt, xt = slice(max(-dy, 0), h + min(-dy, 0)), slice(max(-dx, 0), w + min(-dx, 0))
    expect[0, ys, xs] = truth[0, 0, yt, xt]
    assert float((b - expect).abs().max()) < 1e-6
    res = Fista(model.op, b, tau=0.0, max_iter=100).run()
    sane(res.x)
    # the visible part of the scene is recovered exactly (to float32 precision)
    assert float((res.x[0, 0, yt, xt] - truth[0, 0, yt, xt]).abs().max()) < 1e-5
    adm = Admm(model, b, tau=0.0, max_iter=300).run()
    sane(adm.x)
    assert float((adm.x[0, 0, yt, xt] - truth[0, 0, yt, xt]).abs().max()) < 1e-4


def _odd_models(h: int, w: int):
    rng = np.random.default_rng(7)
    psf = rng.random((h, w))
    psf /= psf.sum()
    shutter = SensorTiming(rows=h, line_time_us=1, exposure_lines=5,
                           pattern="outside-in").shutter(9)
    mask = (rng.random((h, w)) > 0.3).astype(np.float64)
    return {
        "2d": build_model("2d", psf, dtype=torch.float64),
        "2d_field": build_model("2d", psf, field=(h + 4, w - 6), dtype=torch.float64),
        "2d_masked_rgb": build_model("2d", rng.random((3, h, w)), mask=mask,
                                     dtype=torch.float64),
        "video": build_model("video", psf, shutter=shutter, dtype=torch.float64),
        "spectral": build_model("spectral", psf, filters=rng.random((3, h, w)),
                                dtype=torch.float64),
        "depth": build_model("depth", rng.random((2, h, w)), mask=mask, dtype=torch.float64),
    }


@pytest.mark.parametrize("size", [(37, 53), (8, 8)], ids=["37x53", "8x8"])
def test_odd_and_tiny_sensors_adjoint_and_solvers(size):
    for name, model in _odd_models(*size).items():
        g = torch.Generator().manual_seed(0)
        x = torch.randn(model.scene_shape, generator=g, dtype=torch.float64)
        y = torch.randn(model.meas_shape, generator=g, dtype=torch.float64)
        lhs = float((model.apply(x) * y).sum())
        rhs = float((x * model.adjoint(y)).sum())
        scale = float(torch.linalg.vector_norm(model.apply(x)) * torch.linalg.vector_norm(y))
        assert abs(lhs - rhs) <= 1e-10 * scale, name
        b = torch.as_tensor(np.random.default_rng(1).random(model.meas_shape))
        tv = TV(weight_k=0.5 if model.k > 1 else 0.0)
        res = Fista(model.op, b, tau=1e-3, tv=tv, max_iter=60, tol=0, restart="monotone").run()
        sane(res.x)
        assert non_increasing([s.objective for s in res.history]), name
        assert res.history[-1].objective < res.history[0].objective, name
        if model.kind.value == "2d":
            sane(Admm(model, b, tau=1e-3, max_iter=60).run().x)


def test_8x8_memory_estimate_and_float32_run():
    model = build_model("2d", np.random.default_rng(0).random((8, 8)))
    est = estimate_model_memory(model)
    assert est.pad == (15, 15) and est.total_bytes < 64 * 1024
    assert check_fits(est) is None or check_fits(est) >= est.total_bytes
    b = torch.rand(model.meas_shape)
    x32 = Fista(model.op, b, tau=1e-3, max_iter=50, tol=0).run().x
    assert x32.dtype == torch.float32
    m64 = build_model("2d", np.random.default_rng(0).random((8, 8)), dtype=torch.float64)
    x64 = Fista(m64.op, b.double(), tau=1e-3, max_iter=50, tol=0).run().x
    assert rel(x32, x64) < 1e-4
