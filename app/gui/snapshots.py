"""Saving camera frames from the app (snap & save), without Qt.

A frame is saved as a TIFF of its raw codes (uint8/uint16, as the camera delivered them) whose
``ImageDescription`` is JSON: the frame's metadata (:meth:`drivers.camera.Frame.metadata`,
which carries its ``format`` and ``format_version``), the software provenance and whatever the
app adds (the scene of the simulated camera, a note). The same JSON is written beside it
(``<name>.json``) for tools that do not read TIFF tags. Both files are written atomically.
:func:`recon.io.load_measurement` reads the TIFF back.
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = ["frame_filename", "save_frame"]


def frame_filename(frame: Any, prefix: str = "snap") -> str:
    """``snap-YYYYmmdd-HHMMSS-f<id>.tif`` from the frame's timestamp and id."""
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(frame.timestamp))
    return f"{prefix}-{stamp}-f{frame.frame_id:06d}.tif"


def save_frame(frame: Any, path: str | Path, extra: Mapping[str, Any] | None = None,
               *, sidecar: bool = True) -> list[Path]:
    """Save ``frame`` to ``path`` (a ``.tif``; a folder gets :func:`frame_filename`).

    The one writer of frames (the app's snapshots, ``lenslesscam snap``). Returns ``[tiff,
    json]``, or ``[tiff]`` without the ``sidecar`` JSON.
    """
    import numpy as np
    import tifffile

    from recon.atomic import atomic_write, atomic_write_json
    from recon.formats import provenance

    target = Path(path)
    if target.is_dir() or target.suffix == "":
        target = target / frame_filename(frame)
    if target.suffix.lower() not in (".tif", ".tiff"):
        raise ValueError(f"{target}: frames are saved as .tif")
    meta: dict[str, Any] = dict(frame.metadata())
    meta["provenance"] = provenance()
    if extra:
        meta["app"] = dict(extra)
    description = json.dumps(meta, ensure_ascii=True, default=str)
    pixels = np.ascontiguousarray(frame.pixels)

    def _write(tmp: Path) -> None:
        tifffile.imwrite(tmp, pixels, photometric="minisblack", description=description,
                         metadata=None)

    tif = atomic_write(target, _write)
    if not sidecar:
        return [tif]
    return [tif, atomic_write_json(target.with_suffix(".json"), meta)]
