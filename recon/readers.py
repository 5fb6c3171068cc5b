"""Readers: image files to arrays, and the PSF / measurement / PSF stack loaders.

:func:`load_image` reads a file into its raw array (raw dtype, the file's own layout): TIFF,
PNG/JPEG/BMP, ``.npy``, ``.npz``, MATLAB ``.mat`` (v5 and v7.3). :func:`load_psf`,
:func:`load_measurement` and :func:`load_psf_stack` chain the steps of :mod:`recon.preprocess`
in the fixed order dark -> channels -> downsample -> clip -> normalise, and validate the
result with errors naming the file. Whole problems (mask, shutter, filters, truth, the
downsampling rules) are loaded by :func:`recon.problem.load_problem`.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from recon.inputwarnings import warn_input
from recon.preprocess import (
    ChannelOrder,
    Channels,
    NormMode,
    _as_float,
    box_downsample,
    clip_nonneg,
    normalise,
    subtract_dark,
    to_channel_first,
    to_gray,
)
from recon.textfmt import percent

__all__ = ["FILTER_KEYS", "FRAME_FORMAT", "DarkSpec", "EmptyPsfError", "PathLike", "load_image",
           "load_measurement", "load_psf", "load_psf_any", "load_psf_stack",
           "recorded_black_level"]

PathLike = str | os.PathLike[str]
Array = npt.NDArray[Any]
F32 = npt.NDArray[np.float32]
DarkSpec = float | int | Array | PathLike | None


_TIFF_EXT = (".tif", ".tiff")


_CV_EXT = (".png", ".jpg", ".jpeg", ".bmp")


_ACCEPTED_INT = (np.uint8, np.uint16, np.uint32, np.int16, np.int32)


class EmptyPsfError(ValueError):
    """A PSF (or a stack plane) with no positive value after its dark was subtracted."""

def load_image(
    path: PathLike, *, key: str | None = None, prefer: Sequence[str] | None = None
) -> Array:
    """Read an image file into a numpy array with its raw dtype and the file's layout.

    Supported: TIFF (``.tif``/``.tiff``; a multi-page file gives ``(pages, H, W)`` or
    ``(pages, H, W, S)``), PNG/JPEG/BMP (8 or 16 bit kept; colour is returned RGB(A), ``(H, W,
    3|4)``), ``.npy``, ``.npz`` and MATLAB ``.mat`` (v5 through scipy, v7.3 through h5py,
    transposed to MATLAB's axis order). ``key`` names the variable of an ``.npz``/``.mat``; by
    default the only array in the file is taken, else the first present of ``arr_0``, ``psf``,
    ``meas``, ``measurement``, ``image``, ``data`` (``prefer`` replaces that list).

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: unknown extension, unreadable or corrupt file, missing ``key``.

    """
    return _load_image(path, key=key, prefer=_DEFAULT_KEYS if prefer is None else prefer)


_DEFAULT_KEYS: tuple[str, ...] = ("arr_0", "psf", "meas", "measurement", "image", "data")


_PSF_KEYS: tuple[str, ...] = ("psf", "arr_0", "image", "data")


_MEAS_KEYS: tuple[str, ...] = ("meas", "measurement", "b", "arr_0", "image", "data")
#: a dark file: a plain dark frame, or the pixel maps of ``calibrate darks`` (its mean dark)
_DARK_KEYS: tuple[str, ...] = ("dark_mean", "dark", *_DEFAULT_KEYS)


_STACK_KEYS: tuple[str, ...] = ("psf", "psfs", "zstack", "stack", "arr_0", "data")


FILTER_KEYS: tuple[str, ...] = ("filters", "mask", "arr_0", "data")
"""The variables a filter cube's ``.mat``/``.npz`` is read from, in order (recon and
``calibrate filters`` alike)."""


def _load_image(path: PathLike, *, key: str | None, prefer: Sequence[str]) -> Array:
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file")
    if p.is_dir():
        raise ValueError(f"{p}: is a directory, expected an image file")
    if not p.is_file():  # reading a named pipe waits for a writer forever
        raise ValueError(f"{p}: not a regular file (a pipe, socket or device); save the data "
                         "to a file")
    ext = p.suffix.lower()
    if ext == ".npz":
        _check_ours(p)
    if ext in _TIFF_EXT:
        data = _read_tiff(p)
        _check_ours(p, data)
        return data
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


#: The format name of a frame the drivers save (``drivers.camera.FRAME_FORMAT``: recon does
#: not import drivers; a test keeps the two equal).
FRAME_FORMAT = "lenslesscam-frame"


def recorded_black_level(path: PathLike) -> float | None:
    """The camera's black level a saved frame records (``Frame.black_level``), else None.

    What ``dark='auto'`` subtracts from such a frame instead of estimating a level from its
    pixels: the code an unlit pixel reads, as the camera reported it. None for any other file,
    a frame saved before the level was recorded, or a camera that does not report one; a
    recorded value that is not a number >= 0 (a damaged file) is None with a warning naming it.
    """
    meta = _our_metadata(Path(path))
    if not meta or meta.get("format") != FRAME_FORMAT:
        return None
    value = meta.get("black_level")
    if value is None:
        return None
    level = (float(value) if isinstance(value, int | float) and not isinstance(value, bool)
             else float("nan"))
    if np.isfinite(level) and level >= 0:
        return level
    from recon.checks import MeasurementWarning

    warn_input(f"frame file {path} records black_level {value!r}, not a number >= 0: not used "
               "(the dark level is estimated from the pixels; give --dark N)",
               MeasurementWarning, stacklevel=4)
    return None


def _our_metadata(p: Path) -> dict[str, Any] | None:
    """The metadata a TIFF's first description or an ``.npz``'s ``metadata`` entry holds.

    Cheap (the pixels are not read); None for a file without such JSON or one that cannot be
    read (its reader says why).
    """
    import json

    try:
        if p.suffix.lower() == ".npz":
            with np.load(p, allow_pickle=False) as z:
                if "metadata" not in z.files:
                    return None
                raw = z["metadata"]
                meta = json.loads(str(raw)) if raw.ndim == 0 and raw.dtype.kind == "U" else None
        else:
            import tifffile

            with tifffile.TiffFile(p) as tf:
                meta = json.loads(tf.pages.first.description)
    except Exception:
        return None
    return meta if isinstance(meta, dict) else None


def _check_ours(p: Path, data: Array | None = None) -> None:
    """Refuse a calibration or reconstruction file of ours that is newer or corrupt.

    Read as a plain image, a file whose metadata declares one of our formats kept its pixels
    and lost its checks: a newer ``format_version`` or pixels that fail their hash were used
    silently. Its own reader's checks run first, raising :class:`~recon.formats.FormatError`:
    on ``data``, a TIFF's pixels as read already (one read, not two), or, for an ``.npz``
    (small: pixel maps, shutters), by :func:`recon.calibfile.load_calibration`.
    """
    meta = _our_metadata(p)
    if meta is None:
        return
    from recon.calibfile import CALIBRATION_FORMATS, checked_calibration_tiff, load_calibration
    from recon.reconfile import RECONSTRUCTION_FORMAT, checked_reconstruction

    fmt = meta.get("format")
    if fmt in CALIBRATION_FORMATS.values():
        if data is None:
            load_calibration(p)
        else:
            checked_calibration_tiff(p, meta, data)
    elif fmt == RECONSTRUCTION_FORMAT and data is not None:
        checked_reconstruction(p, meta, data)


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
    with open(p, "rb") as f:
        magic = f.read(6)
    if magic != b"\x93NUMPY":  # numpy would call anything else pickled data
        raise ValueError(f"cannot read {p} as NPY: not a NumPy .npy file (no NPY header)")
    try:
        arr = np.load(p, allow_pickle=False)
    except ValueError as exc:
        if "allow_pickle" in str(exc):  # numpy's advice to unpickle: never taken here
            raise ValueError(f"cannot read {p} as NPY: it holds Python objects, not numbers "
                             "(pickled data is never loaded)") from exc
        raise ValueError(f"cannot read {p} as NPY: {exc}") from exc
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
        f"{p}: contains several arrays ({', '.join(sorted(keys))}) and none is named "
        f"{', '.join(prefer)}: choose one with --key where the command has it, or name it so "
        "(or save it alone)"
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


_normalise_fn: Callable[[Array, NormMode], Array] = normalise


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
    if dt.kind == "f":
        _check_subnormal(a, p, what)
    if dt.kind == "f" and dt.itemsize > 4:  # read into float32: its range must hold the values
        top = float(np.max(np.abs(a)))
        f32 = np.finfo(np.float32)
        if top > float(f32.max):
            raise ValueError(f"{what} file {p} has values up to {top:.3g}, beyond the float32 "
                             f"range (up to {float(f32.max):.3g}) it is read into; rescale it")
        if 0.0 < top < float(f32.smallest_normal):
            raise ValueError(f"{what} file {p} has values no larger than {top:.3g}, below the "
                             f"float32 range (from {float(f32.smallest_normal):.3g}) it is read "
                             "into; rescale it")


def _check_subnormal(a: Array, p: Path, what: str) -> None:
    """Refuse float data whose largest magnitude is below its dtype's smallest normal number.

    Such values are subnormal: they keep fewer significant bits the smaller they are (a
    float32 image scaled by 1e-44 holds 7 distinct values and reconstructs as noise), so the
    image is lost to rounding, or all but; it is a file written in the wrong units.
    """
    fi = np.finfo(a.dtype)
    top = float(np.max(np.abs(a)))
    if not 0.0 < top < float(fi.smallest_normal):
        return
    bits = max(1, int(np.floor(np.log2(top / float(fi.smallest_subnormal)))) + 1)
    raise ValueError(f"{what} file {p} has values no larger than {top:.3g}, below the smallest "
                     f"normal {a.dtype} number ({float(fi.smallest_normal):.3g}): subnormal "
                     f"numbers that keep at most {bits} significant bits ({fi.nmant + 1} in "
                     f"a normal {a.dtype}); save the data in its own units (or rescale it)")


def _to_chw(a: Array, p: Path, what: str) -> Array:
    if a.ndim not in (2, 3):
        raise ValueError(
            f"{what} file {p} has shape {a.shape}: expected a 2D image (H, W) or a colour "
            "image (H, W, 3)"
        )
    try:
        return to_channel_first(a)
    except ValueError as exc:
        hint = ("; a stack of PSFs (depth planes) is read with --model depth --psf-stack "
                "FILE (psf_stack in a job spec)" if what == "PSF" else "")
        raise ValueError(f"{what} file {p}: {exc}{hint}") from exc


def _select_channels(
    a: Array, channels: Channels, p: Path, what: str, order: ChannelOrder = "rgb",
    shared_gray: bool = False,
) -> Array:
    if order not in ("rgb", "bgr"):
        raise ValueError(f"channel order must be 'rgb' or 'bgr', got {order!r}")
    if order == "bgr" and a.shape[0] >= 3:  # the file stores B, G, R: make it R, G, B
        a = np.concatenate([a[2::-1], a[3:]])
    if channels == "gray":
        return to_gray(a)
    if channels == "rgb":
        if a.shape[0] == 1 and shared_gray:
            return a  # one plane for every colour channel (the caller shares it)
        if a.shape[0] == 1:
            raise ValueError(f"{what} file {p} is grayscale; cannot load it with channels='rgb'")
        return a[:3]
    raise ValueError(f"channels must be 'gray' or 'rgb', got {channels!r}")


def _dark_for(
    dark: DarkSpec,
    key: str | None,
    image: Array,
    channels: Channels | None,
    what: str,
    p: Path,
    order: ChannelOrder = "rgb",
    measured: Array | None = None,
) -> float | Array | Literal["auto"] | None:
    """Turn a ``dark`` argument into what :func:`subtract_dark` takes, matched to ``image``.

    A dark *file* gets the image's treatment (channel-first, channel selection; for a stack,
    ``channels=None``: one gray plane). A dark *array* is used as given and must match the
    image's shape or its trailing (H, W).
    """
    if dark is None:
        return None
    if isinstance(dark, str) and dark == "auto":
        recorded = recorded_black_level(p)  # the camera's own level beats an estimate
        if recorded is not None:
            return recorded
        if what == "measurement":  # no unlit corner on a lensless frame: its darkest pixels
            from recon.preprocess import measurement_dark_level

            level = measurement_dark_level(image, measured)
            return np.broadcast_to(level, np.shape(image))
        return "auto"  # a PSF: its corner patch, unlit around the caustic
    if isinstance(dark, str | os.PathLike):
        dp = Path(dark)
        d = _load_image(dp, key=key, prefer=_DARK_KEYS)
        _validate_raw(d, dp, "dark")
        if channels is None:
            if d.ndim == 3:
                d = to_gray(_to_chw(d, dp, "dark"))[0]
        else:
            d = _select_channels(_to_chw(d, dp, "dark"), channels, dp, "dark", order)
        d = _as_float(d)
        if d.ndim >= 2 and image.ndim >= 2 and d.shape[-2:] != image.shape[-2:]:
            # a dark frame (or the pixel maps of ``calibrate darks``) of another sensor size
            raise ValueError(
                f"dark file {dp} is {d.shape[-2]}x{d.shape[-1]} (rows x columns) and the "
                f"{what} file {p} is {image.shape[-2]}x{image.shape[-1]}: take the dark at the "
                "same sensor size, ROI and binning"
            )
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


#: a raw measurement with at least this fraction of its pixels at full scale is warned about
#: when read (a few hot or bright pixels of a sensor are not: one pixel at 65535 in the 3D
#: DiffuserCam example frame is 0.001 %; 0.1 % of a 2-megapixel frame is 2000 pixels)
SATURATION_WARN_FRACTION = 1e-3


def _check_saturation(raw: Array, p: Path) -> None:
    """Warn of a raw measurement (integer data) with many pixels at full scale.

    Many: ``SATURATION_WARN_FRACTION`` or more of its pixels. Every pixel saturated is an
    error: the file holds no image.
    """
    from recon.checks import MeasurementWarning, check_measurement

    check = check_measurement(raw)
    if not check.saturated:
        return
    if check.saturated == check.n_pixels:
        raise ValueError(f"measurement file {p}: every pixel is saturated (at the full scale "
                         f"{check.full_scale:g} of {raw.dtype}): it holds no image; capture it "
                         "with a shorter exposure")
    if check.saturated_fraction < SATURATION_WARN_FRACTION:
        return
    only = replace(check, flags=("saturated",))
    warn_input(f"measurement file {p}: {only.message()}", MeasurementWarning, stacklevel=4)


#: a raw measurement read without a dark level whose darkest pixels are at least this fraction
#: of its brightest is warned about: a sensor's black level (sCMOS: about 100 codes) taken for
#: light. The real raw frames at hand are far below it with their dark levels in (the DiffuserCam
#: tutorial's hand 0.6 %, dark about 34 codes; the 3D example 0.2 %, dark about 100): bright
#: frames, where a black level costs little. The simulated bench frame without its dark level
#: of 100 is at 41 %, and its reconstruction's correlation with the scene falls from 0.99 to
#: 0.25. Lensless frames with no black level can sit on a floor of their own (the caustics of
#: a bright scene overlap): the MirFlickr measurements, dark removed, at up to 10 %, simulated
#: ones of the bundled scenes at 6-12 %; a fifth stays above them.
BLACK_LEVEL_WARN_FRACTION = 0.2


#: a measurement read without a mask that is exactly 0 on at least this fraction of its pixels
#: in the file (before any dark subtraction) is warned about: erased or dead pixels
#: (``simulate --erasure`` writes 0 there) read as black light, which the reconstruction fits
#: (90 % erasures without their mask: 9.3 dB against 14.7). A sensor's raw frame is not 0
#: where it is dark (its black level, its noise): the real frames at hand have no pixel at 0.
UNMASKED_ZERO_WARN_FRACTION = 0.25


def _check_unmasked_zeros(chw: Array, p: Path) -> None:
    """Warn of a measurement file, read with no mask, that is 0 in many of its pixels."""
    from recon.checks import MeasurementWarning

    zero = float(np.mean(np.all(chw == 0, axis=0)))
    if zero >= UNMASKED_ZERO_WARN_FRACTION:
        warn_input(
            f"measurement file {p}: {percent(zero)} of its pixels are 0 and no mask was "
            "given: erased or dead pixels would be fitted as black; give their mask (--mask, "
            "the spec's mask; 1 = measured)", MeasurementWarning, stacklevel=4)


def _check_black_level(raw: Array, p: Path) -> None:
    """Warn of raw (integer) data, read with no dark level, that sits on a floor.

    The floor is the 0.1th percentile (a few dark or dead pixels do not hide it); a floor of
    ``BLACK_LEVEL_WARN_FRACTION`` of the maximum or more is most likely the sensor's black
    level, which the reconstruction would take for light.
    """
    from recon.checks import MeasurementWarning

    if raw.dtype.kind not in "ui" or raw.size == 0:
        return
    top = float(raw.max())
    floor = float(np.percentile(raw, 0.1))
    if top <= 0 or floor < BLACK_LEVEL_WARN_FRACTION * top:
        return
    warn_input(
        f"measurement file {p}: raw {raw.dtype} data read with no dark level, and its darkest "
        f"pixels are at {floor:g} ({100 * floor / top:.0f} % of its maximum {top:g}): a "
        "sensor's black level would be taken for light; give the dark level (--dark N, 'auto' "
        "or a dark frame; 0 if the camera removes it)", MeasurementWarning, stacklevel=4)


def _prepare(
    path: PathLike,
    *,
    what: str,
    dark: DarkSpec,
    downsample: int,
    channels: Channels,
    key: str | None,
    prefer: Sequence[str],
    order: ChannelOrder = "rgb",
    shared_gray: bool = False,
    unmasked: bool = False,
    measured: Array | None = None,
) -> tuple[F32, Path]:
    p = Path(path)
    if what == "PSF":
        _refuse_a_stack(p)
    raw = _load_image(p, key=key, prefer=prefer)
    _validate_raw(raw, p, what)
    chw = _select_channels(_to_chw(raw, p, what), channels, p, what, order, shared_gray)
    _check_planes(raw, p, what, channels)
    if what == "PSF" and np.any(raw):  # constant or clipped: a one-line PsfWarning (all zero:
        # the error below says more)
        from recon.psfcheck import check_psf

        check_psf(raw, warn=True, name=f"PSF file {p}")
        if dark is None:
            _check_psf_black_level(raw, p, what)
    elif what == "measurement":
        _check_saturation(raw, p)
        if dark is None:
            _check_black_level(raw, p)
        if unmasked:
            _check_unmasked_zeros(chw, p)
    # float64 for data float32 cannot hold until the dark level is off (a 0..200 signal on a
    # 1e9 pedestal kept 4 levels when the pedestal was subtracted after the cast to float32)
    arr = _as_float(chw)
    d = _dark_for(dark, key, chw, channels, what, p, order, measured)
    if d is not None:
        arr = _subtract_dark(arr, d, p, what)  # into float32
    arr = arr.astype(np.float32, copy=False)
    _check_negative(arr, p, dark, measured, what)
    out = clip_nonneg(box_downsample(arr, downsample)).astype(np.float32, copy=False)
    return out, p


def _check_planes(raw: Array, p: Path, what: str, channels: Channels) -> None:
    """Warn of planes first ``(3|4, H, W)`` read as colour where they may be frames.

    A colour image file stores its channels last (H, W, 3|4); planes first is how a stack of
    frames (a burst, a multi-page TIFF, a NumPy stack) comes. Four planes are read as R, G, B
    and alpha, the fourth dropped; three, read as gray, are mixed with the luma weights. Both
    are right for a colour image and silently wrong for frames, so they are said (three planes
    read as ``rgb`` are what was asked for, and stay silent).
    """
    if raw.ndim != 3 or raw.shape[0] not in (3, 4) or raw.shape[2] in (3, 4):
        return
    n = raw.shape[0]
    if n == 3 and channels != "gray":
        return
    how = ("read as R, G, B and alpha: the fourth plane is dropped" if n == 4 else
           "read as R, G, B and mixed to one gray plane (luma weights)")
    if n == 4 and channels == "gray":
        how += ", the other three mixed to gray"
    from recon.checks import MeasurementWarning
    from recon.psfcheck import PsfWarning

    warn_input(f"{what} file {p} has {n} planes first {tuple(raw.shape)}, {how}; if they are "
               f"{n} frames (a burst or a multi-page stack), not colour channels, give one "
               "file per frame", MeasurementWarning if what == "measurement" else PsfWarning,
               stacklevel=4)


def _subtract_dark(arr: Array, d: Any, p: Path, what: str) -> F32:
    """:func:`subtract_dark` into float32, its errors naming the file."""
    try:
        return subtract_dark(arr, d).astype(np.float32, copy=False)
    except ValueError as exc:
        raise ValueError(f"{what} file {p}: {exc}") from None


def _check_psf_black_level(raw: Array, p: Path, what: str, stacklevel: int = 4) -> None:
    """Warn of a raw (integer) PSF, read with no dark level, whose floor holds much light.

    The rule is :data:`recon.psfcheck.FLOOR_WARN_SHARE`: a caustic's darkest pixels hold
    almost none of its light, so a floor (its 0.1th percentile) that would hold 5 % or more
    of it is a black level (or ambient light), which the reconstruction takes for light.
    """
    from recon.psfcheck import FLOOR_WARN_SHARE, PsfWarning, psf_floor

    if raw.dtype.kind not in "ui" or raw.size == 0:
        return
    floor, share = psf_floor(raw)
    if share < FLOOR_WARN_SHARE:
        return
    warn_input(
        f"{what} file {p}: raw {raw.dtype} data read with no dark level, and its darkest pixels "
        f"are at {floor:g} counts, a floor that holds {100 * share:.0f} % of its light (a "
        "caustic's darkest pixels hold almost none): a sensor's black level would be taken for "
        "light; give the dark level: --dark N (the PSF's too) or --psf-dark N; 0 if the camera "
        "removes it", PsfWarning, stacklevel=stacklevel)


def _check_negative(arr: Array, p: Path, dark: DarkSpec, measured: Array | None,
                    what: str = "measurement", stacklevel: int = 4) -> None:
    """Warn of a measurement or PSF mostly below 0 after its dark level, before the clip at 0.

    The rule is :func:`recon.checks.negative_after_dark`, one entry for both: more than 5 %
    of the (measured) pixels negative, and deep enough to matter (a measurement: below -5 % of
    its maximum; a PSF, whose peaks hide that: together 5 % of its light); read noise around a
    correct dark stays silent. ``measured``: the mask (H, W) of the file's pixels, when
    known; else every pixel counts. ``what``: ``'measurement'`` (a
    :class:`MeasurementWarning`), ``'PSF'`` or ``'PSF stack'`` (a :class:`PsfWarning`).
    """
    from recon.checks import MeasurementWarning, negative_after_dark
    from recon.psfcheck import PsfWarning

    mask = None
    if measured is not None and np.shape(measured) == arr.shape[-2:]:
        mask = measured
    is_meas = what == "measurement"
    msg = negative_after_dark(arr, mask, kind="measurement" if is_meas else "PSF")
    if msg is None:
        return
    how = (f"with dark {_describe_dark(dark)}" if dark is not None else
           "read with no dark level (negative in the file)")
    warn_input(f"{what} file {p} {how}: {msg}", MeasurementWarning if is_meas else PsfWarning,
               stacklevel=stacklevel)


def load_psf(
    path: PathLike,
    *,
    dark: DarkSpec = None,
    downsample: int = 1,
    channels: Channels = "gray",
    normalise: NormMode | None = "sum",
    key: str | None = None,
    channel_order: ChannelOrder = "rgb",
    shared_gray: bool = False,
) -> F32:
    """Load a PSF as float32 ``(C, H, W)``: dark -> downsample -> clip at 0 -> normalise.

    Args:
        path: image file (see :func:`load_image`).
        dark: ``None``, a level, a dark frame (array or file) or ``'auto'`` (the camera's
            black level a saved frame records, :func:`recorded_black_level`, else the corner
            patch ``[5:15, 5:15]`` as in the DiffuserCam tutorial); subtracted at full
            resolution.
        downsample: box-filter factor over rows and columns.
        channels: ``'gray'`` (luma, ``C = 1``) or ``'rgb'`` (``C = 3``).
        normalise: ``'sum'`` (unit total, default), ``'max'``, ``'l2'`` or ``None``; one
            factor for all channels, so the colour balance is kept.
        key: variable name in an ``.npz``/``.mat`` file.
        channel_order: ``'bgr'`` for files that store colour as B, G, R (the DiffuserCam
            Lensless MirFlickr dataset); the result is always R, G, B.
        shared_gray: with ``channels='rgb'``, a grayscale file gives its one plane
            (``C = 1``, a PSF the colour channels share) instead of an error.

    Warns (:class:`recon.psfcheck.PsfWarning`): a constant or clipped PSF; a raw (integer)
    PSF read with no dark level whose floor holds much of its light (a black level:
    :data:`recon.psfcheck.FLOOR_WARN_SHARE`); a PSF mostly below 0 after its dark level,
    before the clip (:func:`recon.checks.negative_after_dark`).

    Raises:
        FileNotFoundError, ValueError: missing file, unreadable file, NaN/inf values, values
            all subnormal, bad dtype or shape, a dark level beyond the data's float range;
            :class:`EmptyPsfError` for an all-zero PSF.

    """
    arr, p = _prepare(
        path,
        what="PSF",
        dark=dark,
        downsample=downsample,
        channels=channels,
        key=key,
        prefer=_PSF_KEYS,
        order=channel_order,
        shared_gray=shared_gray,
    )
    if not np.any(arr > 0):
        extra = f" after dark subtraction (dark={_describe_dark(dark)})" if dark is not None else ""
        raise EmptyPsfError(f"PSF file {p} is all zero or negative{extra}")
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
    channel_order: ChannelOrder = "rgb",
    unmasked: bool = False,
    measured: Array | None = None,
) -> F32:
    """Load a measurement as float32 ``(C, H, W)``: dark -> downsample -> clip -> normalise.

    Same arguments as :func:`load_psf`, but ``dark='auto'`` is the recorded black level, else
    :func:`recon.preprocess.measurement_dark_level` (the 1st percentile of the measured pixels,
    not a PSF's corner patch); by default the result is scaled to maximum 1
    (``normalise=None`` keeps the counts). ``unmasked``: it is read without an erasure mask
    (a file that is 0 on many pixels is warned about). ``measured``: its erasure mask (H, W)
    in the file's layout (nonzero = measured), for the automatic dark level and the check of
    negative pixels. A measurement
    negative in many measured pixels after its dark level is warned about
    (:func:`recon.checks.negative_measurement`: a dark level above the black level) before they
    are clipped to 0. Raises for NaN/inf values, a bad dtype or shape, and an all-zero
    measurement when it is to be normalised.
    """
    arr, p = _prepare(
        path,
        what="measurement",
        dark=dark,
        downsample=downsample,
        channels=channels,
        key=key,
        prefer=_MEAS_KEYS,
        order=channel_order,
        unmasked=unmasked,
        measured=measured,
    )
    if normalise is not None:
        if not np.any(arr > 0):
            raise ValueError(f"measurement file {p} is all zero; cannot normalise it")
        arr = _normalise_fn(arr, normalise)
    return np.ascontiguousarray(arr, dtype=np.float32)


def _refuse_a_stack(p: Path) -> None:
    """A PSF stack of ours (``calibrate depth``) given as one PSF is refused, naming --psf-stack.

    Its planes were read as colour channels and mixed into one PSF, with a warning whose advice
    ("give one file per frame") did not fit.
    """
    from recon.calibfile import PSF_STACK_FORMAT

    meta = _our_metadata(p)
    if meta is not None and meta.get("format") == PSF_STACK_FORMAT:
        raise ValueError(f"PSF file {p} is a stack of PSFs (a depth calibration): give it as "
                         "--psf-stack (the depth model), or one of its planes as --psf")


def _natural_key(path: Path) -> tuple[Any, ...]:
    """Sort key of a file name with its numbers by value (``psf2`` before ``psf10``)."""
    import re

    return tuple(int(part) if part.isdigit() else part.lower()
                 for part in re.split(r"(\d+)", path.name))


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
    image files in natural name order, numbers by value: ``psf2`` before ``psf10``; plain
    sorting put 10 after 1 and silently swapped planes), or one file holding the whole stack
    (multi-page TIFF, or a 3-axis ``.npy``/``.npz``/``.mat`` array ``(K, H, W)``). Each
    plane: dark -> downsample -> clip at 0; then one normalisation for the whole stack
    (default ``'max'``, the convention of the DiffuserCam 3D data), which keeps the planes'
    relative energies.
    """
    planes: list[Array] = []
    names: list[Path] = []
    if isinstance(paths, str | os.PathLike):
        p = Path(paths)
        if p.is_dir():
            exts = (*_TIFF_EXT, *_CV_EXT, ".npy")
            files = sorted(
                (f for f in p.iterdir()
                 if f.suffix.lower() in exts and not f.name.startswith(".")),
                key=_natural_key)
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
    # the stack's checks name its file, or its first and last plane files
    label = names[0] if len(set(names)) == 1 else Path(f"{names[0]} ... {names[-1]}")
    if dark is None and all(pl.dtype.kind in "ui" for pl in planes):
        _check_psf_black_level(np.stack(planes), label, "PSF stack", stacklevel=3)
    d = _dark_for(dark, key, stack, None, "PSF stack", names[0])
    if d is not None:
        stack = _subtract_dark(stack, d, label, "PSF stack")
    _check_negative(stack, label, dark, None, "PSF stack", stacklevel=3)
    stack = clip_nonneg(box_downsample(stack, downsample))
    for k in range(stack.shape[0]):
        if not np.any(stack[k] > 0):
            extra = (f" after dark subtraction (dark={_describe_dark(dark)})" if dark is not None
                     else "")
            raise EmptyPsfError(
                f"PSF stack plane {k} ({names[k]}) is all zero or negative{extra}")
    if normalise is not None:
        stack = _normalise_fn(stack, normalise)
    return np.ascontiguousarray(stack, dtype=np.float32)


def _describe_dark(dark: DarkSpec) -> str:
    if isinstance(dark, np.ndarray):
        return f"frame of shape {dark.shape}"
    return str(dark)


def load_psf_any(path: PathLike) -> F32:
    """A 2D PSF ``(H, W)``, summing to 1, as the app loads one.

    A PSF calibration file (:mod:`recon.calibfile`), else any image file through
    :func:`load_psf`.
    """
    from recon.formats import NotOurFile

    p = Path(path)
    try:
        from recon.calibfile import load_psf_calibration

        psf, _meta = load_psf_calibration(p)
        return np.asarray(psf, dtype=np.float32)
    except NotOurFile:  # not a calibration file: read it as an image (one of ours is checked)
        pass
    out: F32 = np.asarray(load_psf(p, normalise="sum"), dtype=np.float32)[0]
    return out
