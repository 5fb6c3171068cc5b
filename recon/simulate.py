"""Simulated measurements through the same forward models that the solvers invert.

Order of effects: clean = A v; optionally scaled so its maximum is 1 (``normalise``); Poisson
noise at ``photons`` expected photo-electrons for a value of 1; Gaussian noise of standard
deviation ``noise`` (in units of the normalised measurement); saturation at ``saturation``;
quantisation to ``bits`` over [0, saturation or 1]; then the erasures: exactly
round(f * H * W) sensor pixels are set to 0 and marked 0 in the mask (shared by all channels).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from recon.models import ForwardModel
from recon.operators import Conv2D, Crop

__all__ = ["Simulation", "erasure_mask", "render_frames", "simulate"]


def erasure_mask(shape: tuple[int, int], fraction: float, seed: int = 0) -> np.ndarray:
    """A (H, W) float32 mask with exactly round(fraction * H * W) zeros (erased pixels)."""
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"erasure fraction must be in [0, 1], got {fraction}")
    h, w = shape
    n = h * w
    n_erased = round(fraction * n)
    mask = np.ones(n, dtype=np.float32)
    idx = np.random.default_rng(seed).permutation(n)[:n_erased]
    mask[idx] = 0.0
    return mask.reshape(h, w)


@dataclass
class Simulation:
    """A simulated measurement and everything needed to score a reconstruction of it."""

    meas: np.ndarray
    mask: np.ndarray | None
    clean: np.ndarray
    truth: np.ndarray
    scale: float
    saturated: int
    params: dict[str, Any] = field(default_factory=dict)

    @property
    def saturated_fraction(self) -> float:
        """Fraction of the sensor's pixels that were clipped at ``saturation``."""
        return self.saturated / self.meas.size if self.meas.size else 0.0


def simulate(
    model: ForwardModel,
    scene: Any,
    *,
    erasure: float = 0.0,
    noise: float = 0.0,
    photons: float | None = None,
    bits: int | None = None,
    saturation: float | None = None,
    normalise: bool = True,
    seed: int = 0,
) -> Simulation:
    """Simulate a measurement of ``scene`` (C, K, Hs, Ws) through ``model``.

    The model must have no mask of its own (the erasure mask is drawn here); build the
    reconstruction model with ``mask=sim.mask``.
    """
    if model.mask is not None:
        raise ValueError("simulate() draws its own erasure mask: pass a model without a mask")
    v = np.asarray(scene, dtype=np.float64)
    if v.shape != model.scene_shape:
        raise ValueError(f"scene has shape {v.shape}, the model expects {model.scene_shape}")
    if not np.isfinite(v).all():
        raise ValueError("scene contains NaN or inf values")
    if noise < 0 or (photons is not None and photons <= 0):
        raise ValueError("noise must be >= 0 and photons > 0")
    with torch.no_grad():
        clean = model.apply(torch.as_tensor(v, dtype=model.op.dtype)).double().numpy()
    peak = float(clean.max())
    scale = 1.0 / peak if (normalise and peak > 0) else 1.0
    clean = clean * scale
    rng = np.random.default_rng(seed)
    meas = clean.copy()
    if photons is not None:
        try:
            meas = rng.poisson(np.clip(meas, 0, None) * photons) / photons
        except ValueError as exc:  # numpy's "lam value too large"
            raise ValueError(f"photons {photons:g} is too many to draw Poisson noise for "
                             f"({exc}); leave it out: the noise is negligible there") from None
    if noise > 0:
        meas = meas + rng.normal(0.0, noise, size=meas.shape)
    top = float(np.max(np.abs(meas)))
    if not top <= float(np.finfo(np.float32).max):
        cause = f"noise {noise:g}: use a smaller noise" if noise > 0 else "scale the scene"
        raise ValueError(f"the simulated measurement reaches {top:.3g}, beyond the float32 "
                         f"range it is saved in ({cause})")
    saturated = 0
    if saturation is not None:
        saturated = int((meas >= saturation).sum())
        meas = np.minimum(meas, saturation)
    if bits is not None:
        top = saturation if saturation is not None else 1.0
        levels = 2**bits - 1
        meas = np.round(np.clip(meas, 0, top) / top * levels) / levels * top
    mask = None
    if erasure > 0:
        hw = (int(model.meas_shape[-2]), int(model.meas_shape[-1]))
        mask = erasure_mask(hw, erasure, seed=seed + 1)
        meas = meas * mask
    params = {"erasure": erasure, "noise": noise, "photons": photons, "bits": bits,
              "saturation": saturation, "normalise": normalise, "seed": seed,
              "model": model.kind.value, "saturated": saturated,
              "saturated_fraction": saturated / meas.size if meas.size else 0.0}
    return Simulation(meas.astype(np.float32), mask, clean.astype(np.float32),
                      v.astype(np.float32), scale, saturated, params)


def render_frames(psf: np.ndarray) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """A renderer for the simulated camera: ``render(frames (K,Hs,Ws), shutter (K,H)) -> (H,W)``.

    This is the function the app injects into ``drivers.SimulatedCamera``: it computes
    ``sum_k M_k . crop(h * v_k)`` with the same operators as the video forward model the solvers
    invert (float64; the operators are cached per scene shape).
    """
    psf64 = np.asarray(psf, dtype=np.float64)
    if psf64.ndim != 2:
        raise ValueError(f"render_frames needs a 2D PSF (H, W), got shape {psf64.shape}")
    sensor = (int(psf64.shape[0]), int(psf64.shape[1]))
    cache: dict[tuple[int, ...], tuple[Conv2D, Crop]] = {}

    def render(frames: np.ndarray, shutter: np.ndarray) -> np.ndarray:
        f = np.asarray(frames, dtype=np.float64)
        m = np.asarray(shutter, dtype=np.float64)
        if f.ndim != 3 or m.shape != (f.shape[0], sensor[0]):
            raise ValueError(f"render: frames {f.shape} and shutter {m.shape} do not fit a "
                             f"sensor of {sensor[0]} rows")
        key = tuple(f.shape)
        if key not in cache:
            cache.clear()
            conv = Conv2D(psf64, (1, *f.shape), dtype=torch.float64)
            crop = Crop(conv.out_shape, sensor, (f.shape[1] // 2, f.shape[2] // 2),
                        dtype=torch.float64)
            cache[key] = (conv, crop)
        conv, crop = cache[key]
        with torch.no_grad():
            per_k = crop.apply(conv.apply(torch.as_tensor(f)[None]))[0]  # (K, H, W)
            out = (per_k * torch.as_tensor(m)[:, :, None]).sum(dim=0)
        return np.asarray(out.numpy())

    return render


def synthetic_psf(shape: tuple[int, int], n_points: int = 40, blur: float = 1.0,
                  seed: int = 0) -> np.ndarray:
    """A caustic-like pseudorandom PSF (sparse blurred points), unit sum, float32.

    For tests and for the simulated camera when no measured PSF is given; real work uses a
    measured PSF (see ``recon.samples``).
    """
    from scipy.ndimage import gaussian_filter

    h, w = shape
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w), dtype=np.float64)
    ys = rng.integers(h // 8, h - h // 8, n_points)
    xs = rng.integers(w // 8, w - w // 8, n_points)
    np.add.at(img, (ys, xs), rng.uniform(0.5, 1.0, n_points))
    img = gaussian_filter(img, blur) if blur > 0 else img
    return np.asarray(img / img.sum(), dtype=np.float32)
