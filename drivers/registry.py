"""Opening cameras by spec string, and listing what is attached.

Specs: ``sim``; ``genicam`` or ``genicam:N`` (N counts the devices of all discovered GenTL
producers, see :func:`drivers.genicam.find_producers`); ``v4l2``, ``v4l2:N``,
``v4l2:/dev/videoN`` or ``v4l2:PATH`` (an image sequence pattern or a video file).
:func:`parse_camera_spec` is the one reading of a spec (surrounding spaces stripped, the name
case-folded): every command and :func:`open_camera` go through it, so ``"sim "`` is the
simulated camera everywhere. :func:`camera_source_match` tells whether a path is a file a
file camera reads (its video, or a frame of its image sequence), so that no command writes
its output over its own input.
"""

from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

from drivers.camera import CameraBase

__all__ = [
    "CameraInfo",
    "CameraSpec",
    "SerialPortInfo",
    "camera_source_match",
    "list_cameras",
    "list_serial_ports",
    "open_camera",
    "parse_camera_spec",
]

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CameraInfo:
    """A camera that :func:`open_camera` can open with ``spec``."""

    spec: str
    backend: str
    description: str
    demo: bool = False  # a demo producer's or simulated camera, not hardware


@dataclass(frozen=True)
class SerialPortInfo:
    """A serial port as pyserial lists it."""

    device: str
    description: str
    hwid: str


class CameraSpec(NamedTuple):
    """A camera spec as read: ``name`` (``sim``, ``genicam``, ``v4l2``) and its argument."""

    name: str
    arg: str

    def __str__(self) -> str:
        return f"{self.name}:{self.arg}" if self.arg else self.name

    @property
    def source_file(self) -> str | None:
        """The file (or printf-style sequence pattern) a ``v4l2:PATH`` camera reads, else None."""
        if self.name != "v4l2" or not self.arg:
            return None
        if self.arg.isdigit() or re.fullmatch(r"/dev/video\d+", self.arg):
            return None
        return self.arg


def parse_camera_spec(spec: str) -> CameraSpec:
    """Read a camera spec: surrounding spaces stripped, the name case-folded, checked.

    Raises :class:`ValueError` with one line for an unknown name or a bad argument.
    """
    name, _, arg = str(spec).strip().partition(":")
    name = name.strip().lower()
    if name == "sim":
        if arg:
            raise ValueError(f"camera spec 'sim' takes no argument, got {spec!r}")
    elif name == "genicam":
        if arg and not arg.isdigit():
            raise ValueError(f"genicam spec must be 'genicam' or 'genicam:N', got {spec!r}")
    elif name != "v4l2":
        raise ValueError(f"unknown camera spec {spec!r}: use 'sim', 'genicam[:N]' or "
                         "'v4l2[:N|:/dev/videoN|:PATH]'")
    return CameraSpec(name, arg)


def camera_source_match(spec: str | CameraSpec, path: str | os.PathLike[str]) -> Path | None:
    """The file camera ``spec`` reads that an output ``path`` must not be, or None.

    A ``v4l2:VIDEO`` camera reads that one file (returned: the output check compares it with
    ``path``, links included); a ``v4l2:DIR/%04d.png`` camera reads every file of its sequence:
    the frame ``path`` is (or links to), or ``path`` itself when it would be one (a name of the
    sequence in its folder), else None. Devices and the simulated camera read no file (None).
    """
    cs = spec if isinstance(spec, CameraSpec) else parse_camera_spec(spec)
    source = cs.source_file
    if source is None:
        return None
    out = Path(path)
    # a file that exists is a video even with a % in its name (as drivers.v4l2 reads it)
    if "%" not in source or os.path.isfile(source):
        return Path(source)  # the one file: the output check compares the paths
    from drivers.v4l2 import sequence_name_of  # the camera's own rule of a sequence's names

    pattern = Path(source).name
    folder = Path(source).parent
    try:
        if out.resolve().parent == folder.resolve() and sequence_name_of(pattern,
                                                                          out.resolve().name):
            return out
        if not out.exists():
            return None
        same = os.stat(out)
        with os.scandir(folder) as entries:
            for entry in entries:
                if sequence_name_of(pattern, entry.name):
                    st = entry.stat()
                    if (st.st_dev, st.st_ino) == (same.st_dev, same.st_ino):
                        return Path(entry.path)
    except OSError:  # an unreadable folder: the camera cannot read it either
        return None
    return None


def _make_camera(spec: str, **kwargs: Any) -> CameraBase:
    name, arg = parse_camera_spec(spec)
    if name == "sim":
        from drivers.simcam import SimulatedCamera

        return SimulatedCamera(**kwargs)
    if name == "genicam":
        from drivers.genicam import GenICamCamera

        return GenICamCamera(int(arg or 0), **kwargs)
    from drivers.v4l2 import V4L2Camera

    source: int | str = int(arg) if arg.isdigit() else (arg or 0)
    return V4L2Camera(source, **kwargs)


def open_camera(spec: str, **kwargs: Any) -> CameraBase:
    """Create the camera ``spec`` names (keyword arguments go to its constructor) and open it.

    Use it as a context manager, or call ``close()``.
    """
    cam = _make_camera(spec, **kwargs)
    cam.open()
    return cam


def list_cameras(*, genicam_producers: list[str] | None = None) -> list[CameraInfo]:
    """The simulated camera, every GenTL device, every V4L2 node.

    A backend whose discovery fails is logged and skipped.
    """
    out = [CameraInfo("sim", "sim", "Simulated camera (renders a scene; no hardware)",
                      demo=True)]
    try:
        from drivers.genicam import is_demo_producer, list_genicam_devices

        for d in list_genicam_devices(genicam_producers):
            out.append(CameraInfo(d.spec, "genicam", f"{d.display_name or d.model} [{d.producer}]",
                                  demo=is_demo_producer(d.producer)))
    except Exception as exc:  # a broken producer must not hide the other cameras
        _log.warning("GenICam discovery failed: %s", exc)
    try:
        from drivers.v4l2 import list_v4l2_devices

        for v in list_v4l2_devices():
            out.append(CameraInfo(v.spec, "v4l2", f"{v.path} {v.name}".strip()))
    except Exception as exc:
        _log.warning("V4L2 discovery failed: %s", exc)
    return out


def list_serial_ports() -> list[SerialPortInfo]:
    """Serial ports pyserial finds (``serial.tools.list_ports``); PTYs are not listed."""
    from serial.tools import list_ports

    return [
        SerialPortInfo(p.device, p.description or "", p.hwid or "")
        for p in sorted(list_ports.comports(), key=lambda p: p.device)
    ]
