"""Shared pieces of the stability catalogue (docs/stability.md): small cases and checks."""

from __future__ import annotations

import itertools
import math

import numpy as np
import torch

from recon.models import ForwardModel, build_model
from recon.simulate import synthetic_psf
from recon.tv import TV

H, W = 32, 40


def blocks(h: int = H, w: int = W, seed: int = 0) -> np.ndarray:
    """A piecewise-constant scene (h, w) in [0, ~2]."""
    rng = np.random.default_rng(seed)
    s = np.zeros((h, w))
    for _ in range(4):
        y0, x0 = rng.integers(0, h - 4), rng.integers(0, w - 4)
        hh, ww = rng.integers(3, max(4, h // 2)), rng.integers(3, max(4, w // 2))
        s[y0 : y0 + hh, x0 : x0 + ww] += rng.uniform(0.3, 1)
    return s


def psf2d(h: int = H, w: int = W, seed: int = 1) -> np.ndarray:
    return synthetic_psf((h, w), seed=seed)


def objective(model: ForwardModel, x: torch.Tensor, b: torch.Tensor, tau: float,
              tv: TV | None = None) -> float:
    """0.5 ||A x - b||^2 + tau TV(x), in float64, for any solver's estimate."""
    tv = tv or TV()
    with torch.no_grad():
        r = model.apply(x) - b.to(x.dtype)
    return 0.5 * float(torch.sum(r.double() ** 2)) + (tau * tv.value(x) if tau else 0.0)


def non_increasing(values: list[float]) -> bool:
    return all(b <= a for a, b in itertools.pairwise(values))


def all_finite(values: list[float]) -> bool:
    return all(math.isfinite(v) for v in values)


def sane(x: torch.Tensor) -> None:
    """A reconstruction is finite and non-negative."""
    assert bool(torch.isfinite(x).all()), "NaN/inf in the result"
    assert float(x.min()) >= 0.0, f"negative values in a non-negative result: {float(x.min())}"


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    """||a - b|| / ||b|| in float64."""
    a64, b64 = a.double(), b.double()
    return float(torch.linalg.vector_norm(a64 - b64) / torch.linalg.vector_norm(b64))


def dense(model: ForwardModel) -> torch.Tensor:
    """The forward model as a dense float64 matrix (tiny models only)."""
    n = math.prod(model.scene_shape)
    eye = torch.eye(n, dtype=model.op.dtype).reshape(n, *model.scene_shape)
    with torch.no_grad():
        cols = [model.apply(e).reshape(-1) for e in eye]
    return torch.stack(cols, dim=1).double()


def tiny_models(h: int = 12, w: int = 10, seed: int = 5) -> dict[str, ForwardModel]:
    """Every masked model kind on a tiny sensor (erasures, video, spectral, depth)."""
    from drivers.timing import SensorTiming

    rng = np.random.default_rng(seed)
    psf = synthetic_psf((h, w), seed=2)
    shutter = SensorTiming(rows=h, line_time_us=1, exposure_lines=4,
                           pattern="outside-in").shutter(2)
    return {
        "2d_erasures": build_model("2d", psf, mask=(rng.random((h, w)) > 0.9).astype(np.float32)),
        "video": build_model("video", psf, shutter=shutter),
        "spectral": build_model("spectral", psf, filters=rng.random((5, h, w))),
        "depth": build_model("depth", np.stack([synthetic_psf((h, w), seed=s) for s in range(3)]),
                             mask=(rng.random((h, w)) > 0.5).astype(np.float32)),
    }
