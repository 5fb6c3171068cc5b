"""Calibration files: what the bench produces and the reconstructions read.

``recon`` owns the formats (``calibration`` writes them through these functions; ``recon``
never imports ``calibration``). Five kinds, each with a ``format`` name, ``format_version``,
the date, the software version, :func:`~recon.formats.provenance` and a hash of every array
(so a corrupt file is caught when it is read):

=================  =========================================  ===============================
kind               file                                       main array
=================  =========================================  ===============================
``psf``            float32 TIFF, JSON in ImageDescription     PSF (H, W), dark subtracted
``psf-stack``      float32 multi-page TIFF, JSON description  PSF stack (K, H, W), one plane
                                                              per source position (depth)
``filter-cube``    float32 multi-page TIFF, JSON description  filter transmissions (K, H, W)
``shutter``        ``.npz``: ``shutter`` + ``metadata`` JSON  M (K, rows), with its timing
``pixel-maps``     ``.npz``: ``mask``, ``dark_mean``,          mask (H, W): 1 = good pixel,
                   ``dark_std``, ``hot``, ``dead``, metadata  0 = hot or dead (erasure mask)
=================  =========================================  ===============================

Every writer checks that the metadata it is given has the keys its kind requires (for a PSF:
camera, exposure, gain, frames averaged, dark level, timing, quality report), adds the keys
the format owns, and writes atomically (:func:`~recon.atomic.atomic_write`), so a failed
calibration never leaves a half-written file. :func:`load_calibration` reads any of them and
raises :class:`~recon.formats.FormatError` for a foreign or corrupt file.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from recon.atomic import atomic_write
from recon.formats import (
    FORMAT_VERSION,
    FormatError,
    NewerFormat,
    NotOurFile,
    array_hash,
    json_default,
    provenance,
    software_version,
    whole_version,
)

__all__ = [
    "CALIBRATION_FORMATS",
    "DARK_CORRECTED_KINDS",
    "FILTER_CUBE_FORMAT",
    "PIXEL_MAPS_FORMAT",
    "PSF_FORMAT",
    "PSF_STACK_FORMAT",
    "REQUIRED_KEYS",
    "SHUTTER_FORMAT",
    "SUFFIXES",
    "Calibration",
    "calibration_kind",
    "check_calibration_suffix",
    "load_calibration",
    "load_filter_cube_file",
    "load_pixel_mask",
    "load_psf_calibration",
    "load_psf_stack_file",
    "load_shutter",
    "save_filter_cube",
    "save_pixel_maps",
    "save_psf_calibration",
    "save_psf_stack",
    "save_shutter",
]

PathLike = str | os.PathLike[str]
F32 = npt.NDArray[np.float32]
Array = npt.NDArray[Any]

PSF_FORMAT = "lenslesscam.psf-calibration"
PSF_STACK_FORMAT = "lenslesscam.psf-stack"
FILTER_CUBE_FORMAT = "lenslesscam.filter-cube"
SHUTTER_FORMAT = "lenslesscam.shutter"
PIXEL_MAPS_FORMAT = "lenslesscam.pixel-maps"

#: kind -> format name.
CALIBRATION_FORMATS: dict[str, str] = {
    "psf": PSF_FORMAT,
    "psf-stack": PSF_STACK_FORMAT,
    "filter-cube": FILTER_CUBE_FORMAT,
    "shutter": SHUTTER_FORMAT,
    "pixel-maps": PIXEL_MAPS_FORMAT,
}
_KIND_OF_FORMAT = {v: k for k, v in CALIBRATION_FORMATS.items()}

#: Metadata keys the caller must give, per kind.
REQUIRED_KEYS: dict[str, tuple[str, ...]] = {
    "psf": (
        "camera",
        "exposure_us",
        "gain",
        "frames_averaged",
        "dark_level",
        "timing",
        "quality",
    ),
    "psf-stack": ("camera", "positions", "planes", "timing"),
    "filter-cube": ("source", "normalisation"),
    "shutter": ("timing", "bin_lines", "row_factor", "method"),
    "pixel-maps": ("camera", "exposure_us", "frames_averaged", "thresholds"),
}

#: Keys the format writes itself (a caller may not set them).
_RESERVED = frozenset(
    {
        "format",
        "format_version",
        "kind",
        "shape",
        "dtype",
        "arrays",
        "date",
        "software_version",
        "provenance",
    }
)

_TIFF_KINDS = ("psf", "psf-stack", "filter-cube")
_NPZ_KINDS = ("shutter", "pixel-maps")
_PIXEL_MAP_ARRAYS = ("mask", "dark_mean", "dark_std", "hot", "dead")


@dataclass(frozen=True)
class Calibration:
    """A calibration file as read: its kind, arrays and metadata.

    ``data`` is the main array (``psf``, the stack, the filter cube, ``shutter`` or
    ``mask``); ``arrays`` holds every array of the file by name.
    """

    kind: str
    data: Array
    metadata: dict[str, Any]
    path: Path
    arrays: dict[str, Array] = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# writing




def _finite_json(obj: Any) -> Any:
    """Replace non-finite floats by None (JSON has no NaN)."""
    if isinstance(obj, dict):
        return {k: _finite_json(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_finite_json(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _header(kind: str, metadata: Mapping[str, Any], arrays: Mapping[str, Array]) -> dict[str, Any]:
    """Validate the caller's metadata and build the full, JSON-clean metadata dict."""
    user = dict(metadata)
    clash = sorted(_RESERVED & set(user))
    if clash:
        raise ValueError(f"metadata keys {clash} are reserved for the {kind} calibration format")
    missing = [k for k in REQUIRED_KEYS[kind] if k not in user]
    if missing:
        raise ValueError(f"{kind} calibration metadata lacks {', '.join(missing)}")
    main = next(iter(arrays.values()))
    meta: dict[str, Any] = {
        "format": CALIBRATION_FORMATS[kind],
        "format_version": FORMAT_VERSION,
        "kind": kind,
        "shape": list(main.shape),
        "dtype": str(main.dtype),
        "arrays": {
            name: {"shape": list(a.shape), "dtype": str(a.dtype), "hash": array_hash(a)}
            for name, a in arrays.items()
        },
        "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "software_version": software_version(),
        "provenance": provenance(),
    }
    meta.update(user)
    try:
        text = json.dumps(meta, default=json_default, allow_nan=True)
        clean: dict[str, Any] = _finite_json(json.loads(text))
        json.dumps(clean, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{kind} calibration metadata is not JSON-serialisable: {exc}") from exc
    return clean


def _float_array(a: Any, ndim: int, what: str) -> F32:
    arr = np.asarray(a)
    if arr.dtype.kind not in "fiub":
        raise ValueError(f"{what} must be numeric, got dtype {arr.dtype}")
    if arr.ndim != ndim:
        raise ValueError(f"{what} must have {ndim} axes, got shape {arr.shape}")
    if min(arr.shape) == 0:
        raise ValueError(f"{what} must not be empty, got shape {arr.shape}")
    out = np.ascontiguousarray(arr, dtype=np.float32)
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{what} contains NaN or infinite values")
    return out


#: the file suffixes each kind is saved under (the first is the one to suggest)
SUFFIXES: dict[str, tuple[str, ...]] = {
    "psf": (".tif", ".tiff"),
    "psf-stack": (".tif", ".tiff"),
    "filter-cube": (".tif", ".tiff"),
    "shutter": (".npz",),
    "pixel-maps": (".npz",),
}


def check_calibration_suffix(path: PathLike, kind: str) -> Path:
    """Refuse a name a ``kind`` calibration is not saved under (the writers' own rule).

    Callable before any capture, so that ``calibrate darks --out darks.tif`` stops at once
    instead of after the frames. Raises :class:`ValueError` with one line; returns the path.
    """
    target = Path(path)
    suffixes = SUFFIXES[kind]
    if target.suffix.lower() not in suffixes:
        raise ValueError(f"{target}: a {kind} calibration is saved as "
                         f"{' or '.join(suffixes)}")
    return target


def _save_tiff(path: PathLike, kind: str, data: F32, metadata: Mapping[str, Any]) -> Path:
    import tifffile

    target = check_calibration_suffix(path, kind)
    meta = _header(kind, metadata, {"data": data})
    description = json.dumps(meta, ensure_ascii=True)

    def write(tmp: Path) -> None:
        tifffile.imwrite(
            tmp, data, photometric="minisblack", description=description, metadata=None
        )

    return atomic_write(target, write)


def _save_npz(
    path: PathLike, kind: str, arrays: Mapping[str, Array], metadata: Mapping[str, Any]
) -> Path:
    target = check_calibration_suffix(path, kind)
    meta = _header(kind, metadata, arrays)
    payload = {name: np.ascontiguousarray(a) for name, a in arrays.items()}
    payload["metadata"] = np.array(json.dumps(meta, ensure_ascii=True))

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **payload)  # type: ignore[arg-type]

    return atomic_write(target, write)


def save_psf_calibration(path: PathLike, psf: Any, metadata: Mapping[str, Any]) -> Path:
    """Save a PSF (H, W) as a float32 TIFF with its calibration metadata (atomically).

    ``metadata`` must hold ``camera``, ``exposure_us``, ``gain``, ``frames_averaged``,
    ``dark_level``, ``timing`` (a dict or None) and ``quality`` (the quality report); more keys
    are kept as given. Returns the path.
    """
    data = _float_array(psf, 2, "PSF")
    if np.any(data < 0):
        raise ValueError("PSF has negative values (clip it at zero before saving)")
    return _save_tiff(path, "psf", data, metadata)


def save_psf_stack(path: PathLike, stack: Any, metadata: Mapping[str, Any]) -> Path:
    """Save a PSF stack (K, H, W), one plane per position, as a multi-page float32 TIFF.

    ``metadata`` must hold ``camera``, ``positions`` (K labels), ``planes`` (K per-plane
    dicts: exposure, quality, ...) and ``timing``.
    """
    data = _float_array(stack, 3, "PSF stack")
    k = data.shape[0]
    for key in ("positions", "planes"):
        v = metadata.get(key)
        if not isinstance(v, list | tuple) or len(v) != k:
            raise ValueError(f"PSF stack metadata '{key}' must list one entry per plane ({k})")
    return _save_tiff(path, "psf-stack", data, metadata)


def save_filter_cube(path: PathLike, cube: Any, metadata: Mapping[str, Any]) -> Path:
    """Save a filter cube (K, H, W) of transmissions as a multi-page float32 TIFF.

    ``metadata`` must hold ``source`` (where it came from) and ``normalisation``.
    """
    data = _float_array(cube, 3, "filter cube")
    return _save_tiff(path, "filter-cube", data, metadata)


def save_shutter(
    path: PathLike,
    shutter: Any,
    metadata: Mapping[str, Any],
    extra_arrays: Mapping[str, Any] | None = None,
) -> Path:
    """Save a shutter function M (K, rows) as ``.npz`` with the timing it came from.

    ``metadata`` must hold ``timing`` (the sensor timing as a dict), ``bin_lines`` (time bin
    width in lines), ``row_factor`` (row downsampling) and ``method`` (``'timing'`` or
    ``'measured'``). ``extra_arrays`` (for example the measured row windows) are stored beside
    ``shutter`` under their names.
    """
    m = _float_array(shutter, 2, "shutter function")
    if np.any(m < 0):
        raise ValueError("shutter function has negative values")
    arrays: dict[str, Array] = {"shutter": m}
    for name, a in dict(extra_arrays or {}).items():
        if name in ("shutter", "metadata"):
            raise ValueError(f"extra array name {name!r} is reserved")
        arrays[str(name)] = np.ascontiguousarray(np.asarray(a))
    return _save_npz(path, "shutter", arrays, metadata)


def save_pixel_maps(
    path: PathLike,
    *,
    mask: Any,
    dark_mean: Any,
    dark_std: Any,
    hot: Any,
    dead: Any,
    metadata: Mapping[str, Any],
) -> Path:
    """Save dark statistics and hot/dead pixel maps as ``.npz``.

    ``mask`` (H, W) is 1 for a good pixel and 0 for a hot or dead one: the erasure mask of the
    2D-with-erasures model. ``metadata`` must hold ``camera``, ``exposure_us``,
    ``frames_averaged`` and ``thresholds``.
    """
    m = _float_array(mask, 2, "pixel mask")
    if not np.all((m == 0) | (m == 1)):
        raise ValueError("pixel mask must be 0 (bad) or 1 (good)")
    arrays: dict[str, Array] = {
        "mask": m,
        "dark_mean": _float_array(dark_mean, 2, "dark mean"),
        "dark_std": _float_array(dark_std, 2, "dark std"),
        "hot": np.ascontiguousarray(np.asarray(hot, dtype=bool)),
        "dead": np.ascontiguousarray(np.asarray(dead, dtype=bool)),
    }
    for name, a in arrays.items():
        if a.shape != m.shape:
            raise ValueError(f"pixel map '{name}' has shape {a.shape}, the mask {m.shape}")
    return _save_npz(path, "pixel-maps", arrays, metadata)


# --------------------------------------------------------------------------------------------
# reading


def _check_meta(p: Path, meta: Any, expect: str | None) -> tuple[str, dict[str, Any]]:
    if not isinstance(meta, dict):
        raise NotOurFile(f"{p} is not a lenslesscam calibration file (no metadata)")
    fmt = meta.get("format")
    kind = _KIND_OF_FORMAT.get(fmt) if isinstance(fmt, str) else None
    if kind is None:
        raise NotOurFile(
            f"{p} is not a lenslesscam calibration file (format {fmt!r}; expected one of "
            f"{', '.join(sorted(_KIND_OF_FORMAT))})"
        )
    if expect is not None and kind != expect:
        raise FormatError(f"{p} is a {kind} calibration, expected a {expect} calibration")
    version = whole_version(meta.get("format_version"))
    if version is None or not (1 <= version <= FORMAT_VERSION):
        raise (NewerFormat if version is not None and version > FORMAT_VERSION else FormatError)(
            f"{p}: {kind} calibration format_version {meta.get('format_version')!r} is not "
            f"supported by this release (reads 1..{FORMAT_VERSION})"
        )
    missing = [k for k in REQUIRED_KEYS[kind] if k not in meta]
    if missing:
        raise FormatError(f"{p}: {kind} calibration metadata lacks {', '.join(missing)}")
    return kind, meta


def _check_array(p: Path, meta: dict[str, Any], name: str, a: Array) -> None:
    info = meta.get("arrays", {}).get(name)
    if not isinstance(info, dict):
        raise FormatError(f"{p}: metadata does not describe array '{name}'; the file is corrupt")
    if list(a.shape) != info.get("shape") or str(a.dtype) != info.get("dtype"):
        raise FormatError(
            f"{p}: array '{name}' is {a.shape} {a.dtype}, its metadata says "
            f"{info.get('shape')} {info.get('dtype')}; the file is corrupt"
        )
    if array_hash(a) != info.get("hash"):
        raise FormatError(f"{p}: array '{name}' does not match its hash; the file is corrupt")


def _read_tiff(p: Path, expect: str | None) -> Calibration:
    import tifffile

    try:
        with tifffile.TiffFile(p) as tf:
            desc = tf.pages.first.description
            data = np.asarray(tf.asarray())
    except Exception as exc:
        raise FormatError(f"cannot read {p} as TIFF: {exc}") from exc
    try:
        meta = json.loads(desc)
    except (TypeError, ValueError):
        raise NotOurFile(
            f"{p} is not a lenslesscam calibration file (no JSON metadata in its description)"
        ) from None
    return checked_calibration_tiff(p, meta, data, expect)


def checked_calibration_tiff(p: Path, meta: Any, data: Array,
                             expect: str | None = None) -> Calibration:
    """A calibration TIFF ``p`` from its metadata and pixels, checked.

    The checks of :func:`load_calibration` (format, version, kind, shape, hash), for a caller
    that read the pixels already.
    """
    kind, meta = _check_meta(p, meta, expect)
    if kind not in _TIFF_KINDS:
        raise FormatError(f"{p}: a {kind} calibration must be an .npz file, not a TIFF")
    shape = meta.get("shape")
    want_ndim = 2 if kind == "psf" else 3
    if not isinstance(shape, list) or len(shape) != want_ndim:
        raise FormatError(f"{p}: metadata shape {shape!r} does not fit a {kind} calibration")
    if data.dtype != np.float32 or data.size != math.prod(shape):
        raise FormatError(
            f"{p}: data {data.shape} {data.dtype} does not match metadata shape {shape} "
            "float32; the file is corrupt"
        )
    arr = np.ascontiguousarray(data.reshape(shape))
    _check_array(p, meta, "data", arr)
    return Calibration(kind, arr, meta, p, {"data": arr})


def _read_npz(p: Path, expect: str | None) -> Calibration:
    try:
        with np.load(p, allow_pickle=False) as z:
            arrays = {name: np.asarray(z[name]) for name in z.files}
    except Exception as exc:
        raise FormatError(f"cannot read {p} as .npz: {exc}") from exc
    raw = arrays.pop("metadata", None)
    if raw is None or raw.ndim != 0 or raw.dtype.kind != "U":
        raise NotOurFile(f"{p} is not a lenslesscam calibration file (no metadata entry)")
    try:
        meta = json.loads(str(raw))
    except ValueError:
        raise FormatError(f"{p}: its metadata is not valid JSON; the file is corrupt") from None
    kind, meta = _check_meta(p, meta, expect)
    if kind not in _NPZ_KINDS:
        raise FormatError(f"{p}: a {kind} calibration must be a TIFF file, not .npz")
    described = set(meta.get("arrays", {}))
    if set(arrays) != described:
        raise FormatError(
            f"{p}: holds arrays {sorted(arrays)}, its metadata describes {sorted(described)}; "
            "the file is corrupt"
        )
    for name, a in arrays.items():
        _check_array(p, meta, name, a)
    main_name = "shutter" if kind == "shutter" else "mask"
    if main_name not in arrays:
        raise FormatError(f"{p}: {kind} calibration has no '{main_name}' array")
    if kind == "pixel-maps" and any(k not in arrays for k in _PIXEL_MAP_ARRAYS):
        raise FormatError(f"{p}: pixel maps need arrays {', '.join(_PIXEL_MAP_ARRAYS)}")
    return Calibration(kind, arrays[main_name], meta, p, arrays)


def load_calibration(path: PathLike, *, expect: str | None = None) -> Calibration:
    """Read any calibration file (kind from its metadata; ``expect`` demands one kind).

    Raises:
        FileNotFoundError: no such file.
        FormatError: not a lenslesscam calibration file, an unsupported version, the wrong
            kind, or corrupt content (shape, dtype or hash mismatch).

    """
    if expect is not None and expect not in CALIBRATION_FORMATS:
        raise ValueError(f"unknown calibration kind {expect!r}")
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file")
    if p.is_dir():
        raise FormatError(f"{p} is a directory, not a calibration file")
    ext = p.suffix.lower()
    if ext in (".tif", ".tiff"):
        return _read_tiff(p, expect)
    if ext == ".npz":
        return _read_npz(p, expect)
    raise NotOurFile(f"{p}: calibration files are .tif/.tiff or .npz, not {p.suffix!r}")


#: calibration kinds whose main array is already dark-subtracted (the capture took darks)
DARK_CORRECTED_KINDS = frozenset({"psf", "psf-stack"})


def calibration_kind(path: PathLike) -> str | None:
    """The kind of a calibration TIFF, read from its metadata alone; None for any other file.

    Cheap (the first page's description, not the pixels) and silent: a plain image, another
    format or an unreadable file is None; :func:`load_calibration` says what is wrong with one.
    """
    p = Path(path)
    if p.suffix.lower() not in (".tif", ".tiff") or not p.is_file():
        return None
    try:
        import tifffile

        with tifffile.TiffFile(p) as tf:
            meta = json.loads(tf.pages.first.description)
    except Exception:  # not a TIFF, no JSON description: not one of ours
        return None
    fmt = meta.get("format") if isinstance(meta, dict) else None
    return _KIND_OF_FORMAT.get(fmt) if isinstance(fmt, str) else None


def load_psf_calibration(path: PathLike) -> tuple[F32, dict[str, Any]]:
    """The PSF (H, W) float32 (dark subtracted, in ADU) and its metadata."""
    cal = load_calibration(path, expect="psf")
    return np.asarray(cal.data, dtype=np.float32), cal.metadata


def load_psf_stack_file(path: PathLike) -> tuple[F32, dict[str, Any]]:
    """The PSF stack (K, H, W) float32 and its metadata."""
    cal = load_calibration(path, expect="psf-stack")
    return np.asarray(cal.data, dtype=np.float32), cal.metadata


def load_filter_cube_file(path: PathLike) -> tuple[F32, dict[str, Any]]:
    """The filter cube (K, H, W) float32 and its metadata."""
    cal = load_calibration(path, expect="filter-cube")
    return np.asarray(cal.data, dtype=np.float32), cal.metadata


def load_shutter(path: PathLike) -> tuple[F32, dict[str, Any]]:
    """The shutter function M (K, rows) float32 and its metadata (``timing`` included)."""
    cal = load_calibration(path, expect="shutter")
    return np.asarray(cal.data, dtype=np.float32), cal.metadata


def load_pixel_mask(path: PathLike) -> F32:
    """The erasure mask (H, W) float32 of a pixel-maps file (1 = good, 0 = hot or dead)."""
    cal = load_calibration(path, expect="pixel-maps")
    return np.asarray(cal.data, dtype=np.float32)
