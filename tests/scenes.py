"""Synthetic test scenes shared by the solver tests."""

from __future__ import annotations

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
