"""Preprocessing of lensless images: small composable steps, and THE downsampling rules.

Dark subtraction (:func:`subtract_dark`, :func:`auto_dark_level`), clipping
(:func:`clip_nonneg`), box downsampling (:func:`box_downsample`), normalisation
(:func:`normalise`), channel layout (:func:`to_channel_first`, :func:`to_gray`), and the one rule
each for downsampling a masked measurement (:func:`downsample_masked`, :func:`downsample_mask`:
a coarse pixel is measured when ANY sensor pixel under it is, its value the mean of the
measured ones) and a shutter function (:func:`downsample_rows`: the mean of ``factor`` rows;
:func:`bin_time`: the mean of ``factor`` time bins).
Pure numpy.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

__all__ = [
    "AUTO_DARK_PATCH",
    "LUMA_WEIGHTS",
    "ChannelOrder",
    "Channels",
    "NormMode",
    "auto_dark_level",
    "bin_time",
    "box_downsample",
    "clip_nonneg",
    "downsample_mask",
    "downsample_masked",
    "downsample_rows",
    "measurement_dark_level",
    "normalise",
    "normalise_factor",
    "subtract_dark",
    "to_channel_first",
    "to_gray",
]

Array = npt.NDArray[Any]
F32 = npt.NDArray[np.float32]
NormMode = Literal["max", "sum", "l2"]
Channels = Literal["gray", "rgb"]
ChannelOrder = Literal["rgb", "bgr"]


#: Corner patch (rows, columns) whose mean is the 'auto' dark level, as in the DiffuserCam
#: tutorial (``bg = np.mean(psf[5:15, 5:15])``).
AUTO_DARK_PATCH: tuple[slice, slice] = (slice(5, 15), slice(5, 15))


#: Rec. 601 luma weights (R, G, B), as used by OpenCV and Pillow for colour -> gray.
LUMA_WEIGHTS: tuple[float, float, float] = (0.299, 0.587, 0.114)


def _as_float(a: Array) -> Array:
    """Float view/copy of ``a``: float arrays keep their dtype, others become float32.

    32- and 64-bit integers become float64, which holds them (float32 keeps 24 bits: a 0..200
    signal on a 1e9 pedestal kept 4 levels); the loaders cast to float32 after the dark level
    is subtracted.
    """
    arr = np.asarray(a)
    if arr.dtype.kind == "f":
        return arr
    if arr.dtype.kind in "iu" and arr.dtype.itemsize >= 4:
        return arr.astype(np.float64)
    return arr.astype(np.float32)


def auto_dark_level(a: Array) -> Array:
    """Dark level as the DiffuserCam tutorial estimates it: mean of ``a[..., 5:15, 5:15]``.

    Returns an array broadcastable against ``a`` (one level per leading index, e.g. per
    colour channel, shape ``(..., 1, 1)``).
    """
    arr = np.asarray(a)
    if arr.ndim < 2 or arr.shape[-2] < 15 or arr.shape[-1] < 15:
        raise ValueError(
            f"cannot estimate the dark level: image of shape {arr.shape} is smaller than "
            "the 15x15 corner needed for patch [5:15, 5:15]"
        )
    patch = arr[(..., *AUTO_DARK_PATCH)].astype(np.float64)
    return np.asarray(patch.mean(axis=(-2, -1), keepdims=True))


def measurement_dark_level(a: Array, measured: Array | None = None) -> Array:
    """Dark level of a lensless measurement estimated from itself: its 1st percentile.

    Every pixel of a lensless frame sees scene light (a caustic covers the sensor), so no patch
    is dark and any estimate from the frame errs high; its darkest pixels err least (on the
    simulated bench, black level 100: 1st percentile 152, corner patch mean 330; the app's
    preview 28.2 against 23.9 dB). One level per leading index (colour channel), shape
    ``(..., 1, 1)``, over the ``measured`` pixels (an (H, W) mask, nonzero = measured) when given.
    The one rule of ``--dark auto`` on a measurement without a recorded black level and of the
    app's automatic dark level; a PSF's is :func:`auto_dark_level` (its corner is unlit).
    """
    arr = np.asarray(a)  # in its own dtype: a float64 copy of every frame cost the preview
    if arr.ndim < 2:  # 2.4x the time of the partition itself
        raise ValueError(f"cannot estimate the dark level of an image of shape {arr.shape}")
    flat = arr.reshape(*arr.shape[:-2], -1)
    if measured is not None and np.shape(measured) == arr.shape[-2:]:
        keep = np.asarray(measured).reshape(-1) > 0
        if keep.any():
            flat = flat[..., keep]
    k = flat.shape[-1] // 100
    level = np.partition(flat, k, axis=-1)[..., k].astype(np.float64)
    return np.asarray(level)[..., None, None]


def subtract_dark(a: Array, dark: float | Array | Literal["auto"]) -> Array:
    """Subtract a dark level: a scalar, a dark frame, or ``'auto'`` (:func:`auto_dark_level`).

    A dark frame must have the shape of ``a`` or of its trailing axes (it is broadcast over
    the leading ones). Returns a float array (as :func:`_as_float`: float32 for integers of up
    to 16 bits, float64 for wider ones); values may become negative (see :func:`clip_nonneg`).
    """
    arr = _as_float(a)
    if isinstance(dark, str):
        if dark != "auto":
            raise ValueError(f"dark must be a number, an array or 'auto', got {dark!r}")
        level = auto_dark_level(arr)
        return np.asarray(arr - level.astype(arr.dtype))
    d = np.asarray(dark)
    top = float(np.finfo(arr.dtype).max)  # beyond it the cast overflows to inf (numpy warns)
    if d.ndim == 0:
        if not (math.isfinite(float(d)) and float(d) >= 0):
            raise ValueError(f"dark level must be a finite number >= 0 (the sensor's black "
                             f"offset), got {float(d)}")
        if float(d) > top:
            raise ValueError(f"dark level {float(d):g} is beyond the range of the {arr.dtype} "
                             f"image it is subtracted from (up to {top:.3g}): it would leave "
                             "every pixel at -inf; give the sensor's black level in the file's "
                             "units")
        return np.asarray(arr - arr.dtype.type(float(d)))
    if d.shape != arr.shape[arr.ndim - d.ndim :] or d.ndim > arr.ndim:
        raise ValueError(f"dark frame shape {d.shape} does not match image shape {arr.shape}")
    if not np.all(np.isfinite(d)):
        raise ValueError("dark frame contains NaN or infinite values")
    big = float(np.max(np.abs(d))) if d.size and d.dtype.kind == "f" else 0.0
    if big > top:
        raise ValueError(f"dark frame has values up to {big:.3g}, beyond the range of the "
                         f"{arr.dtype} image it is subtracted from (up to {top:.3g}); rescale it")
    return np.asarray(arr - d.astype(arr.dtype))


def clip_nonneg(a: Array) -> Array:
    """Set negative values to zero (same dtype)."""
    arr = np.asarray(a)
    return np.asarray(np.maximum(arr, arr.dtype.type(0)))


def box_downsample(a: Array, factor: int) -> Array:
    """Mean over ``factor x factor`` blocks of the last two axes; a remainder is dropped.

    Integer input gives float32 (float64 for 32- and 64-bit integers, :func:`_as_float`);
    float input keeps its dtype. ``factor=1`` returns a float copy.
    """
    if isinstance(factor, bool) or not isinstance(factor, int | np.integer) or factor < 1:
        raise ValueError(f"downsample factor must be a positive integer, got {factor!r}")
    f = int(factor)
    arr = _as_float(a)
    if arr.ndim < 2:
        raise ValueError(f"box_downsample needs at least 2 axes, got shape {arr.shape}")
    h, w = arr.shape[-2] // f, arr.shape[-1] // f
    if h == 0 or w == 0:
        raise ValueError(
            f"downsample factor {f} is larger than the image ({arr.shape[-2]}x{arr.shape[-1]})"
        )
    if f == 1:
        return arr.copy()
    cropped = arr[..., : h * f, : w * f]
    blocks = cropped.reshape(*arr.shape[:-2], h, f, w, f)
    return np.asarray(blocks.mean(axis=(-3, -1), dtype=np.float64), dtype=arr.dtype)


def downsample_masked(meas: Array, mask: Array, factor: int) -> tuple[F32, F32]:
    """Box-downsample a measurement (C, H, W) that has erased pixels (mask (H, W), 1 = measured).

    A coarse pixel is the mean over its *measured* sub-pixels (erased pixels hold no data, so
    averaging their zeros in would bias it) and counts as measured when any sub-pixel is.
    Erased pixels (coarse ones with no measured sub-pixel) are 0 in the result, whatever the
    file held there (a hot pixel, NaN): they must not set the measurement's scale nor count in
    a residual. Returns (measurement, mask), float32.
    """
    m = np.asarray(mask, dtype=np.float64)
    b = np.asarray(meas, dtype=np.float64)
    if m.shape != b.shape[-2:]:
        raise ValueError(f"mask of shape {m.shape} does not match the measurement {b.shape}")
    m = (m > 0.5).astype(np.float64)
    b = np.where(m > 0, b, 0.0)
    if factor == 1:
        return b.astype(np.float32), m.astype(np.float32)
    count = box_downsample(m, factor)
    total = box_downsample(b, factor)
    out = np.where(count > 0, total / np.maximum(count, 1e-12), 0.0)
    return out.astype(np.float32), downsample_mask(m, factor)


def downsample_mask(mask: Array, factor: int) -> F32:
    """The coarse mask of a sensor mask (H, W) (1 = measured): THE mask downsampling rule.

    A coarse pixel is measured when ANY sensor pixel under it is (its value, in
    :func:`downsample_masked`, is the mean of the measured ones), so no measured pixel is
    lost. Every command (FISTA, UDN jobs, planner, trade, GUI) downsamples masks this way.
    """
    m = np.asarray(mask)
    return (box_downsample(m > 0.5, factor) > 0).astype(np.float32)


def _shutter_and_factor(shutter: Array, factor: int) -> tuple[npt.NDArray[np.float64], int]:
    """A shutter function M (K, rows) as float64 and a checked integer factor >= 1."""
    m = np.asarray(shutter, dtype=np.float64)
    if m.ndim != 2:
        raise ValueError(f"shutter must be (K, rows), got shape {m.shape}")
    if isinstance(factor, bool) or int(factor) != factor or factor < 1:
        raise ValueError(f"factor must be an integer >= 1, got {factor!r}")
    return m, int(factor)


def downsample_rows(shutter: Array, factor: int) -> npt.NDArray[np.float64]:
    """THE shutter downsampling rule: average ``factor`` consecutive rows of M (K, rows).

    Matches a measurement box-downsampled by ``factor``; trailing rows that do not fill a
    block are dropped, as box downsampling drops them.
    """
    m, f = _shutter_and_factor(shutter, factor)
    rows = (m.shape[1] // f) * f
    if rows == 0:
        raise ValueError(f"cannot downsample {m.shape[1]} rows by {f}")
    return np.asarray(m[:, :rows].reshape(m.shape[0], rows // f, f).mean(axis=2))


def bin_time(shutter: Array, factor: int) -> npt.NDArray[np.float64]:
    """THE time-binning rule: merge ``factor`` consecutive time bins of M (K, rows).

    The mean, so a bin of width ``factor * w`` keeps the units of M. A trailing partial group
    is averaged over ``factor`` too (it is a bin with less exposure).
    """
    m, f = _shutter_and_factor(shutter, factor)
    k = m.shape[0]
    k_new = -(-k // f)
    padded = np.zeros((k_new * f, m.shape[1]), dtype=np.float64)
    padded[:k] = m
    return np.asarray(padded.reshape(k_new, f, m.shape[1]).mean(axis=1))


def normalise(a: Array, mode: NormMode = "max") -> Array:
    """Scale ``a`` so its maximum (``'max'``), total (``'sum'``) or L2 norm (``'l2'``) is 1.

    One factor for the whole array, so the relative weights of channels and planes are kept:
    ``a`` divided by :func:`normalise_factor` ``(a, mode)``. Raises ValueError when that
    quantity is zero, negative or not finite.
    """
    arr = _as_float(a)
    s = normalise_factor(arr, mode)
    if s > float(np.finfo(arr.dtype).max):  # the factor itself overflows the array's type
        return np.asarray(arr.astype(np.float64) / s).astype(arr.dtype)
    return np.asarray(arr / arr.dtype.type(s))


def normalise_factor(a: Array, mode: NormMode = "max") -> float:
    """The factor :func:`normalise` divides ``a`` by: its maximum, total or L2 norm.

    A Python float (in the units of ``a``), so a caller can record it and undo the scaling.
    Raises ValueError when it is zero, negative or not finite.
    """
    arr = _as_float(a)
    if mode == "max":
        s = float(np.max(arr))
    elif mode == "sum":
        s = float(np.sum(arr, dtype=np.float64))
    elif mode == "l2":
        s = float(np.linalg.norm(arr.ravel().astype(np.float64)))
    else:
        raise ValueError(f"normalise mode must be 'max', 'sum' or 'l2', got {mode!r}")
    if not math.isfinite(s) or s <= 0:
        raise ValueError(f"cannot normalise by {mode}: it is {s} (must be positive)")
    return s


def to_channel_first(a: Array, layout: Literal["auto", "hwc", "chw"] = "auto") -> Array:
    """Bring an image to channel-first ``(C, H, W)``.

    ``(H, W)`` becomes ``(1, H, W)``; ``(H, W, 3|4)`` is transposed. With ``layout='auto'`` a
    3-axis array whose last axis has 3 or 4 entries (and whose first does not have 1, 3 or 4)
    is taken as HWC, one whose first axis has 1, 3 or 4 entries as CHW; anything else is
    ambiguous (for example a stack of pages) and raises ValueError.
    """
    arr = np.asarray(a)
    if arr.ndim == 2:
        return arr[np.newaxis]
    if arr.ndim != 3:
        raise ValueError(
            f"expected an image of shape (H, W), (H, W, C) or (C, H, W), got shape {arr.shape}"
        )
    if layout == "hwc":
        return np.ascontiguousarray(np.moveaxis(arr, -1, 0))
    if layout == "chw":
        return arr
    if layout != "auto":
        raise ValueError(f"layout must be 'auto', 'hwc' or 'chw', got {layout!r}")
    first_c = arr.shape[0] in (1, 3, 4)
    last_c = arr.shape[2] in (3, 4)
    if last_c and not first_c:
        return np.ascontiguousarray(np.moveaxis(arr, -1, 0))
    if first_c and not last_c:
        return arr
    if first_c and last_c:  # e.g. (3, H, 3): take the smaller leading axis as channels
        raise ValueError(f"cannot tell the channel axis of shape {arr.shape}; pass layout=")
    raise ValueError(
        f"cannot tell the channel axis of shape {arr.shape}: not (H, W, 3|4) nor (1|3|4, H, W)"
        " (a multi-page stack?)"
    )


def to_gray(a: Array, weights: Sequence[float] = LUMA_WEIGHTS) -> Array:
    """Channel-first colour ``(C, ...)`` to gray ``(1, ...)`` with the Rec. 601 luma weights.

    ``C = 1`` is returned unchanged, ``C = 4`` (RGBA) drops alpha. The weights are normalised
    to sum 1, so a gray image keeps its level. Float output (as :func:`_as_float`).
    """
    arr = _as_float(a)
    if arr.ndim < 1:
        raise ValueError("to_gray needs a channel axis")
    c = arr.shape[0]
    if c == 1:
        return arr
    if c == 4:
        arr = arr[:3]
        c = 3
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != (c,):
        raise ValueError(f"to_gray: {c} channels but {w.size} weights")
    w = w / w.sum()
    out = np.tensordot(w, arr.astype(np.float64), axes=(0, 0))[np.newaxis]
    return out.astype(arr.dtype)
