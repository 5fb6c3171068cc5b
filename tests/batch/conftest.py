"""Fixtures for the batch tests: tiny simulated measurements on disk, manifests, a UDN spec."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from recon.models import build_model
from recon.simulate import simulate, synthetic_psf

H, W = 24, 28
#: A small network that still has every part (as tests/udn uses).
TINY_NET = {"scales": 3, "channels": 16, "skip_channels": 4, "input_channels": 8}


def blocks(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    s = np.zeros((H, W))
    for _ in range(4):
        y0, x0 = rng.integers(0, H - 4), rng.integers(0, W - 4)
        s[y0 : y0 + rng.integers(3, H // 2), x0 : x0 + rng.integers(3, W // 2)] += rng.uniform(
            0.3, 1)
    return s


def make_data(folder: Path, n: int) -> Path:
    """psf.npy and meas/mNN.npy, meas/tNN.npy (truth) for n scenes in ``folder``."""
    (folder / "meas").mkdir(parents=True, exist_ok=True)
    psf = synthetic_psf((H, W), seed=1)
    np.save(folder / "psf.npy", psf)
    model = build_model("2d", psf)
    for i in range(n):
        sim = simulate(model, blocks(i)[None, None], noise=0.01, seed=i)
        np.save(folder / "meas" / f"m{i:02d}.npy", sim.meas)
        np.save(folder / "meas" / f"t{i:02d}.npy", sim.truth)
    return folder


def write_udn_spec(folder: Path, max_iter: int, checkpoint_every: int,
                   name: str = "udn.toml") -> Path:
    """A tiny UDN job spec; its [data] names m00 (a batch item replaces the measurement)."""
    import tomli_w

    spec = {
        "job": {"name": "batch-tiny"},
        "data": {"psf": "psf.npy", "measurement": "meas/m00.npy"},
        "network": dict(TINY_NET),
        "stopping": {"max_iter": max_iter, "patience": 100000},
        "output": {"checkpoint_every": checkpoint_every, "preview_every": 0,
                   "status_seconds": 0.0},
    }
    p = folder / name
    p.write_text(tomli_w.dumps(spec), encoding="utf-8")
    return p


