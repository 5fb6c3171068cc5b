"""The exact forward model on a grid ``a`` times coarser than the sensor.

A measurement box-downsampled by ``a`` (mean over a x a blocks, as :func:`recon.io.box_downsample`
does) of a scene that is constant on a x a blocks is *exactly* a convolution of the coarse
scene with a coarse kernel, and that kernel is not the box-downsampled PSF. Per axis, with the
fine crop offset ``o_f = Hs // 2`` and the coarse one ``o_c = (Hs // a) // 2``::

    b_a(S) = (1/a) sum_p b(a S + p),   b(s) = sum_i v(i) h(s + o_f - i),  v(i) = v_a(i // a)
    =>  b_a(S) = sum_J v_a(J) h_c(S + o_c - J)
    with h_c(M) = sum_{d=-(a-1)}^{a-1} (a - |d|) / a * h(a M + delta + d),  delta = o_f - a o_c

that is, the PSF filtered by the a x a triangle (box * box: one box for the sensor's block
mean, one for the scene's block) and sampled every ``a`` pixels at phase ``delta``; its support
is one tap wider than ``H // a`` on each side. Box-downsampling the PSF instead (one box, the
wrong phase) leaves a model error of several percent of the measurement's peak for a sharp
caustic, far above the noise of a downsampled measurement; the cross-validation of the plan
then mistakes that error for structure (tests/plan/test_coarse.py measures both).

Scale: the kernel sums to the PSF's sum (each fine PSF pixel is shared by the taps around it
with weights summing to 1 per axis), and the coarse scene is in the fine scene's units
(radiance per fine pixel), because the measurement is block-averaged, not summed.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = ["coarse_psf", "crop_delta"]

F32 = npt.NDArray[np.float32]


def crop_delta(field: int, factor: int) -> int:
    """Phase ``delta = field // 2 - a * ((field // a) // 2)`` of the coarse sampling."""
    return field // 2 - factor * ((field // factor) // 2)


def _axis_kernel(n: int, factor: int, delta: int) -> tuple[npt.NDArray[np.float64], int]:
    """Matrix K (n_c, n): coarse tap M (from m_lo) = sum_s K[M - m_lo, s] h(s); and -m_lo."""
    a = factor
    m_lo = -((a - 1 + delta) // a)  # ceil((-(a - 1) - delta) / a)
    m_hi = (n - 1 + (a - 1) - delta) // a
    taps = m_hi - m_lo + 1
    mat = np.zeros((taps, n), dtype=np.float64)
    for j in range(taps):
        m = j + m_lo
        for d in range(-(a - 1), a):
            s = a * m + delta + d
            if 0 <= s < n:
                mat[j, s] += (a - abs(d)) / a
    return mat, -m_lo


def coarse_psf(psf: Any, factor: int, field: tuple[int, int]) -> tuple[F32, tuple[int, int]]:
    """Coarse kernel of a PSF (..., H, W) for a scene field ``field`` and factor ``a``.

    Returns the kernel (..., Hc, Wc) and its origin (oy, ox): the array index of tap M = 0
    (the crop offset of the coarse model grows by the origin). ``factor = 1`` returns the PSF
    and (0, 0).
    """
    p = np.asarray(psf, dtype=np.float64)
    if p.ndim < 2:
        raise ValueError(f"PSF must have at least 2 axes, got shape {p.shape}")
    a = int(factor)
    if a < 1:
        raise ValueError(f"factor must be >= 1, got {factor}")
    if a == 1:
        return np.asarray(p, dtype=np.float32), (0, 0)
    ky, oy = _axis_kernel(p.shape[-2], a, crop_delta(int(field[0]), a))
    kx, ox = _axis_kernel(p.shape[-1], a, crop_delta(int(field[1]), a))
    # two matrix products (BLAS); the same as np.einsum("ys,...st,xt->...yx", ky, p, kx),
    # which without path optimisation took 20 s on a 540x960 PSF, four times per plan
    out = ky @ p @ kx.T
    return np.asarray(out, dtype=np.float32), (oy, ox)
