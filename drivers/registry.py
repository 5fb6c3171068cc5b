"""Opening cameras by spec string, and listing what is attached.

Specs: ``sim``; ``genicam`` or ``genicam:N`` (N counts the devices of all discovered GenTL
producers, see :func:`drivers.genicam.find_producers`); ``v4l2``, ``v4l2:N``,
``v4l2:/dev/videoN`` or ``v4l2:PATH`` (an image sequence pattern or a video file).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

from drivers.camera import CameraBase

__all__ = ["CameraInfo", "SerialPortInfo", "list_cameras", "list_serial_ports", "open_camera"]

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


def _make_camera(spec: str, **kwargs: Any) -> CameraBase:
    name, _, arg = spec.strip().partition(":")
    name = name.lower()
    if name == "sim":
        if arg:
            raise ValueError(f"camera spec 'sim' takes no argument, got {spec!r}")
        from drivers.simcam import SimulatedCamera

        return SimulatedCamera(**kwargs)
    if name == "genicam":
        from drivers.genicam import GenICamCamera

        if arg and not arg.isdigit():
            raise ValueError(f"genicam spec must be 'genicam' or 'genicam:N', got {spec!r}")
        return GenICamCamera(int(arg or 0), **kwargs)
    if name == "v4l2":
        from drivers.v4l2 import V4L2Camera

        source: int | str = int(arg) if arg.isdigit() else (arg or 0)
        return V4L2Camera(source, **kwargs)
    raise ValueError(
        f"unknown camera spec {spec!r}: use 'sim', 'genicam[:N]' or 'v4l2[:N|:/dev/videoN|:PATH]'"
    )


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
