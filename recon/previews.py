"""8-bit previews of arrays: contrast stretch, frame montage, PNG and GIF writers.

The one preview writer: :func:`preview_image` turns a scene (C, K, H, W) into the image shown
(gray or RGB, else the channel mean; one pair of levels for all frames; K frames tiled), and
:func:`write_png` / :func:`write_gif` write it atomically. Used by
:func:`recon.reconfile.save_reconstruction` and by the UDN jobs' previews.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from recon.atomic import atomic_write

__all__ = ["contrast_stretch", "preview_frames", "preview_image", "write_gif", "write_png"]

Array = npt.NDArray[Any]
PathLike = str | os.PathLike[str]


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


#: ``format`` of the text metadata every PNG written here carries
PREVIEW_FORMAT = "lenslesscam.preview"


def write_png(path: PathLike, chw8: npt.NDArray[np.uint8]) -> Path:
    """Write a uint8 (1|3, H, W) image as PNG, atomically, with text metadata.

    The PNG's text chunk ``lenslesscam`` holds JSON: ``format`` (:data:`PREVIEW_FORMAT`),
    ``format_version`` and ``provenance`` (versions, host, time), so a preview found alone
    says what made it (a display image: contrast-stretched 8 bits, never data to reuse).
    """
    import json

    from PIL.PngImagePlugin import PngInfo

    from recon.formats import FORMAT_VERSION, provenance

    img = _pil_image(chw8)
    info = PngInfo()
    info.add_text("lenslesscam", json.dumps(
        {"format": PREVIEW_FORMAT, "format_version": FORMAT_VERSION,
         "note": "display image: contrast-stretched 8 bits, not data",
         "provenance": provenance()}, default=str))
    return atomic_write(path, lambda tmp: img.save(tmp, format="PNG", pnginfo=info))


def _preview_channels(x: Array) -> Array:
    """(C, K, H, W) -> (C', K, H, W) with C' in (1, 3): gray stays, RGB stays, else mean."""
    if x.shape[0] in (1, 3):
        return x
    return np.asarray(x.mean(axis=0, keepdims=True))


def write_gif(path: PathLike, frames: npt.NDArray[np.uint8], duration_ms: int = 100) -> Path:
    """Write uint8 frames (K, 1|3, H, W) as an animated GIF, atomically."""
    images = [_pil_image(f) for f in frames]

    def _save(tmp: Path) -> None:
        images[0].save(
            tmp, format="GIF", save_all=True, append_images=images[1:], duration=duration_ms, loop=0
        )

    return atomic_write(path, _save)


def preview_frames(x: Array) -> npt.NDArray[np.uint8]:
    """A scene (C, K, H, W) as uint8 frames (K, C', H, W), C' in (1, 3), one pair of levels."""
    arr = np.asarray(x, dtype=np.float32)
    if arr.ndim != 4:
        raise ValueError(f"a preview needs (C, K, H, W), got shape {arr.shape}")
    return np.moveaxis(contrast_stretch(_preview_channels(arr)), 1, 0)


def preview_image(x: Array) -> npt.NDArray[np.uint8]:
    """THE preview of a scene (C, K, H, W): uint8 (C', H', W'), the K frames tiled."""
    frames = preview_frames(x)
    return frames[0] if frames.shape[0] == 1 else _montage(frames)
