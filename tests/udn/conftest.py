"""Fixtures for the UDN tests: a tiny simulated 2D case on disk and spec writers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from recon.models import build_model
from recon.simulate import simulate, synthetic_psf
from tests.scenes import blocks_scene

H, W = 24, 28
#: A small network that still has every part (3 scales, skips).
TINY_NET = {"scales": 3, "channels": 16, "skip_channels": 4, "input_channels": 8}


@pytest.fixture(autouse=True)
def _one_thread():
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def tiny_problem(erasure: float = 0.5, h: int = H, w: int = W, seed: int = 0):
    psf = synthetic_psf((h, w), seed=1)
    truth = blocks_scene(h, w, seed)[None, None]
    sim = simulate(build_model("2d", psf), truth, noise=0.01, erasure=erasure, seed=2)
    return psf, sim


@pytest.fixture
def tiny_data(tmp_path: Path) -> Path:
    """psf.npy, meas.npy, mask.npy, truth.npy in tmp_path/data."""
    d = tmp_path / "data"
    d.mkdir()
    psf, sim = tiny_problem()
    np.save(d / "psf.npy", psf)
    np.save(d / "meas.npy", sim.meas)
    np.save(d / "mask.npy", sim.mask)
    np.save(d / "truth.npy", sim.truth)
    return d


def write_spec(folder: Path, name: str = "job.toml", **sections: dict) -> Path:
    """A spec for the tiny case in ``folder``; keyword tables override / add keys."""
    import tomli_w

    spec: dict[str, dict] = {
        "job": {"name": "tiny"},
        "data": {"psf": "psf.npy", "measurement": "meas.npy", "mask": "mask.npy",
                 "truth": "truth.npy"},
        "network": dict(TINY_NET),
        "stopping": {"max_iter": 40, "patience": 1000},
        "device": {"threads": 1},
        # FISTA-TV at the end (about 1 s here, the tau search) only where a test asks for it
        # (tests/udn/test_ensemble.py): the default's, on, is checked there and in the CLI's
        "output": {"checkpoint_every": 20, "preview_every": 20, "status_seconds": 0.0,
                   "with_fista": False},
    }
    for sec, keys in sections.items():
        spec.setdefault(sec, {}).update(keys)
    for sec in spec.values():
        for k in [k for k, v in sec.items() if v is None]:
            del sec[k]
    p = folder / name
    p.write_text(tomli_w.dumps(spec), encoding="utf-8")
    return p
