"""``lenslesscam calibrate``: PSF, depth stack, darks/pixel maps, shutter function, filter cube.

Each subcommand runs the same workflow the GUI wizard runs (``calibration``) and draws its
progress on stderr. A refusal (saturated PSF, no light, off-centre source, camera timeout)
is printed as one line with what to change, exit code 2, and no file is written.

``--camera sim`` is the simulated camera; with ``--source sim`` it sees the simulated point
source, whose firmware runs on a real PTY for the duration of the command.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from app.commands._common import ProgressBar, TerminateAsInterrupt, parse_duration_us
from app.commands._options import (
    FINITE,
    NONNEG,
    NONNEG_INT,
    POSITIVE,
    POSITIVE_INT,
    UNIT,
    add_overwrite_option,
    check_command_outputs,
    finite_float,
    parse_hw,
)


def _common(p: argparse.ArgumentParser, *, source: bool, source_required: bool) -> None:
    g = p.add_argument_group("devices")
    g.add_argument("--camera", default="sim", help="camera spec: sim, genicam[:N], v4l2[:N]")
    from app.commands.devices import add_producer_argument

    add_producer_argument(g)
    if source:
        g.add_argument(
            "--source",
            help="point source: 'sim' (simulated firmware on a PTY) or a serial port path"
            + (" (default: sim with the simulated camera; a real camera needs its port)"
               if source_required else ""),
        )
        p.set_defaults(source_required=source_required)
        g.add_argument(
            "--intensity", type=UNIT, default=1.0, help="source intensity 0..1 (default 1)"
        )
    g.add_argument("--exposure", help="exposure (10ms, 250us, 0.5s); default the camera's")
    g.add_argument("--gain", type=FINITE, default=None, help="camera gain (device units)")
    g.add_argument("--timeout", type=POSITIVE, default=5.0, help="seconds to wait for a frame")
    g.add_argument("--settle", type=NONNEG_INT, default=1, help="frames dropped after each change")
    add_sim_camera_arguments(p)


def add_sim_camera_arguments(p: Any) -> None:
    """The simulated camera's options: the same camera for ``calibrate`` and ``snap``."""
    s = p.add_argument_group("simulated camera (--camera sim)")
    s.add_argument("--sim-size", help="sensor HxW (default: the --sim-psf's, else 64x80)")
    s.add_argument("--sim-psf", help="PSF file the simulator renders with (default synthetic)")
    s.add_argument("--sim-flux", type=POSITIVE, default=5e6, help="point source e-/ms (sim)")
    s.add_argument("--sim-seed", type=NONNEG_INT, default=0,
                   help="seed of the simulated camera's PSF and noise (0)")


def register(sub: Any) -> None:
    """Add ``calibrate`` and its subcommands."""
    p = sub.add_parser("calibrate", help="calibrate at the bench: PSF, darks, shutter, filters")
    csub = p.add_subparsers(dest="what", metavar="WHAT", required=True)

    psf = csub.add_parser("psf", help="capture a PSF with the point source")
    _common(psf, source=True, source_required=True)
    _psf_options(psf)
    psf.add_argument("--out", required=True, help="calibration file (.tif)")
    add_overwrite_option(psf)
    psf.set_defaults(func=run_psf)

    depth = csub.add_parser("depth", help="capture a PSF stack over a series of positions")
    _common(depth, source=True, source_required=True)
    _psf_options(depth)
    depth.add_argument(
        "--positions", required=True, help="comma-separated labels, e.g. 10mm,20mm,40mm"
    )
    depth.add_argument(
        "--no-prompt", action="store_true", help="do not wait for Enter before each position"
    )
    depth.add_argument("--out", required=True, help="stack file (.tif)")
    add_overwrite_option(depth)
    depth.set_defaults(func=run_depth)

    darks = csub.add_parser("darks", help="dark frames and hot/dead pixel maps")
    _common(darks, source=True, source_required=False)
    darks.add_argument("--frames", type=POSITIVE_INT, default=16, help="dark frames to average")
    darks.add_argument(
        "--flats", type=NONNEG_INT, default=0, help="flat frames to average (dead pixels); 0: none"
    )
    darks.add_argument("--hot-sigma", type=POSITIVE, default=6.0,
                       help="a pixel is hot this many sigmas above the dark median (6)")
    darks.add_argument("--dead-fraction", type=UNIT, default=0.5,
                       help="a pixel is dead when its flat response is below this fraction of "
                       "the 5x5 local median around it (0.5)")
    darks.add_argument("--no-prompt", action="store_true", help="do not wait for Enter")
    darks.add_argument("--out", required=True, help="pixel-maps file (.npz)")
    add_overwrite_option(darks)
    darks.set_defaults(func=run_darks)

    sh = csub.add_parser(
        "shutter", help="shutter function from the timing, or measured with --source"
    )
    _common(sh, source=True, source_required=False)
    sh.add_argument("--bin-lines", type=POSITIVE_INT, default=None,
                    help="time bin width in lines (default: the finest the rows resolve, at "
                         "least the --downsample factor; more bins than rows are refused)")
    sh.add_argument("--downsample", type=POSITIVE_INT, default=1, help="row downsampling factor")
    sh.add_argument("--pulse", help="strobe pulse length (default one line time)")
    sh.add_argument("--step", help="delay step (default half the pulse)")
    sh.add_argument("--span", help="last delay (default 1.25 x frame time)")
    sh.add_argument("--frames-per-delay", type=POSITIVE_INT, default=1,
                    help="frames averaged at each strobe delay (1)")
    sh.add_argument("--out", required=True, help="shutter file (.npz)")
    add_overwrite_option(sh)
    sh.set_defaults(func=run_shutter)

    fc = csub.add_parser("filters", help="validate, normalise and save a filter cube")
    fc.add_argument("--cube", required=True, help="filter cube file (.mat, .npy, .npz, .tif)")
    fc.add_argument("--key", help="variable name in a .mat/.npz file")
    where = fc.add_mutually_exclusive_group(required=True)
    where.add_argument("--sensor", help="sensor size HxW")
    where.add_argument("--like", help="a PSF or calibration file of the sensor's size")
    fc.add_argument("--layout", choices=("auto", "khw", "hwk"), default="auto",
                    help="axis order of the cube: auto, khw or hwk")
    fc.add_argument("--normalise", choices=("max", "none"), default="max",
                    help="scale the whole cube by one factor so its largest transmission is 1 "
                    "(max; the bands keep their ratios), or keep the values, which must be in "
                    "[0, 1] (none)")
    fc.add_argument("--downsample", type=POSITIVE_INT, default=1,
                    help="box downsampling factor of the cube (default 1)")
    fc.add_argument("--out", required=True, help="filter-cube file (.tif)")
    add_overwrite_option(fc)
    fc.set_defaults(func=run_filters)


def _psf_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("PSF capture")
    g.add_argument("--frames", type=POSITIVE_INT, default=16, help="PSF frames to average")
    g.add_argument("--darks", type=POSITIVE_INT, default=16, help="dark frames to average")
    g.add_argument("--no-auto-exposure", action="store_true", help="keep the exposure")
    g.add_argument("--target", type=finite_float(0, 1, lo_open=True), default=0.75,
                   help="target peak (fraction)")
    g.add_argument(
        "--max-exposure", default="1s", help="longest exposure auto-exposure may use (1s)"
    )
    g.add_argument(
        "--centre", default="none", help="'none', 'centroid' or ROW,COL moved to the centre"
    )
    g.add_argument("--shape", help="crop/pad the PSF to HxW")
    g.add_argument("--max-offcentre", type=UNIT, default=0.25, help="fraction of the sensor")
    g.add_argument("--min-snr", type=NONNEG, default=10.0,
                   help="refuse a PSF whose peak SNR is below this (10)")
    g.add_argument("--pixel-maps", help="pixel-maps file whose bad pixels are repaired too")


#: the largest frame the simulated camera renders within a frame timeout on one core
SIM_MAX_PIXELS = 4096 * 4096
#: the smallest simulated sensor (HxW): drivers.simcam.SimulatedCamera needs 2 rows
SIM_MIN_HW = (2, 1)


@contextlib.contextmanager
def _devices(args: argparse.Namespace) -> Iterator[tuple[Any, Any]]:
    """Open the camera and the source (spawning the simulated firmware for ``sim``)."""
    import tempfile

    from drivers.lightsource import LightSourceBusy, SerialPointSource
    from drivers.registry import open_camera, parse_camera_spec

    with contextlib.ExitStack() as stack:
        # SIGTERM / SIGHUP (kill, timeout, a closed terminal) stop the command as Ctrl-C does,
        # so the clean-up below runs: light off, firmware stopped, temporary files removed
        stack.enter_context(TerminateAsInterrupt())
        src_spec: str | None = getattr(args, "source", None)
        if src_spec is not None and not src_spec.strip():
            raise ValueError("--source is empty: give sim or the point source's serial port")
        if src_spec is None and getattr(args, "source_required", False):
            # the simulated bench with nothing attached; a real camera sees a real source only
            if parse_camera_spec(args.camera).name != "sim":
                raise ValueError(f"--source is needed with --camera {args.camera}: the serial "
                                 "port of the point source (sim goes with --camera sim)")
            src_spec = "sim"
        from app.commands.devices import producer_kwargs

        kwargs = producer_kwargs(args.producer, args.camera)  # refused with another backend
        state_path = None
        source = None
        port: str | None
        if src_spec == "sim":
            from drivers.pointsource_sim import spawn_simulated_source

            tmp = stack.enter_context(tempfile.TemporaryDirectory(prefix="lenslesscam-cal-"))
            # removed by the firmware if this process is killed outright (no clean-up here)
            sim = spawn_simulated_source(Path(tmp) / "light-state.json", owned_folder=tmp)
            stack.callback(sim.stop)
            state_path = sim.state_path
            port = sim.port
        else:
            port = src_spec
        backend = parse_camera_spec(args.camera).name
        if backend == "sim":
            camera = open_camera("sim", **sim_camera_kwargs(args, state_path))
        else:
            # a file source (image sequence, video) ends where it ends: looped, its frames
            # were averaged again and again as if new (16 darks from 5 files)
            camera = open_camera(args.camera, **({"loop": False} if backend == "v4l2" else kwargs))
        stack.callback(camera.close)
        if args.exposure:
            camera.exposure_us = parse_duration_us(args.exposure)
        if args.gain is not None:
            camera.gain = args.gain
        if port:
            source = SerialPointSource(port)
            try:
                source.open()
            except LightSourceBusy as exc:  # "port X is in use by another process"
                raise ValueError(str(exc)) from exc
            except Exception as exc:
                # the driver's messages name the source already: say it once
                reason = str(exc)
                for said in (f"cannot open {source.describe()}: ", f"{source.describe()}: "):
                    reason = reason.removeprefix(said)
                raise ValueError(f"cannot open the point source on {port}: {reason}") from exc
            stack.callback(source.close)
        yield camera, source


def sim_camera_kwargs(args: argparse.Namespace, state_path: Path | None) -> dict[str, Any]:
    """The simulated camera of the ``--sim-*`` options (its size, PSF renderer and seed)."""
    from recon.simulate import render_frames, synthetic_psf

    if args.sim_psf:
        from recon.io import box_downsample, load_psf, normalise

        psf = load_psf(args.sim_psf)[0]
        if args.sim_size:
            h, w = parse_hw(args.sim_size, "--sim-size", SIM_MIN_HW)
            f = psf.shape[0] // h
            if f < 1 or psf.shape[0] != f * h or psf.shape[1] != f * w:
                raise ValueError(
                    f"--sim-psf {args.sim_psf} is {psf.shape[0]}x{psf.shape[1]}: not an "
                    f"integer multiple of --sim-size {h}x{w}"
                )
            psf = normalise(box_downsample(psf, f), "sum")
        h, w = (int(psf.shape[0]), int(psf.shape[1]))
    else:
        h, w = parse_hw(args.sim_size or "64x80", "--sim-size", SIM_MIN_HW)
    if h * w > SIM_MAX_PIXELS:  # a 16384x16384 frame timed out, then a traceback (or a hang)
        raise ValueError(f"the simulated camera is {h}x{w}: it renders at most "
                         f"{SIM_MAX_PIXELS / 1e6:.1f} M pixels a frame in time (4096x4096); "
                         "choose a smaller --sim-size (or --sim-psf)")
    if not args.sim_psf:
        psf = synthetic_psf((h, w), seed=args.sim_seed)
    return {
        "width": w,
        "height": h,
        "renderer": render_frames(psf),
        "light_state": state_path,
        "point_position": (h // 2, w // 2),
        "point_flux_e_per_ms": args.sim_flux,
        "pacing": False,
        "exposure_us": 100.0,
        "seed": args.sim_seed,
    }


def _drive(workflow: Any, label: str) -> Any:
    """Run a workflow with a progress bar on stderr (when it is a terminal)."""
    bar = ProgressBar(1000, label)
    try:
        for p in workflow:
            bar.update(int(1000 * p.fraction), p.message[:60])
    finally:
        bar.close()
    return workflow.result


def _psf_settings(args: argparse.Namespace) -> Any:
    from calibration.psf import PsfSettings

    centre: Any = args.centre
    if centre not in ("none", "centroid"):
        import math

        parts = centre.split(",")
        try:
            centre = tuple(float(v) for v in parts)
        except ValueError:
            centre = ()
        if len(centre) != 2 or not all(math.isfinite(v) for v in centre):
            raise ValueError(f"--centre must be 'none', 'centroid' or ROW,COL (two finite "
                             f"numbers, pixels of the capture), got {args.centre!r}")
    return PsfSettings(
        n_frames=args.frames,
        n_darks=args.darks,
        auto_exposure=not args.no_auto_exposure,
        max_exposure_us=parse_duration_us(args.max_exposure),
        target_peak=args.target,
        intensity=args.intensity,
        centre=centre,
        shape=parse_hw(args.shape, "--shape") if args.shape else None,
        max_offcentre=args.max_offcentre,
        min_snr=args.min_snr,
        frame_timeout_s=args.timeout,
        settle_frames=args.settle,
    )


def _check_outputs(args: argparse.Namespace, kind: str) -> None:
    """Check, before any capture, what can be checked of the output.

    The camera spec (read once), the output's suffix for ``kind`` (the calibration file
    writers' own rule) and the output rule of every command (the camera's files are inputs).
    """
    from app.commands.devices import check_camera_command_outputs
    from drivers.registry import parse_camera_spec
    from recon.calibfile import check_calibration_suffix

    if hasattr(args, "camera"):
        args.camera = str(parse_camera_spec(args.camera))  # read once ("sim " is sim)
    check_calibration_suffix(args.out, kind)
    if hasattr(args, "camera"):
        check_camera_command_outputs(args, [args.out])
    else:
        check_command_outputs(args, [args.out])


def _bad_pixels(args: argparse.Namespace) -> tuple[Any, dict[str, Any] | None]:
    """The bad pixels of ``--pixel-maps`` and what the PSF's metadata records of the file."""
    if not args.pixel_maps:
        return None, None
    import numpy as np

    from recon.calibfile import load_calibration
    from recon.formats import file_hash

    cal = load_calibration(args.pixel_maps, expect="pixel-maps")
    path = Path(args.pixel_maps).expanduser().resolve()
    info = {"file": str(path), "file_hash": file_hash(path),
            "camera": cal.metadata.get("camera"), "date": cal.metadata.get("date")}
    return np.asarray(cal.data) == 0, info


def _maps_metadata(maps: dict[str, Any] | None, camera: Any) -> dict[str, Any] | None:
    """What a PSF or stack records of its pixel maps (None: none given).

    Maps taken with another camera than ``camera`` are said, on stderr and in the record.
    """
    if maps is None:
        return None
    then = maps.get("camera")
    if isinstance(then, dict):
        from calibration.sources import camera_description

        now = camera_description(camera)
        differ = [f"{k} {then[k]} vs {now[k]}" for k in ("backend", "camera_id", "model")
                  if then.get(k) is not None and now.get(k) is not None and then[k] != now[k]]
        if differ:
            maps["warning"] = (f"--pixel-maps {maps.get('file')} were taken with another "
                               f"camera ({', '.join(differ)}): its hot and dead pixels may not "
                               "be this sensor's")
            _warn([maps["warning"]])
    return {"pixel_maps": maps}


def run_psf(args: argparse.Namespace) -> int:
    """Capture and save a PSF calibration."""
    _check_outputs(args, "psf")
    from calibration.psf import capture_psf
    from calibration.workflow import Workflow

    settings = _psf_settings(args)
    bad, maps = _bad_pixels(args)
    with _devices(args) as (camera, source):
        wf = Workflow(
            capture_psf(camera, source, settings, out=args.out, bad_pixels=bad,
                        bad_pixels_from=f"--pixel-maps {args.pixel_maps}",
                        extra_metadata=_maps_metadata(maps, camera)),
            "PSF calibration",
        )
        cal = _drive(wf, "PSF")
    _warn(cal.warnings)
    # the report of the PSF as saved (centred, cropped or padded with --centre, --shape)
    print(f"wrote {cal.path} ({cal.psf.shape[0]}x{cal.psf.shape[1]})")
    print(f"exposure {cal.exposure_us:g} us; {cal.quality.summary()}")
    return 0


def _warn(lines: Any, where: str = "") -> None:
    """Print a workflow's warnings on stderr, one line each (the CLI's warning format)."""
    for line in lines:
        print(f"lenslesscam: warning: {where}{line}", file=sys.stderr)


def run_depth(args: argparse.Namespace) -> int:
    """Capture and save a depth PSF stack."""
    _check_outputs(args, "psf-stack")
    from calibration.psf import capture_depth_stack
    from calibration.workflow import Workflow

    positions = [p.strip() for p in args.positions.split(",")]
    if not any(positions):
        raise ValueError("--positions lists no position")
    if not all(positions):  # "10mm,,20mm": a typo, or a position left out
        raise ValueError(f"--positions {args.positions!r} has an empty entry: give one label "
                         "per position, comma-separated")
    repeated = sorted({p for p in positions if positions.count(p) > 1})
    if repeated:
        raise ValueError(f"--positions names {', '.join(repeated)} more than once: each plane "
                         "of the stack is one position")
    settings = _psf_settings(args)

    def prompt(index: int, position: str) -> None:
        if args.no_prompt:
            return
        sys.stderr.write(
            f"\nMove the point source to {position} ({index + 1} of {len(positions)}) "
            "and press Enter... "
        )
        sys.stderr.flush()
        if not sys.stdin.readline():
            raise ValueError("no answer on standard input (use --no-prompt to run unattended)")

    bad, maps = _bad_pixels(args)  # (it was accepted and ignored)
    with _devices(args) as (camera, source):
        wf = Workflow(
            capture_depth_stack(
                camera, source, positions, prompt=prompt, settings=settings, out=args.out,
                bad_pixels=bad, bad_pixels_from=f"--pixel-maps {args.pixel_maps}",
                extra_metadata=_maps_metadata(maps, camera),
            ),
            "depth stack",
        )
        result = _drive(wf, "depth")
    for pos, plane in zip(result.positions, result.planes, strict=True):
        _warn(plane.warnings, f"position {pos}: ")
    n = len(positions)
    print(f"wrote {result.path} ({n} plane{'' if n == 1 else 's'})")
    for pos, plane in zip(result.positions, result.planes, strict=True):
        print(f"  {pos}: exposure {plane.exposure_us:g} us; {plane.quality.summary()}")
    return 0


def run_darks(args: argparse.Namespace) -> int:
    """Capture darks (and flats) and save the pixel maps."""
    _check_outputs(args, "pixel-maps")
    from calibration.darks import calibrate_pixel_maps
    from calibration.workflow import Workflow

    def ask(text: str) -> Any:
        if args.no_prompt:
            return None

        def prompt() -> None:
            sys.stderr.write(f"\n{text} and press Enter... ")
            sys.stderr.flush()
            if not sys.stdin.readline():
                raise ValueError("no answer on standard input (use --no-prompt)")

        return prompt

    with _devices(args) as (camera, source):
        wf = Workflow(
            calibrate_pixel_maps(
                camera,
                source=source,
                n_darks=args.frames,
                n_flats=args.flats,
                prepare_darks=None if source is not None else ask("Cover the sensor"),
                prepare_flats=ask("Illuminate the sensor uniformly") if args.flats else None,
                hot_sigma=args.hot_sigma,
                dead_fraction=args.dead_fraction,
                timeout_s=args.timeout,
                settle=args.settle,
                out=args.out,
            ),
            "pixel maps",
        )
        maps = _drive(wf, "darks")
    print(f"wrote {maps.path}")
    noise = maps.dark_noise_adu
    said = (
        "noise: unknown (one dark frame; capture 2 or more with --frames)"
        if noise is None
        else f"noise {noise:.3g} ADU rms (sqrt of the mean per-pixel temporal variance, "
        "hot/dead pixels excluded)"
    )
    print(
        f"{int(maps.hot.sum())} hot, {int(maps.dead.sum())} dead pixels; dark level "
        f"{maps.metadata()['dark_level']:.4g} ADU, {said}"
    )
    return 0


def run_shutter(args: argparse.Namespace) -> int:
    """Shutter function from the camera's timing, or measured by strobing the source.

    :func:`calibration.shutter.calibrate_shutter`, the wizard's path too: the frame's model
    chooses the bins (the finest the rows resolve without ``--bin-lines``) and refuses more
    bins than rows before the scan and before anything is written.
    """
    _check_outputs(args, "shutter")
    from calibration.shutter import ShutterSettings, calibrate_shutter
    from calibration.workflow import Workflow

    if (args.bin_lines is not None and args.bin_lines < 1) or args.downsample < 1:
        raise ValueError("--bin-lines and --downsample must be >= 1")
    pulse_us = _strobe_time(args.pulse, "--pulse") if args.pulse else None
    step_us = _strobe_time(args.step, "--step") if args.step else None
    with _devices(args) as (camera, source):
        settings = ShutterSettings(
            pulse_us=pulse_us,
            step_us=step_us,
            span_us=parse_duration_us(args.span) if args.span else None,
            frames_per_delay=args.frames_per_delay,
            intensity=args.intensity,
            frame_timeout_s=args.timeout,
            settle_frames=args.settle,
        )
        wf = Workflow(
            calibrate_shutter(
                camera,
                source,
                settings,
                bin_lines=args.bin_lines,
                row_factor=args.downsample,
                out=args.out,
                timeout_s=args.timeout,
            ),
            "shutter" if source is None else "shutter measurement",
        )
        sf = _drive(wf, "shutter")
    print(f"wrote {sf.path}: shutter {sf.shutter.shape[0]} bins x {sf.shutter.shape[1]} rows")
    if sf.measurement is None:
        print(f"timing {sf.timing.to_dict()}")
    else:
        print(sf.measurement.summary())
    return 0


def _strobe_time(text: str, option: str) -> float:
    """``--pulse`` / ``--step`` as the point source sends it (:func:`calibration.strobe_time`).

    Shorter than its 0.1 us step is refused; a finer value is rounded, with a warning.
    """
    from calibration.shutter import strobe_time

    sent, warning = strobe_time(parse_duration_us(text), f"{option} {text}")
    if warning is not None:
        _warn([warning])
    return sent


def run_filters(args: argparse.Namespace) -> int:
    """Validate, normalise and save a filter cube."""
    _check_outputs(args, "filter-cube")
    from calibration.filters import load_filter_cube

    if args.key is not None and Path(args.cube).suffix.lower() not in (".mat", ".npz"):
        raise ValueError(f"--key {args.key} names a variable of a .mat or .npz file; "
                         f"{args.cube} holds one array (leave --key out)")

    if args.sensor:
        shape = parse_hw(args.sensor, "--sensor")
    else:
        import numpy as np

        from recon.calibfile import load_calibration
        from recon.formats import NotOurFile
        from recon.io import load_image

        p = Path(args.like)
        try:  # a calibration .npz holds several arrays (which load_image refuses): its main one
            cal = load_calibration(p) if p.suffix.lower() == ".npz" else None
        except NotOurFile:  # an .npz of someone else's: read as an array
            cal = None
        if cal is not None and cal.kind == "shutter":
            raise ValueError(f"--like {p} is a shutter calibration, (time bins, rows): it does "
                             "not give the sensor's size; give a PSF or pixel-maps file, or "
                             "--sensor HxW")
        # (a TIFF of ours, PSF or stack, is checked by load_image as any input)
        like = np.asarray(cal.data if cal is not None else load_image(p))
        if like.ndim < 2:
            raise ValueError(f"--like {args.like} is not an image (shape {like.shape})")
        shape = (int(like.shape[-2]), int(like.shape[-1]))
    cube = load_filter_cube(
        args.cube,
        shape,
        key=args.key,
        layout=args.layout,
        normalise=args.normalise,
        downsample=args.downsample,
    ).save(args.out)
    print(f"wrote {cube.path}: {cube.bands} bands of {shape[0]}x{shape[1]}")
    return 0
