"""``lenslesscam devices`` and ``lenslesscam snap``: list the bench hardware, save one frame.

::

    lenslesscam devices [--json] [--producer CTI ...]
    lenslesscam snap --camera sim|genicam[:N]|v4l2[:N|:PATH] [--exposure 10ms] [--gain G]
                     [--timeout 5] [--light-state PATH] [--producer CTI ...] --out F.tif

``snap`` writes a TIFF (atomically) whose ImageDescription is the frame's metadata as JSON
(``Frame.metadata()`` plus provenance), so the frame can be interpreted later (exposure,
ROI, sensor timing for the shutter function). Durations take a unit: ``10ms``, ``500us``,
``0.01s`` (a bare number is microseconds).
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path
from typing import Any

from app.commands._options import (
    FINITE,
    POSITIVE,
    add_overwrite_option,
    check_command_outputs,
)

__all__ = ["parse_duration_us", "register"]

_UNITS_US = {"us": 1.0, "µs": 1.0, "ms": 1000.0, "s": 1_000_000.0}


def parse_duration_us(text: str) -> float:
    """``10ms`` -> 10000.0 (microseconds); units us, µs, ms, s; a bare number is us."""
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*(us|µs|ms|s)?\s*", text)
    if not m:
        raise argparse.ArgumentTypeError(f"not a duration: {text!r} (e.g. 10ms, 500us, 0.5s)")
    value = float(m.group(1)) * _UNITS_US[m.group(2) or "us"]
    if value <= 0:
        raise argparse.ArgumentTypeError(f"duration must be > 0: {text!r}")
    return value


def register(subparsers: Any) -> None:
    """Add the ``devices`` and ``snap`` subcommands."""
    p = subparsers.add_parser(
        "devices",
        help="list cameras (simulated, GenICam, V4L2) and serial ports",
        description="List cameras (simulated, every GenTL producer's devices, V4L2 nodes) "
        "and serial ports.",
    )
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument(
        "--producer", action="append", default=[], metavar="CTI", help="extra GenTL producer"
    )
    p.set_defaults(func=_devices)

    s = subparsers.add_parser(
        "snap",
        help="acquire one frame and save it with its metadata",
        description="Acquire one frame and save it as TIFF with its metadata (JSON).",
    )
    s.add_argument(
        "--camera", default="sim", help="sim | genicam[:N] | v4l2[:N|:PATH] (default sim)"
    )
    s.add_argument("--exposure", type=parse_duration_us, help="exposure, e.g. 10ms")
    s.add_argument("--gain", type=FINITE, help="gain (device units)")
    s.add_argument("--timeout", type=POSITIVE, default=5.0, help="seconds to wait for the frame")
    s.add_argument("--light-state", help="sim only: state file of a simulated point source")
    from app.commands.calibrate import add_sim_camera_arguments

    add_sim_camera_arguments(s)  # the very camera calibrate --camera sim opens
    s.add_argument(
        "--producer", action="append", default=[], metavar="CTI", help="extra GenTL producer"
    )
    s.add_argument("--out", required=True, help="output TIFF file")
    add_overwrite_option(s)
    s.set_defaults(func=_snap)


def _devices(args: argparse.Namespace) -> int:
    from drivers.genicam import find_producers
    from drivers.registry import list_cameras, list_serial_ports

    skipped: list[str] = []
    producers = find_producers(args.producer, skipped=skipped)
    cameras = list_cameras(genicam_producers=[str(p) for p in producers])
    ports = list_serial_ports()
    if args.json:
        print(
            json.dumps(
                {
                    "cameras": [vars(c) for c in cameras],
                    "gentl_producers": [str(p) for p in producers],
                    "gentl_skipped": skipped,
                    "serial_ports": [vars(p) for p in ports],
                },
                indent=2,
            )
        )
        return 0
    print("Cameras:")
    width = max(len(c.spec) for c in cameras)
    for c in cameras:
        print(f"  {c.spec:<{width}}  {c.description}")
    print("GenTL producers:")
    for prod in producers or []:
        print(f"  {prod}")
    if not producers:
        print("  (none; set GENICAM_GENTL64_PATH)")
    for line in skipped:
        print(f"  ({line})")
    print("Serial ports:")
    for sp in ports:
        print(f"  {sp.device}  {sp.description}")
    if not ports:
        print("  (none; simulated source: python -m drivers.pointsource_sim --pty)")
    return 0


def _snap(args: argparse.Namespace) -> int:
    from app.cli import CliError
    from drivers.camera import CameraError
    from drivers.registry import open_camera

    if Path(args.out).suffix.lower() not in (".tif", ".tiff"):
        raise CliError(f"--out {args.out}: a frame is saved as TIFF with its metadata; name "
                       "it .tif")
    if args.light_state:
        from drivers.lightstate import check_light_state_file

        if not Path(args.light_state).exists():
            raise CliError(f"--light-state {args.light_state}: no such file (the simulated "
                           "source's state file)")
        try:  # a light-state file as the simulated firmware writes it, not any file
            check_light_state_file(args.light_state)
        except ValueError as exc:
            raise CliError(f"--light-state {exc}") from None
    check_command_outputs(args, [args.out])  # before the camera is opened
    kwargs: dict[str, Any] = {}
    name = args.camera.partition(":")[0].lower()
    if name == "sim":
        # calibrate's simulated camera (same PSF, size and seed: a PSF calibrated on it fits
        # this frame), looking at the demo scene: a lensless frame through its PSF
        from app.commands.calibrate import sim_camera_kwargs
        from drivers.simcam import StillScene, demo_pattern

        kwargs = sim_camera_kwargs(args, None)
        kwargs.update(scene=StillScene(demo_pattern(kwargs["height"], kwargs["width"])),
                      exposure_us=10_000.0)
        if args.light_state:
            kwargs["light_state"] = args.light_state
    elif args.light_state:
        raise CliError("--light-state applies to the simulated camera only")
    if name == "genicam" and args.producer:
        from drivers.genicam import find_producers

        kwargs["producers"] = find_producers(args.producer)
    try:
        with open_camera(args.camera, **kwargs) as cam:
            if args.exposure is not None:
                cam.exposure_us = args.exposure
            if args.gain is not None:
                cam.gain = args.gain
            frame = cam.snap(timeout_s=args.timeout)
    except CameraError as exc:
        raise CliError(str(exc)) from exc
    path = _save_frame(args.out, frame)
    exposure = "?" if frame.exposure_us is None else f"{frame.exposure_us:g} us"
    print(
        f"saved {path}: {frame.shape[0]}x{frame.shape[1]} (HxW) {frame.pixels.dtype} "
        f"{frame.pixel_format}, exposure {exposure}, frame {frame.frame_id} ({frame.backend})"
    )
    return 0


def _save_frame(out: str, frame: Any) -> str:
    import tifffile

    from recon.atomic import atomic_write
    from recon.formats import provenance

    meta = frame.metadata()
    meta["provenance"] = provenance()
    description = json.dumps(meta)

    def writer(tmp: Any) -> None:
        tifffile.imwrite(
            tmp, frame.pixels, photometric="minisblack", description=description, metadata=None
        )

    return str(atomic_write(out, writer))
