"""Bench hardware behind interfaces: cameras, light sources, and their simulators.

Public names are imported lazily (``import drivers`` stays cheap: the simulated firmware
process and the CLI's ``--help`` do not pay for numpy or the backends' libraries).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from drivers.camera import (
        AcquisitionFinished,
        AcquisitionOverflow,
        Camera,
        CameraBase,
        CameraError,
        CameraTimeout,
        Capabilities,
        Feature,
        FeatureNotAvailable,
        Frame,
        FrameError,
        FrameStreamer,
        Roi,
        StreamMode,
        StreamStats,
        TriggerMode,
    )
    from drivers.genicam import GenICamCamera, find_producers, list_genicam_devices
    from drivers.lightsource import (
        DeviceError,
        LightSource,
        LightSourceDisconnected,
        LightSourceError,
        LightSourceProtocolError,
        LightSourceStatus,
        LightSourceTimeout,
        SerialPointSource,
    )
    from drivers.lightstate import LightMode, LightState, LightStateFile
    from drivers.pointsource_sim import SimulatedSource, spawn_simulated_source
    from drivers.registry import (
        CameraInfo,
        SerialPortInfo,
        list_cameras,
        list_serial_ports,
        open_camera,
    )
    from drivers.simcam import (
        CropRenderer,
        MovingScene,
        SimulatedCamera,
        SpectralScene,
        StillScene,
    )
    from drivers.timing import ReadoutPattern, SensorTiming, ShutterMode
    from drivers.v4l2 import V4L2Camera

_EXPORTS: dict[str, str] = {
    **dict.fromkeys(
        (
            "AcquisitionFinished",
            "AcquisitionOverflow",
            "Camera",
            "CameraBase",
            "CameraError",
            "CameraTimeout",
            "Capabilities",
            "Feature",
            "FeatureNotAvailable",
            "Frame",
            "FrameError",
            "FrameStreamer",
            "Roi",
            "StreamMode",
            "StreamStats",
            "TriggerMode",
        ),
        "drivers.camera",
    ),
    **dict.fromkeys(("GenICamCamera", "find_producers", "list_genicam_devices"), "drivers.genicam"),
    **dict.fromkeys(
        (
            "DeviceError",
            "LightSource",
            "LightSourceDisconnected",
            "LightSourceError",
            "LightSourceProtocolError",
            "LightSourceStatus",
            "LightSourceTimeout",
            "SerialPointSource",
        ),
        "drivers.lightsource",
    ),
    **dict.fromkeys(("LightMode", "LightState", "LightStateFile"), "drivers.lightstate"),
    **dict.fromkeys(("SimulatedSource", "spawn_simulated_source"), "drivers.pointsource_sim"),
    **dict.fromkeys(
        ("CameraInfo", "SerialPortInfo", "list_cameras", "list_serial_ports", "open_camera"),
        "drivers.registry",
    ),
    **dict.fromkeys(
        ("CropRenderer", "MovingScene", "SimulatedCamera", "SpectralScene", "StillScene"),
        "drivers.simcam",
    ),
    **dict.fromkeys(("ReadoutPattern", "SensorTiming", "ShutterMode"), "drivers.timing"),
    "V4L2Camera": "drivers.v4l2",
}

__all__ = [
    "AcquisitionFinished",
    "AcquisitionOverflow",
    "Camera",
    "CameraBase",
    "CameraError",
    "CameraInfo",
    "CameraTimeout",
    "Capabilities",
    "CropRenderer",
    "DeviceError",
    "Feature",
    "FeatureNotAvailable",
    "Frame",
    "FrameError",
    "FrameStreamer",
    "GenICamCamera",
    "LightMode",
    "LightSource",
    "LightSourceDisconnected",
    "LightSourceError",
    "LightSourceProtocolError",
    "LightSourceStatus",
    "LightSourceTimeout",
    "LightState",
    "LightStateFile",
    "MovingScene",
    "ReadoutPattern",
    "Roi",
    "SensorTiming",
    "SerialPointSource",
    "SerialPortInfo",
    "ShutterMode",
    "SimulatedCamera",
    "SimulatedSource",
    "SpectralScene",
    "StillScene",
    "StreamMode",
    "StreamStats",
    "TriggerMode",
    "V4L2Camera",
    "find_producers",
    "list_cameras",
    "list_genicam_devices",
    "list_serial_ports",
    "open_camera",
    "spawn_simulated_source",
]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'drivers' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
