"""Synthetic test scenes shared by the solver tests."""

from __future__ import annotations

from typing import Any

import numpy as np


def blocks_scene(h: int, w: int, seed: int = 0, count: int = 5) -> np.ndarray:
    """``count`` overlapping rectangles of random brightness on a zero background, (h, w)."""
    rng = np.random.default_rng(seed)
    s = np.zeros((h, w))
    for _ in range(count):
        y0, x0 = rng.integers(0, h - 4), rng.integers(0, w - 4)
        dy, dx = rng.integers(3, h // 2), rng.integers(3, w // 2)
        s[y0 : y0 + dy, x0 : x0 + dx] += rng.uniform(0.3, 1)
    return s


def disc_case(erasure: float, h: int = 40, w: int = 48) -> tuple[Any, Any, np.ndarray]:
    """A bright disc on a grey field through a synthetic PSF, ``erasure`` of the pixels erased,
    1 % noise: (the masked model, the measurement as a tensor, the truth)."""
    import torch

    from recon.models import build_model
    from recon.simulate import simulate, synthetic_psf

    y, x = np.mgrid[0:h, 0:w] / w
    scene = (0.2 + 0.6 * ((x - 0.4) ** 2 + (y - 0.4) ** 2 < 0.05))[None, None]
    psf = synthetic_psf((h, w), seed=3)
    sim = simulate(build_model("2d", psf), scene.astype(np.float32), erasure=erasure,
                   noise=0.01, seed=0)
    return build_model("2d", psf, mask=sim.mask), torch.as_tensor(sim.meas), sim.truth


def dataset_layout_pair(folder: Any, shape: tuple[int, int] = (24, 32), seed: int = 3) -> Any:
    """A colour pair in the DiffuserCam MirFlickr layout, written to ``folder``.

    ``psf.npy``: a padded-grid PSF (2H, 2W, 3); ``meas.npy``: the sensor, its central window
    (H, W, 3); ``truth.npy``: the scene on the sensor's field (H, W, 3); all stored BGR and
    upside-down, as the dataset stores them. Returns the upright RGB scene (3, 1, H, W).
    """
    from pathlib import Path

    import torch

    from recon.models import build_model

    h, w = shape
    rng = np.random.default_rng(seed)
    psf = rng.random((2 * h, 2 * w)).astype(np.float32) ** 6
    psf3 = np.stack([psf * g for g in (0.9, 1.0, 1.1)])  # RGB
    scene = np.zeros((3, 1, h, w), np.float32)
    scene[0, :, h // 6:h // 2, w // 6:w * 5 // 8] = 1.0
    scene[1, :, h * 5 // 12:h * 5 // 6, w * 3 // 8:w * 7 // 8] = 0.8
    scene[2, :, 2:h - 2, 2:w // 4] = 0.6
    full = build_model("2d", psf3, field=(h, w)).apply(torch.as_tensor(scene)).numpy()
    meas = full[:, h // 2:h // 2 + h, w // 2:w // 2 + w]

    def stored(a: Any) -> Any:  # (3, H, W) RGB upright -> (H, W, 3) BGR upside-down
        return np.ascontiguousarray(a[::-1, ::-1].transpose(1, 2, 0))

    d = Path(folder)
    np.save(d / "psf.npy", stored(psf3))
    np.save(d / "meas.npy", stored(meas))
    np.save(d / "truth.npy", stored(scene[:, 0]))
    return scene
