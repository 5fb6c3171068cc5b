"""``lenslesscam devices`` and ``lenslesscam snap``: list the bench hardware, save one frame.

::

    lenslesscam devices [--json] [--producer CTI ...]
    lenslesscam snap --camera sim|genicam[:N]|v4l2[:N|:PATH] [--exposure 10ms] [--gain G]
                     [--timeout 5] [--light-state PATH] [--producer CTI ...] --out F.tif

``snap`` writes a TIFF (atomically) whose ImageDescription is the frame's metadata as JSON
(``Frame.metadata()`` plus provenance), so the frame can be interpreted later (exposure,
ROI, sensor timing for the shutter function), and prints which camera the spec opened (its
description: ``genicam:N`` is a position in a list). A file camera's video or sequence frames
are inputs of the command: ``--out`` may not be one of them, even with ``--overwrite``.
Durations take a unit: ``10ms``, ``500us``, ``0.01s`` (a bare number is microseconds).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any

from app.commands._options import (
    FINITE,
    POSITIVE,
    add_overwrite_option,
    check_command_outputs,
)

__all__ = ["check_camera_command_outputs", "parse_duration_us", "register"]

_UNITS_US = {"us": 1.0, "µs": 1.0, "ms": 1000.0, "s": 1_000_000.0}


def parse_duration_us(text: str) -> float:
    """``10ms`` -> 10000.0 (microseconds); units us, µs, ms, s; a bare number is us."""
    # a sign read, so that -1ms is "must be > 0"
    m = re.fullmatch(r"\s*(-?[0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*(us|µs|ms|s)?\s*", text)
    if not m:
        raise argparse.ArgumentTypeError(f"not a duration: {text!r} (e.g. 10ms, 500us, 0.5s; "
                                         "a bare number is microseconds)")
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
    add_producer_argument(p)
    p.set_defaults(func=_devices)

    s = subparsers.add_parser(
        "snap",
        help="acquire one frame and save it with its metadata",
        description="Acquire one frame and save it as TIFF with its metadata (JSON).",
    )
    s.add_argument(
        "--camera", default="sim", help="sim | genicam[:N] | v4l2[:N|:PATH] (default sim)"
    )
    s.add_argument("--exposure", type=parse_duration_us,
                   help="exposure, e.g. 10ms (units us, ms, s; a bare number is us)")
    s.add_argument("--gain", type=FINITE, help="gain (device units)")
    s.add_argument("--timeout", type=POSITIVE, default=5.0, help="seconds to wait for the frame")
    s.add_argument("--light-state", help="sim only: state file of a simulated point source")
    from app.commands.calibrate import add_sim_camera_arguments

    add_sim_camera_arguments(s)  # the very camera calibrate --camera sim opens
    add_producer_argument(s)
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


def add_producer_argument(p: Any) -> None:
    """``--producer CTI`` (repeatable): the same option, and numbering, in every camera command."""
    p.add_argument("--producer", action="append", default=[], metavar="CTI",
                   help="extra GenTL producer (genicam:N counts its cameras as `devices "
                        "--producer CTI` lists them)")


def producer_kwargs(producers: list[str], camera: str) -> dict[str, Any]:
    """The camera constructor's ``producers`` for ``--producer`` (empty: the default search).

    ``genicam:N`` counts the devices of every producer found, so the same ``--producer``
    options must be given to ``devices``, ``snap`` and ``calibrate`` for N to name the same
    camera. ``--producer`` with another backend is refused: it would be ignored.
    """
    from drivers.registry import parse_camera_spec

    if not producers:
        return {}
    if parse_camera_spec(camera).name != "genicam":
        raise ValueError(f"--producer applies to --camera genicam[:N], not {camera}")
    from drivers.genicam import find_producers

    return {"producers": find_producers(producers)}


def check_camera_command_outputs(args: argparse.Namespace, outputs: list[str]) -> None:
    """:func:`check_command_outputs`, with the files ``--camera`` reads as inputs too.

    A file camera (``v4l2:VIDEO``, ``v4l2:DIR/%04d.tif``) reads its video or every frame of its
    sequence: an output that is one of them is refused as any input is ("it is the input
    --camera ... of this command"), whatever ``--overwrite`` says. Before this ``snap --camera
    v4l2:vid.mkv --out vid.mkv --overwrite`` replaced the recording with one TIFF frame.
    """
    from drivers.registry import camera_source_match, parse_camera_spec
    from recon.atomic import check_outputs

    spec = parse_camera_spec(args.camera)
    for out in outputs:
        source = camera_source_match(spec, out)
        if source is not None:  # the same output check (and message) as for every input
            check_outputs([out], {f"--camera {spec}": source}, overwrite=True)
    check_command_outputs(args, outputs)


def _snap(args: argparse.Namespace) -> int:
    from app.cli import CliError
    from drivers.camera import CameraError
    from drivers.registry import open_camera, parse_camera_spec

    try:  # read once: "sim " is the simulated camera here as in open_camera
        spec = parse_camera_spec(args.camera)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    args.camera = str(spec)
    if Path(args.out).suffix.lower() not in (".tif", ".tiff"):
        raise CliError(f"--out {args.out}: a frame is saved as TIFF with its metadata; name "
                       "it .tif")
    light_gone = False
    if args.light_state:
        from drivers.lightstate import check_light_state_file

        if not Path(args.light_state).exists():
            raise CliError(f"--light-state {args.light_state}: no such file (the simulated "
                           "source's state file)")
        try:  # a light-state file as the simulated firmware writes it, not any file
            light_gone = not check_light_state_file(args.light_state).available
        except ValueError as exc:
            raise CliError(f"--light-state {exc}") from None
    check_camera_command_outputs(args, [args.out])  # before the camera is opened
    kwargs: dict[str, Any] = {}
    if spec.name == "sim":
        # calibrate's simulated camera (same PSF, size and seed: a PSF calibrated on it fits
        # this frame), looking at the demo scene: a lensless frame through its PSF
        from app.commands.calibrate import sim_camera_kwargs
        from drivers.simcam import StillScene, demo_pattern

        kwargs = sim_camera_kwargs(args, None)
        kwargs.update(scene=StillScene(demo_pattern(kwargs["height"], kwargs["width"])),
                      exposure_us=10_000.0)
        if args.light_state:
            kwargs["light_state"] = args.light_state
            if light_gone:
                print(f"lenslesscam: warning: --light-state {args.light_state}: the simulated "
                      "source that wrote it is no longer running; its light reads as off",
                      file=sys.stderr)
    elif args.light_state:
        raise CliError("--light-state applies to the simulated camera only")
    kwargs.update(producer_kwargs(args.producer, args.camera))
    try:
        with open_camera(args.camera, **kwargs) as cam:
            if args.exposure is not None:
                cam.exposure_us = args.exposure
            if args.gain is not None:
                cam.gain = args.gain
            frame = cam.snap(timeout_s=args.timeout)
            described = _describe_camera(cam)
    except CameraError as exc:
        raise CliError(str(exc)) from exc
    path = _save_frame(args.out, frame)
    exposure = "?" if frame.exposure_us is None else f"{frame.exposure_us:g} us"
    print(
        f"saved {path}: {frame.shape[0]}x{frame.shape[1]} (HxW) {frame.pixels.dtype} "
        f"{frame.pixel_format}, exposure {exposure}, frame {frame.frame_id} ({frame.backend})"
    )
    print(f"camera: {described}")  # which device genicam:N or v4l2:N turned out to be
    return 0


def _describe_camera(cam: Any) -> str:
    """The open camera's description line, with its model when the description lacks it."""
    from drivers.camera import CameraError

    text = str(cam.describe())
    try:
        model = str(cam.capabilities().model)
    except CameraError:
        return text
    return text if not model or model in text else f"{text}, model {model}"


def _save_frame(out: str, frame: Any) -> str:
    """The frame as the app saves a snapshot (one writer), without the JSON beside it."""
    from app.gui.snapshots import save_frame

    return str(save_frame(frame, out, sidecar=False)[0])  # a .tif name: checked up front
