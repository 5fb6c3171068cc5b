"""The reconstruction file format: a float32 TIFF with JSON metadata, and its previews.

:func:`save_reconstruction` writes a float32 TIFF whose ``ImageDescription`` tag holds the
metadata as JSON (format, version, provenance, shape, data hash and the caller's metadata),
plus 8-bit previews beside it (:mod:`recon.previews`); :func:`read_reconstruction` reads it
back and checks it; :func:`reconstruction_paths` names the files it writes.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from recon.atomic import atomic_write
from recon.falsecolor import load_false_color_weights
from recon.formats import (
    FORMAT_VERSION,
    FormatError,
    NewerFormat,
    NotOurFile,
    array_hash,
    json_default,
    provenance,
    whole_version,
)
from recon.previews import (
    _montage,
    _preview_channels,
    contrast_stretch,
    preview_frames,
    write_gif,
    write_png,
)

__all__ = [
    "RECONSTRUCTION_FORMAT",
    "RECONSTRUCTION_KINDS",
    "Kind",
    "read_reconstruction",
    "reconstruction_paths",
    "save_reconstruction",
]

PathLike = str | os.PathLike[str]
Array = npt.NDArray[Any]
F32 = npt.NDArray[np.float32]
Kind = Literal["image", "video", "spectral", "depth"]
_TIFF_EXT = (".tif", ".tiff")


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


def data_hash(x: Any) -> str:
    """The ``data_hash`` :func:`save_reconstruction` records for the estimate ``x``."""
    return array_hash(np.ascontiguousarray(np.asarray(x), dtype=np.float32))


def reconstruction_paths(path: PathLike, kind: Kind = "image") -> list[Path]:
    """The files :func:`save_reconstruction` writes for ``path`` and ``kind``, TIFF first.

    Commands check these before computing (``recon.atomic.check_outputs``), so a preview
    cannot replace an input either (``--meas hand.png --out hand.tif``).
    """
    if str(path).strip() == "" or Path(path).name in ("", ".", ".."):
        raise ValueError(f"the output path {str(path)!r} names no file")
    target = Path(path)
    if target.is_dir():  # named here: check_outputs' example had no suffix ('adir/x')
        raise FileExistsError(f"{target} is a folder: name a .tif file (for example "
                              f"{target / 'x.tif'})")
    paths = [target, target.with_suffix(".png")]
    if kind == "video":
        paths.append(target.with_suffix(".gif"))
    elif kind == "spectral":
        paths.append(target.with_name(target.stem + "_falsecolor.png"))
    elif kind == "depth":
        paths.append(target.with_name(target.stem + "_mip.png"))
    return paths


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
        "data_hash": data_hash(arr),
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

    new_files = [p for p in reconstruction_paths(target, kind) if not p.exists()]
    try:
        return _write_all(target, _write_tiff, arr, k, kind, weights)
    except BaseException:
        # a set written in part (a full disk at the preview): the files this call created go,
        # so a rerun needs no --overwrite; files it replaced cannot come back
        for p in new_files:
            with contextlib.suppress(OSError):
                p.unlink()
        raise


def _write_all(target: Path, write_tiff: Any, arr: F32, k: int, kind: str,
               weights: Any) -> list[Path]:
    """The TIFF, then its previews (see :func:`save_reconstruction`)."""
    written = [atomic_write(target, write_tiff)]

    frames = preview_frames(arr)  # (K, C', H, W)
    still = frames[0] if k == 1 else _montage(frames)
    written.append(write_png(target.with_suffix(".png"), still))
    if kind == "video":
        written.append(write_gif(target.with_suffix(".gif"), frames))
    elif kind == "spectral" and weights is not None:
        cube = arr.mean(axis=0).astype(np.float64)  # (K, H, W)
        rgb = np.tensordot(weights, cube, axes=(1, 0))  # (3, H, W)
        written.append(
            write_png(target.with_name(target.stem + "_falsecolor.png"), contrast_stretch(rgb))
        )
    elif kind == "depth":
        mip = _preview_channels(arr).max(axis=1)  # (C', H, W)
        written.append(
            write_png(target.with_name(target.stem + "_mip.png"), contrast_stretch(mip))
        )
    return written


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
        raise NotOurFile(
            f"{p} is not a lenslesscam reconstruction (no JSON metadata in its description)"
        ) from exc
    return checked_reconstruction(p, meta, data), meta


def checked_reconstruction(p: Path, meta: Any, data: npt.NDArray[Any]) -> F32:
    """The pixels ``data`` of reconstruction TIFF ``p`` as (C, K, H, W), checked.

    The checks of :func:`read_reconstruction` against its metadata ``meta`` (format, version,
    shape, hash), for a caller that read the pixels already. Raises
    :class:`~recon.formats.NotOurFile` (not a reconstruction) or
    :class:`~recon.formats.FormatError` (newer, corrupt).
    """
    if not isinstance(meta, dict) or meta.get("format") != RECONSTRUCTION_FORMAT:
        found = meta.get("format") if isinstance(meta, dict) else None
        raise NotOurFile(
            f"{p} is not a lenslesscam reconstruction (format {found!r}, expected "
            f"{RECONSTRUCTION_FORMAT!r})"
        )
    version = whole_version(meta.get("format_version"))
    if version is None or version < 1 or version > FORMAT_VERSION:
        raise (NewerFormat if version is not None and version > FORMAT_VERSION else FormatError)(
            f"{p}: reconstruction format_version {meta.get('format_version')!r} is not "
            f"supported by this release (reads 1..{FORMAT_VERSION})"
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
    return arr
