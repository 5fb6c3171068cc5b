"""Loading, preprocessing and saving of lensless images.

Array conventions (numpy at every file boundary, float32 unless stated):

- a scene or reconstruction is ``(C, K, H, W)``: colour channels, frames/bands/depth planes,
  rows, columns;
- a measurement is ``(C, H, W)``;
- a PSF is ``(C, H, W)`` and a PSF stack (one PSF per depth plane) is ``(K, H, W)``.

:func:`load_image` reads a file into its raw array (raw dtype, the file's own layout).
The preprocessing functions (:func:`subtract_dark`, :func:`box_downsample`,
:func:`clip_nonneg`, :func:`normalise`, :func:`to_gray`, :func:`to_channel_first`) are small
and composable; :func:`load_psf`, :func:`load_measurement` and :func:`load_psf_stack` chain
them in the fixed order dark -> downsample -> clip -> normalise, and validate the result.

:func:`save_reconstruction` writes a float32 TIFF whose ``ImageDescription`` tag holds the
metadata as JSON (format, version, provenance, shape, data hash and the caller's metadata),
plus 8-bit previews beside it; :func:`read_reconstruction` reads it back and checks it.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from recon.formats import (
    FORMAT_VERSION,
    FormatError,
    array_hash,
    atomic_write,
    json_default,
    provenance,
)

__all__ = [
    "RECONSTRUCTION_FORMAT",
    "RECONSTRUCTION_KINDS",
    "MeasurementCheck",
    "MeasurementWarning",
    "auto_dark_level",
    "box_downsample",
    "check_measurement",
    "check_pair",
    "clip_nonneg",
    "contrast_stretch",
    "downsample_masked",
    "load_false_color_weights",
    "load_image",
    "load_measurement",
    "load_psf",
    "load_psf_stack",
    "normalise",
    "read_reconstruction",
    "save_reconstruction",
    "subtract_dark",
    "to_channel_first",
    "to_gray",
]

PathLike = str | os.PathLike[str]
Array = npt.NDArray[Any]
F32 = npt.NDArray[np.float32]
DarkSpec = float | int | Array | PathLike | None
NormMode = Literal["max", "sum", "l2"]
Channels = Literal["gray", "rgb"]
Kind = Literal["image", "video", "spectral", "depth"]

#: ``format`` key of a saved reconstruction's metadata.
RECONSTRUCTION_FORMAT = "lenslesscam.reconstruction"
#: Kinds of reconstruction :func:`save_reconstruction` knows how to preview.
RECONSTRUCTION_KINDS: tuple[str, ...] = ("image", "video", "spectral", "depth")
#: Keys of a reconstruction's metadata that this module writes (the caller may not set them).
_RESERVED_KEYS = frozenset(
    {
        "format",
        "format_version",
        "kind",
        "shape",
        "axes",
        "dtype",
        "data_hash",
        "provenance",
        "previews",
    }
)

#: Corner patch (rows, columns) whose mean is the 'auto' dark level, as in the DiffuserCam
#: tutorial (``bg = np.mean(psf[5:15, 5:15])``).
AUTO_DARK_PATCH: tuple[slice, slice] = (slice(5, 15), slice(5, 15))

#: Rec. 601 luma weights (R, G, B), as used by OpenCV and Pillow for colour -> gray.
LUMA_WEIGHTS: tuple[float, float, float] = (0.299, 0.587, 0.114)

_TIFF_EXT = (".tif", ".tiff")
_CV_EXT = (".png", ".jpg", ".jpeg", ".bmp")
_ACCEPTED_INT = (np.uint8, np.uint16, np.uint32, np.int16, np.int32)

# --------------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------------


def load_image(path: PathLike, *, key: str | None = None) -> Array:
    """Read an image file into a numpy array with its raw dtype and the file's layout.

    Supported: TIFF (``.tif``/``.tiff``; a multi-page file gives ``(pages, H, W)`` or
    ``(pages, H, W, S)``), PNG/JPEG/BMP (8 or 16 bit kept; colour is returned RGB(A), ``(H, W,
    3|4)``), ``.npy``, ``.npz`` and MATLAB ``.mat`` (v5 through scipy, v7.3 through h5py,
    transposed to MATLAB's axis order). ``key`` names the variable of an ``.npz``/``.mat``; by
    default the only array in the file is taken, else the first present of ``arr_0``, ``psf``,
    ``meas``, ``measurement``, ``image``, ``data``.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: unknown extension, unreadable or corrupt file, missing ``key``.

    """
    return _load_image(path, key=key, prefer=_DEFAULT_KEYS)


_DEFAULT_KEYS: tuple[str, ...] = ("arr_0", "psf", "meas", "measurement", "image", "data")
_PSF_KEYS: tuple[str, ...] = ("psf", "arr_0", "image", "data")
_MEAS_KEYS: tuple[str, ...] = ("meas", "measurement", "b", "arr_0", "image", "data")
_STACK_KEYS: tuple[str, ...] = ("psf", "psfs", "zstack", "stack", "arr_0", "data")


def _load_image(path: PathLike, *, key: str | None, prefer: Sequence[str]) -> Array:
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file")
    if p.is_dir():
        raise ValueError(f"{p}: is a directory, expected an image file")
    ext = p.suffix.lower()
    if ext in _TIFF_EXT:
        return _read_tiff(p)
    if ext in _CV_EXT:
        return _read_cv(p)
    if ext == ".npy":
        return _read_npy(p)
    if ext == ".npz":
        return _read_npz(p, key, prefer)
    if ext == ".mat":
        return _read_mat(p, key, prefer)
    raise ValueError(
        f"{p}: unknown image file extension {p.suffix!r} (expected one of "
        f"{', '.join(_TIFF_EXT + _CV_EXT + ('.npy', '.npz', '.mat'))})"
    )


def _read_tiff(p: Path) -> Array:
    import tifffile

    try:
        with tifffile.TiffFile(p) as tf:
            series = tf.series
            if len(series) <= 1:
                return np.asarray(tf.asarray())
            # Pages written one at a time form one series each: stack them if they agree.
            kinds = {(tuple(s.shape), str(s.dtype)) for s in series}
            if len(kinds) != 1:
                raise ValueError(
                    f"it holds {len(series)} image series of different shapes or dtypes "
                    f"({', '.join(sorted(f'{s} {d}' for s, d in kinds))})"
                )
            return np.stack([np.asarray(s.asarray()) for s in series])
    except Exception as exc:
        raise ValueError(f"cannot read {p} as TIFF: {exc}") from exc


def _read_cv(p: Path) -> Array:
    import cv2

    try:
        buf = np.fromfile(p, dtype=np.uint8)  # imdecode: works with any path encoding
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    except Exception as exc:
        raise ValueError(f"cannot read {p} as {p.suffix[1:].upper()}: {exc}") from exc
    if img is None:
        raise ValueError(f"cannot read {p} as {p.suffix[1:].upper()}: not a valid image file")
    arr = np.asarray(img)
    if arr.ndim == 3 and arr.shape[2] == 3:
        arr = np.ascontiguousarray(arr[:, :, ::-1])  # BGR -> RGB
    elif arr.ndim == 3 and arr.shape[2] == 4:
        arr = np.ascontiguousarray(arr[:, :, [2, 1, 0, 3]])  # BGRA -> RGBA
    return arr


def _read_npy(p: Path) -> Array:
    try:
        arr = np.load(p, allow_pickle=False)
    except Exception as exc:
        raise ValueError(f"cannot read {p} as NPY: {exc}") from exc
    return np.asarray(arr)


def _pick_key(p: Path, keys: Sequence[str], key: str | None, prefer: Sequence[str]) -> str:
    if key is not None:
        if key not in keys:
            raise ValueError(
                f"{p}: no variable {key!r}; available: {', '.join(sorted(keys)) or '(none)'}"
            )
        return key
    if len(keys) == 1:
        return keys[0]
    for k in prefer:
        if k in keys:
            return k
    if not keys:
        raise ValueError(f"{p}: contains no arrays")
    raise ValueError(
        f"{p}: contains several arrays ({', '.join(sorted(keys))}); choose one with key="
    )


def _read_npz(p: Path, key: str | None, prefer: Sequence[str]) -> Array:
    try:
        with np.load(p, allow_pickle=False) as npz:
            keys = list(npz.files)
            k = _pick_key(p, keys, key, prefer)
            return np.asarray(npz[k])
    except ValueError as exc:
        if str(p) in str(exc):
            raise
        raise ValueError(f"cannot read {p} as NPZ: {exc}") from exc
    except Exception as exc:
        raise ValueError(f"cannot read {p} as NPZ: {exc}") from exc


def _read_mat(p: Path, key: str | None, prefer: Sequence[str]) -> Array:
    import h5py

    if h5py.is_hdf5(p):
        return _read_mat73(p, key, prefer)
    import scipy.io

    try:
        mat = scipy.io.loadmat(p)
    except Exception as exc:
        raise ValueError(f"cannot read {p} as MATLAB v5 file: {exc}") from exc
    keys = [k for k in mat if not k.startswith("__")]
    k = _pick_key(p, keys, key, prefer)
    arr = np.asarray(mat[k])
    if arr.dtype.kind not in "biuf":
        raise ValueError(f"{p}: variable {k!r} is not a numeric array (dtype {arr.dtype})")
    return arr


def _read_mat73(p: Path, key: str | None, prefer: Sequence[str]) -> Array:
    import h5py

    try:
        with h5py.File(p, "r") as fh:
            keys = [k for k in fh if not k.startswith("#") and isinstance(fh[k], h5py.Dataset)]
            k = _pick_key(p, keys, key, prefer)
            arr = np.asarray(fh[k][()])
    except ValueError as exc:
        if str(p) in str(exc):
            raise
        raise ValueError(f"cannot read {p} as MATLAB v7.3 file: {exc}") from exc
    except Exception as exc:
        raise ValueError(f"cannot read {p} as MATLAB v7.3 file: {exc}") from exc
    if arr.dtype.kind not in "biuf":
        raise ValueError(f"{p}: variable {k!r} is not a numeric array (dtype {arr.dtype})")
    # HDF5 stores MATLAB's column-major arrays with the axes reversed.
    return np.ascontiguousarray(arr.T)


# --------------------------------------------------------------------------------------------
# Preprocessing
# --------------------------------------------------------------------------------------------


def _as_float(a: Array) -> Array:
    """Float view/copy of ``a``: float arrays keep their dtype, others become float32."""
    arr = np.asarray(a)
    if arr.dtype.kind == "f":
        return arr
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


def subtract_dark(a: Array, dark: float | Array | Literal["auto"]) -> Array:
    """Subtract a dark level: a scalar, a dark frame, or ``'auto'`` (:func:`auto_dark_level`).

    A dark frame must have the shape of ``a`` or of its trailing axes (it is broadcast over
    the leading ones). Returns a float array (float32 for integer input); values may become
    negative (see :func:`clip_nonneg`).
    """
    arr = _as_float(a)
    if isinstance(dark, str):
        if dark != "auto":
            raise ValueError(f"dark must be a number, an array or 'auto', got {dark!r}")
        level = auto_dark_level(arr)
        return np.asarray(arr - level.astype(arr.dtype))
    d = np.asarray(dark)
    if d.ndim == 0:
        if not math.isfinite(float(d)):
            raise ValueError(f"dark level must be finite, got {float(d)}")
        return np.asarray(arr - arr.dtype.type(float(d)))
    if d.shape != arr.shape[arr.ndim - d.ndim :] or d.ndim > arr.ndim:
        raise ValueError(f"dark frame shape {d.shape} does not match image shape {arr.shape}")
    if not np.all(np.isfinite(d)):
        raise ValueError("dark frame contains NaN or infinite values")
    return np.asarray(arr - d.astype(arr.dtype))


def clip_nonneg(a: Array) -> Array:
    """Set negative values to zero (same dtype)."""
    arr = np.asarray(a)
    return np.asarray(np.maximum(arr, arr.dtype.type(0)))


def box_downsample(a: Array, factor: int) -> Array:
    """Mean over ``factor x factor`` blocks of the last two axes; a remainder is dropped.

    Integer input gives float32; float input keeps its dtype. ``factor=1`` returns a float
    copy.
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
    Returns (measurement, mask), float32.
    """
    m = np.asarray(mask, dtype=np.float64)
    b = np.asarray(meas, dtype=np.float64)
    if m.shape != b.shape[-2:]:
        raise ValueError(f"mask of shape {m.shape} does not match the measurement {b.shape}")
    m = (m > 0.5).astype(np.float64)
    if factor == 1:
        return b.astype(np.float32), m.astype(np.float32)
    count = box_downsample(m, factor)
    total = box_downsample(b * m, factor)
    out = np.where(count > 0, total / np.maximum(count, 1e-12), 0.0)
    return out.astype(np.float32), (count > 0).astype(np.float32)


def normalise(a: Array, mode: NormMode = "max") -> Array:
    """Scale ``a`` so its maximum (``'max'``), total (``'sum'``) or L2 norm (``'l2'``) is 1.

    One factor for the whole array, so the relative weights of channels and planes are kept.
    Raises ValueError when that quantity is zero, negative or not finite.
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
    return np.asarray(arr / arr.dtype.type(s))


# The loaders' ``normalise`` argument shadows the function; they call it through this name.
_normalise_fn: Callable[[Array, NormMode], Array] = normalise


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
    to sum 1, so a gray image keeps its level. Float output (float32 for integer input).
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


def check_pair(psf: Array, meas: Array, *, psf_is_stack: bool = False) -> None:
    """Check that a PSF (or PSF stack) fits a measurement; ValueError naming both shapes.

    Both are 3-axis: ``psf`` ``(C, H, W)`` (or ``(K, H, W)`` when ``psf_is_stack``), ``meas``
    ``(C, H, W)``. Height and width must be equal; a non-stack PSF must have one channel or as
    many channels as the measurement.
    """
    ps, ms = np.shape(psf), np.shape(meas)
    if len(ps) != 3 or len(ms) != 3:
        raise ValueError(
            f"PSF shape {ps} and measurement shape {ms}: both must have 3 axes "
            "(C, H, W) (PSF stack: (K, H, W))"
        )
    if ps[-2:] != ms[-2:]:
        raise ValueError(
            f"PSF shape {ps} and measurement shape {ms} do not match: the PSF must have the "
            f"measurement's height and width ({ms[1]}x{ms[2]}), it has {ps[1]}x{ps[2]}"
        )
    if not psf_is_stack and ps[0] not in (1, ms[0]):
        raise ValueError(
            f"PSF shape {ps} and measurement shape {ms} do not match: the PSF has {ps[0]} "
            f"channels, the measurement {ms[0]}"
        )


class MeasurementWarning(UserWarning):
    """A measurement has saturated, negative or no signal (see :func:`check_measurement`)."""


@dataclass(frozen=True)
class MeasurementCheck:
    """What :func:`check_measurement` found; ``flags`` is empty for a clean measurement.

    ``to_dict()`` is meant for the metadata of a reconstruction and its run record.
    """

    n_pixels: int
    full_scale: float | None
    saturated: int
    saturated_fraction: float
    negative: int
    negative_fraction: float
    nonfinite: int
    flags: tuple[str, ...]

    @property
    def flagged(self) -> bool:
        """True when something is worth a warning."""
        return bool(self.flags)

    def message(self) -> str:
        """One line for a log or a warning."""
        if not self.flags:
            return "measurement looks fine"
        parts = []
        if "saturated" in self.flags:
            parts.append(f"{self.saturated} pixels ({100 * self.saturated_fraction:.3g}%) are "
                         f"saturated (at or above full scale {self.full_scale:g}): the forward "
                         "model cannot explain them and the reconstruction near them is biased")
        if "negative" in self.flags:
            parts.append(f"{self.negative} pixels ({100 * self.negative_fraction:.3g}%) are "
                         "negative (dark subtraction); clip_nonneg() clips them")
        if "nonfinite" in self.flags:
            parts.append(f"{self.nonfinite} pixels are NaN or inf")
        if "all_zero" in self.flags:
            parts.append("every measured pixel is 0: the reconstruction is 0")
        return "; ".join(parts)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for metadata."""
        return {"n_pixels": self.n_pixels, "full_scale": self.full_scale,
                "saturated": self.saturated, "saturated_fraction": self.saturated_fraction,
                "negative": self.negative, "negative_fraction": self.negative_fraction,
                "nonfinite": self.nonfinite, "flags": list(self.flags)}


def check_measurement(
    b: Array,
    full_scale: float | None = None,
    *,
    bits: int | None = None,
    mask: Array | None = None,
    warn: bool = False,
) -> MeasurementCheck:
    """Count saturated, negative and non-finite pixels of a measurement and flag them.

    Pixels at or above ``full_scale`` count as saturated. Flags: ``saturated``, ``negative``,
    ``nonfinite``, ``all_zero``.

    Args:
        b: the measurement (any shape; raw counts or normalised).
        full_scale: the value at which the sensor saturates. Default: ``2**bits - 1`` when
            ``bits`` is given, else the maximum of an integer dtype (255 for uint8, 65535 for
            uint16); for float data without either, saturation is not checked.
        bits: the sensor's bit depth (a 12-bit camera in a uint16 container: ``bits=12``).
        mask: pixels to check (nonzero = measured, broadcast to ``b``); default all.
        warn: also emit a :class:`MeasurementWarning` when something is flagged.

    """
    arr = np.asarray(b)
    if arr.dtype.kind not in "fiub":
        raise ValueError(f"a measurement must be numeric, got dtype {arr.dtype}")
    if full_scale is None and bits is not None:
        if isinstance(bits, bool) or not isinstance(bits, int | np.integer) or bits < 1:
            raise ValueError(f"bits must be a positive integer, got {bits!r}")
        full_scale = float(2 ** int(bits) - 1)
    if full_scale is None and arr.dtype.kind in "iu":
        full_scale = float(np.iinfo(arr.dtype).max)
    if full_scale is not None and not (math.isfinite(full_scale) and full_scale > 0):
        raise ValueError(f"full_scale must be a finite number > 0, got {full_scale!r}")
    vals = arr.astype(np.float64, copy=False)
    if mask is not None:
        sel = np.broadcast_to(np.asarray(mask) != 0, arr.shape)
        vals = vals[sel]
    n = int(vals.size)
    finite = np.isfinite(vals)
    nonfinite = n - int(np.count_nonzero(finite))
    fv = vals[finite] if nonfinite else vals
    saturated = int(np.count_nonzero(fv >= full_scale)) if full_scale is not None else 0
    negative = int(np.count_nonzero(fv < 0))
    flags = []
    if saturated:
        flags.append("saturated")
    if negative:
        flags.append("negative")
    if nonfinite:
        flags.append("nonfinite")
    if n and not np.any(fv != 0) and not nonfinite:
        flags.append("all_zero")
    check = MeasurementCheck(n, None if full_scale is None else float(full_scale), saturated,
                             saturated / n if n else 0.0, negative, negative / n if n else 0.0,
                             nonfinite, tuple(flags))
    if warn and check.flagged:
        warnings.warn(check.message(), MeasurementWarning, stacklevel=2)
    return check


def _validate_raw(a: Array, p: Path, what: str) -> None:
    dt = a.dtype
    if dt.kind == "f":
        n_nan = int(np.count_nonzero(np.isnan(a)))
        if n_nan:
            raise ValueError(f"{what} file {p} contains {n_nan} NaN values")
        n_inf = int(np.count_nonzero(np.isinf(a)))
        if n_inf:
            raise ValueError(f"{what} file {p} contains {n_inf} infinite values")
    elif dt.kind in "iu":
        if dt.type not in _ACCEPTED_INT:
            raise ValueError(
                f"{what} file {p} has unsupported integer dtype {dt} (expected uint8, uint16, "
                "uint32, int16, int32 or float)"
            )
    else:
        raise ValueError(
            f"{what} file {p} has unsupported dtype {dt} (expected integer or float pixels)"
        )
    if a.size == 0:
        raise ValueError(f"{what} file {p} is empty (shape {a.shape})")


def _to_chw(a: Array, p: Path, what: str) -> Array:
    if a.ndim not in (2, 3):
        raise ValueError(
            f"{what} file {p} has shape {a.shape}: expected a 2D image (H, W) or a colour "
            "image (H, W, 3)"
        )
    try:
        return to_channel_first(a)
    except ValueError as exc:
        hint = "; for a stack of PSFs use load_psf_stack" if what == "PSF" else ""
        raise ValueError(f"{what} file {p}: {exc}{hint}") from exc


def _select_channels(a: Array, channels: Channels, p: Path, what: str) -> Array:
    if channels == "gray":
        return to_gray(a)
    if channels == "rgb":
        if a.shape[0] == 1:
            raise ValueError(f"{what} file {p} is grayscale; cannot load it with channels='rgb'")
        return a[:3]
    raise ValueError(f"channels must be 'gray' or 'rgb', got {channels!r}")


def _dark_for(
    dark: DarkSpec, key: str | None, image: Array, channels: Channels | None, what: str, p: Path
) -> float | Array | Literal["auto"] | None:
    """Turn a ``dark`` argument into what :func:`subtract_dark` takes, matched to ``image``.

    A dark *file* gets the image's treatment (channel-first, channel selection; for a stack,
    ``channels=None``: one gray plane). A dark *array* is used as given and must match the
    image's shape or its trailing (H, W).
    """
    if dark is None:
        return None
    if isinstance(dark, str) and dark == "auto":
        return "auto"
    if isinstance(dark, str | os.PathLike):
        dp = Path(dark)
        d = _load_image(dp, key=key, prefer=_DEFAULT_KEYS)
        _validate_raw(d, dp, "dark")
        if channels is None:
            if d.ndim == 3:
                d = to_gray(_to_chw(d, dp, "dark"))[0]
        else:
            d = _select_channels(_to_chw(d, dp, "dark"), channels, dp, "dark")
        d = _as_float(d)
    elif isinstance(dark, int | float | np.integer | np.floating):
        return float(dark)
    else:
        d = np.asarray(dark)
        if d.ndim == 0:
            return float(d)
    if d.shape != image.shape and d.shape != image.shape[-2:]:
        raise ValueError(
            f"dark frame shape {d.shape} does not match {what} file {p} of shape {image.shape}"
        )
    return d


def _prepare(
    path: PathLike,
    *,
    what: str,
    dark: DarkSpec,
    downsample: int,
    channels: Channels,
    key: str | None,
    prefer: Sequence[str],
) -> tuple[F32, Path]:
    p = Path(path)
    raw = _load_image(p, key=key, prefer=prefer)
    _validate_raw(raw, p, what)
    chw = _select_channels(_to_chw(raw, p, what), channels, p, what)
    arr = _as_float(chw).astype(np.float32, copy=False)
    d = _dark_for(dark, key, arr, channels, what, p)
    if d is not None:
        arr = subtract_dark(arr, d).astype(np.float32, copy=False)
    out = clip_nonneg(box_downsample(arr, downsample)).astype(np.float32, copy=False)
    return out, p


def load_psf(
    path: PathLike,
    *,
    dark: DarkSpec = None,
    downsample: int = 1,
    channels: Channels = "gray",
    normalise: NormMode | None = "sum",
    key: str | None = None,
) -> F32:
    """Load a PSF as float32 ``(C, H, W)``: dark -> downsample -> clip at 0 -> normalise.

    Args:
        path: image file (see :func:`load_image`).
        dark: ``None``, a level, a dark frame (array or file) or ``'auto'`` (corner patch
            ``[5:15, 5:15]`` as in the DiffuserCam tutorial); subtracted at full resolution.
        downsample: box-filter factor over rows and columns.
        channels: ``'gray'`` (luma, ``C = 1``) or ``'rgb'`` (``C = 3``).
        normalise: ``'sum'`` (unit total, default), ``'max'``, ``'l2'`` or ``None``; one
            factor for all channels, so the colour balance is kept.
        key: variable name in an ``.npz``/``.mat`` file.

    Raises:
        FileNotFoundError, ValueError: missing file, unreadable file, NaN/inf values, bad
            dtype or shape, all-zero PSF.

    """
    arr, p = _prepare(
        path,
        what="PSF",
        dark=dark,
        downsample=downsample,
        channels=channels,
        key=key,
        prefer=_PSF_KEYS,
    )
    if not np.any(arr > 0):
        extra = f" after dark subtraction (dark={_describe_dark(dark)})" if dark is not None else ""
        raise ValueError(f"PSF file {p} is all zero{extra}")
    if normalise is not None:
        arr = _normalise_fn(arr, normalise)
    return np.ascontiguousarray(arr, dtype=np.float32)


def load_measurement(
    path: PathLike,
    *,
    dark: DarkSpec = None,
    downsample: int = 1,
    channels: Channels = "gray",
    normalise: NormMode | None = "max",
    key: str | None = None,
) -> F32:
    """Load a measurement as float32 ``(C, H, W)``: dark -> downsample -> clip -> normalise.

    Same arguments as :func:`load_psf`; by default the result is scaled to maximum 1
    (``normalise=None`` keeps the counts). Raises for NaN/inf values, a bad dtype or shape, and
    an all-zero measurement when it is to be normalised.
    """
    arr, p = _prepare(
        path,
        what="measurement",
        dark=dark,
        downsample=downsample,
        channels=channels,
        key=key,
        prefer=_MEAS_KEYS,
    )
    if normalise is not None:
        if not np.any(arr > 0):
            raise ValueError(f"measurement file {p} is all zero; cannot normalise it")
        arr = _normalise_fn(arr, normalise)
    return np.ascontiguousarray(arr, dtype=np.float32)


def load_psf_stack(
    paths: PathLike | Sequence[PathLike],
    *,
    dark: DarkSpec = None,
    downsample: int = 1,
    normalise: NormMode | None = "max",
    key: str | None = None,
) -> F32:
    """Load a depth PSF stack as float32 ``(K, H, W)`` (grayscale).

    ``paths`` is a sequence of single-plane files (one per depth, in order), a folder (its
    image files in sorted name order), or one file holding the whole stack (multi-page TIFF,
    or a 3-axis ``.npy``/``.npz``/``.mat`` array ``(K, H, W)``). Each plane: dark ->
    downsample -> clip at 0; then one normalisation for the whole stack (default ``'max'``,
    the convention of the DiffuserCam 3D data), which keeps the planes' relative energies.
    """
    planes: list[Array] = []
    names: list[Path] = []
    if isinstance(paths, str | os.PathLike):
        p = Path(paths)
        if p.is_dir():
            exts = (*_TIFF_EXT, *_CV_EXT, ".npy")
            files = sorted(
                f for f in p.iterdir() if f.suffix.lower() in exts and not f.name.startswith(".")
            )
            if not files:
                raise ValueError(f"{p}: folder contains no image files")
            return load_psf_stack(
                files, dark=dark, downsample=downsample, normalise=normalise, key=key
            )
        raw = _load_image(p, key=key, prefer=_STACK_KEYS)
        _validate_raw(raw, p, "PSF stack")
        if raw.ndim == 2:
            raw = raw[np.newaxis]
        if raw.ndim != 3:
            raise ValueError(
                f"PSF stack file {p} has shape {raw.shape}: expected (K, H, W) grayscale planes"
            )
        planes = [raw[k] for k in range(raw.shape[0])]
        names = [p] * len(planes)
    else:
        if len(paths) == 0:
            raise ValueError("load_psf_stack: no files given")
        for item in paths:
            q = Path(item)
            raw = _load_image(q, key=key, prefer=_PSF_KEYS)
            _validate_raw(raw, q, "PSF")
            if raw.ndim == 3:
                raw = to_gray(_to_chw(raw, q, "PSF"))[0]
            elif raw.ndim != 2:
                raise ValueError(f"PSF file {q} has shape {raw.shape}: expected one 2D plane")
            planes.append(raw)
            names.append(q)
    shape0 = planes[0].shape
    for q, pl in zip(names, planes, strict=True):
        if pl.shape != shape0:
            raise ValueError(
                f"PSF plane {q} has shape {pl.shape}, but the first plane ({names[0]}) has {shape0}"
            )
    stack = np.stack([_as_float(pl).astype(np.float32, copy=False) for pl in planes])
    d = _dark_for(dark, key, stack, None, "PSF stack", names[0])
    if d is not None:
        stack = subtract_dark(stack, d).astype(np.float32, copy=False)
    stack = clip_nonneg(box_downsample(stack, downsample))
    for k in range(stack.shape[0]):
        if not np.any(stack[k] > 0):
            raise ValueError(f"PSF stack plane {k} ({names[k]}) is all zero")
    if normalise is not None:
        stack = _normalise_fn(stack, normalise)
    return np.ascontiguousarray(stack, dtype=np.float32)


def _describe_dark(dark: DarkSpec) -> str:
    if isinstance(dark, np.ndarray):
        return f"frame of shape {dark.shape}"
    return str(dark)


# --------------------------------------------------------------------------------------------
# Saving and reading reconstructions
# --------------------------------------------------------------------------------------------


def contrast_stretch(a: Array, lo_pct: float = 0.1, hi_pct: float = 99.9) -> npt.NDArray[np.uint8]:
    """Map ``a`` to uint8 linearly between its ``lo_pct`` and ``hi_pct`` percentiles.

    One pair of levels for the whole array (so the frames of a video share them); a constant
    array maps to 0.
    """
    arr = np.asarray(a, dtype=np.float64)
    finite = arr[np.isfinite(arr)]
    if finite.size == 0:
        return np.zeros(arr.shape, dtype=np.uint8)
    lo, hi = np.percentile(finite, [lo_pct, hi_pct])
    if not hi > lo:
        return np.zeros(arr.shape, dtype=np.uint8)
    scaled = np.clip((np.nan_to_num(arr, nan=lo) - lo) / (hi - lo), 0.0, 1.0)
    return np.asarray(np.round(scaled * 255.0), dtype=np.uint8)


def _montage(frames: Array, pad: int = 2) -> Array:
    """Tile ``(K, ..., H, W)``-leading frames (K, C, H, W) into one (C, H', W') image."""
    k, c, h, w = frames.shape
    cols = math.ceil(math.sqrt(k))
    rows = math.ceil(k / cols)
    out = np.zeros(
        (c, rows * h + (rows - 1) * pad, cols * w + (cols - 1) * pad), dtype=frames.dtype
    )
    for i in range(k):
        r, q = divmod(i, cols)
        out[:, r * (h + pad) : r * (h + pad) + h, q * (w + pad) : q * (w + pad) + w] = frames[i]
    return out


def _pil_image(chw8: npt.NDArray[np.uint8]) -> Any:
    from PIL import Image

    if chw8.shape[0] == 1:
        return Image.fromarray(chw8[0], mode=None)
    if chw8.shape[0] == 3:
        return Image.fromarray(np.ascontiguousarray(np.moveaxis(chw8, 0, -1)))
    raise ValueError(f"cannot preview {chw8.shape[0]} channels (need 1 or 3)")


def _write_png(path: Path, chw8: npt.NDArray[np.uint8]) -> Path:
    img = _pil_image(chw8)
    return atomic_write(path, lambda tmp: img.save(tmp, format="PNG"))


def _preview_channels(x: Array) -> Array:
    """(C, K, H, W) -> (C', K, H, W) with C' in (1, 3): gray stays, RGB stays, else mean."""
    if x.shape[0] in (1, 3):
        return x
    return np.asarray(x.mean(axis=0, keepdims=True))


def save_reconstruction(
    path: PathLike,
    x: Array,
    metadata: Mapping[str, Any] | None = None,
    *,
    kind: Kind = "image",
    false_color: Array | None = None,
) -> list[Path]:
    """Save a reconstruction ``(C, K, H, W)`` as float32 TIFF with JSON metadata and previews.

    The TIFF holds ``C * K`` pages of ``H x W`` (channel-major) and its ``ImageDescription`` is
    JSON: ``format`` (``'lenslesscam.reconstruction'``), ``format_version``, ``kind``, ``shape``,
    ``axes`` (``'CKHW'``), ``dtype``, ``data_hash``, ``provenance`` and the caller's
    ``metadata`` keys (method, parameters, PSF hash, ...; they must be JSON-serialisable and may
    not reuse those names). Previews beside it (8-bit, contrast-stretched at the 0.1/99.9
    percentiles of the whole array):

    - ``<stem>.png``: the image (a montage of the K frames when ``K > 1``);
    - ``kind='video'``: ``<stem>.gif``, the frames animated;
    - ``kind='spectral'``: ``<stem>_falsecolor.png``, bands mapped to RGB by ``false_color``
      (``(3, K)`` weights; default: the SpectralDiffuserCam calibration resampled to K, see
      :func:`load_false_color_weights`);
    - ``kind='depth'``: ``<stem>_mip.png``, the maximum-intensity projection over K.

    Every file is written atomically. Returns the written paths, TIFF first.
    """
    import tifffile

    target = Path(path)
    if target.suffix.lower() not in _TIFF_EXT:
        raise ValueError(f"{target}: a reconstruction is saved as .tif or .tiff")
    if kind not in RECONSTRUCTION_KINDS:
        raise ValueError(f"kind must be one of {', '.join(RECONSTRUCTION_KINDS)}, got {kind!r}")
    arr = np.asarray(x)
    if arr.ndim != 4:
        raise ValueError(f"a reconstruction must be (C, K, H, W), got shape {arr.shape}")
    if arr.dtype.kind not in "fiu":
        raise ValueError(f"a reconstruction must be numeric, got dtype {arr.dtype}")
    arr = np.ascontiguousarray(arr, dtype=np.float32)
    c, k, h, w = arr.shape
    if min(arr.shape) == 0:
        raise ValueError(f"a reconstruction must not be empty, got shape {arr.shape}")
    user = dict(metadata or {})
    clash = sorted(_RESERVED_KEYS & set(user))
    if clash:
        raise ValueError(f"metadata keys {clash} are reserved for the file format")
    weights: Array | None = None
    if kind == "spectral":
        if false_color is None:
            from recon.samples import false_color_calib_path

            weights = load_false_color_weights(false_color_calib_path(), k)
        else:
            weights = np.asarray(false_color, dtype=np.float64)
            if weights.shape != (3, k):
                raise ValueError(
                    f"false_color weights must have shape (3, K) = (3, {k}), got {weights.shape}"
                )
    meta: dict[str, Any] = {
        "format": RECONSTRUCTION_FORMAT,
        "format_version": FORMAT_VERSION,
        "kind": kind,
        "shape": [c, k, h, w],
        "axes": "CKHW",
        "dtype": "float32",
        "data_hash": array_hash(arr),
        "provenance": provenance(),
    }
    meta.update(user)
    try:
        description = json.dumps(meta, default=json_default, ensure_ascii=True)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"metadata is not JSON-serialisable: {exc}") from exc

    pages = arr.reshape(c * k, h, w)

    def _write_tiff(tmp: Path) -> None:
        tifffile.imwrite(
            tmp,
            pages,
            photometric="minisblack",
            description=description,
            metadata=None,
            bigtiff=pages.nbytes > 2**31,
        )

    written = [atomic_write(target, _write_tiff)]

    shown = _preview_channels(arr)  # (C', K, H, W)
    u8 = contrast_stretch(shown)
    frames = np.moveaxis(u8, 1, 0)  # (K, C', H, W)
    still = frames[0] if k == 1 else _montage(frames)
    written.append(_write_png(target.with_suffix(".png"), still))
    if kind == "video":
        written.append(_write_gif(target.with_suffix(".gif"), frames))
    elif kind == "spectral" and weights is not None:
        cube = arr.mean(axis=0).astype(np.float64)  # (K, H, W)
        rgb = np.tensordot(weights, cube, axes=(1, 0))  # (3, H, W)
        written.append(
            _write_png(target.with_name(target.stem + "_falsecolor.png"), contrast_stretch(rgb))
        )
    elif kind == "depth":
        mip = shown.max(axis=1)  # (C', H, W)
        written.append(
            _write_png(target.with_name(target.stem + "_mip.png"), contrast_stretch(mip))
        )
    return written


def _write_gif(path: Path, frames: npt.NDArray[np.uint8], duration_ms: int = 100) -> Path:
    images = [_pil_image(f) for f in frames]

    def _save(tmp: Path) -> None:
        images[0].save(
            tmp, format="GIF", save_all=True, append_images=images[1:], duration=duration_ms, loop=0
        )

    return atomic_write(path, _save)




def read_reconstruction(path: PathLike) -> tuple[F32, dict[str, Any]]:
    """Read a TIFF written by :func:`save_reconstruction`: ``(array (C, K, H, W), metadata)``.

    Raises:
        FileNotFoundError: no such file.
        FormatError: not a lenslesscam reconstruction (foreign TIFF, missing or wrong
            ``format``), a newer ``format_version``, or corrupt data (shape or hash mismatch).

    """
    import tifffile

    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file")
    try:
        with tifffile.TiffFile(p) as tf:
            first = tf.pages.first
            desc = first.description
            data = np.asarray(tf.asarray())
    except Exception as exc:
        raise FormatError(f"cannot read {p} as TIFF: {exc}") from exc
    try:
        meta = json.loads(desc)
    except (TypeError, ValueError) as exc:
        raise FormatError(
            f"{p} is not a lenslesscam reconstruction (no JSON metadata in its description)"
        ) from exc
    if not isinstance(meta, dict) or meta.get("format") != RECONSTRUCTION_FORMAT:
        found = meta.get("format") if isinstance(meta, dict) else None
        raise FormatError(
            f"{p} is not a lenslesscam reconstruction (format {found!r}, expected "
            f"{RECONSTRUCTION_FORMAT!r})"
        )
    version = meta.get("format_version")
    if not isinstance(version, int) or version < 1 or version > FORMAT_VERSION:
        raise FormatError(
            f"{p}: reconstruction format_version {version!r} is not supported by this release "
            f"(reads 1..{FORMAT_VERSION})"
        )
    shape = meta.get("shape")
    if (
        not isinstance(shape, list)
        or len(shape) != 4
        or not all(isinstance(s, int) and s > 0 for s in shape)
    ):
        raise FormatError(f"{p}: metadata shape {shape!r} is not (C, K, H, W)")
    if data.size != math.prod(shape) or data.dtype != np.float32:
        raise FormatError(
            f"{p}: data of shape {data.shape} ({data.dtype}) does not match metadata shape "
            f"{tuple(shape)} (float32); the file is corrupt"
        )
    arr = np.ascontiguousarray(data.reshape(shape), dtype=np.float32)
    expected = meta.get("data_hash")
    if expected is not None and array_hash(arr) != expected:
        raise FormatError(f"{p}: data hash does not match its metadata; the file is corrupt")
    return arr, meta


# --------------------------------------------------------------------------------------------
# False colour
# --------------------------------------------------------------------------------------------


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
        v = np.asarray(_load_image(p, key=name, prefer=()), dtype=np.float64).ravel()
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
