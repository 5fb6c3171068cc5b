"""False colour: map spectral bands to RGB with the SpectralDiffuserCam calibration weights."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import numpy.typing as npt

from recon.readers import load_image

__all__ = ["load_false_color_weights"]

PathLike = str | os.PathLike[str]


def load_false_color_weights(path_mat: PathLike, n_bands: int) -> npt.NDArray[np.float64]:
    """Read SpectralDiffuserCam's ``red``/``green``/``blue`` weights and resample to n_bands.

    The file holds three ``(1, 65)`` vectors mapping 65 bands to RGB. The result is ``(3,
    n_bands)``: the weights are treated as a piecewise-constant function over the band axis,
    averaged over each of ``n_bands`` equal spans and scaled by ``65 / n_bands``, so each
    colour's total weight is kept (a flat spectrum gives the same colour at any n_bands).
    """
    if isinstance(n_bands, bool) or not isinstance(n_bands, int | np.integer) or n_bands < 1:
        raise ValueError(f"n_bands must be a positive integer, got {n_bands!r}")
    p = Path(path_mat)
    rows = []
    for name in ("red", "green", "blue"):
        v = np.asarray(load_image(p, key=name, prefer=()), dtype=np.float64).ravel()
        if v.size == 0 or not np.all(np.isfinite(v)):
            raise ValueError(f"{p}: variable {name!r} is empty or not finite")
        rows.append(v)
    n0 = rows[0].size
    if any(r.size != n0 for r in rows):
        raise ValueError(
            f"{p}: red, green and blue have different lengths "
            f"({', '.join(str(r.size) for r in rows)})"
        )
    w = np.stack(rows)  # (3, n0)
    return _resample_bins(w, int(n_bands))


def _resample_bins(w: npt.NDArray[np.float64], n: int) -> npt.NDArray[np.float64]:
    """Integrate a piecewise-constant (3, n0) function over n equal bins of [0, n0]."""
    n0 = w.shape[1]
    cum = np.concatenate([np.zeros((w.shape[0], 1)), np.cumsum(w, axis=1)], axis=1)
    edges = np.linspace(0.0, n0, n + 1)
    integ = np.stack([np.interp(edges, np.arange(n0 + 1), c) for c in cum])
    return np.diff(integ, axis=1)
