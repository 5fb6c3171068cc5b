"""``lenslesscam recon fista|udn``: reconstruct a measurement."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

from app.commands._common import ProgressBar, load_array, parse_dark, parse_field


def register(sub: Any) -> None:
    """Add ``recon`` and its methods."""
    p = sub.add_parser("recon", help="reconstruct a measurement (FISTA-TV or UDN)")
    methods = p.add_subparsers(dest="method", metavar="METHOD", required=True)
    f = methods.add_parser("fista", help="FISTA with total variation and non-negativity")
    add_input_arguments(f)
    f.add_argument("--tau", type=float, default=1e-3, help="TV weight (default 1e-3)")
    f.add_argument("--iters", type=int, default=300, help="iteration limit (default 300)")
    f.add_argument("--tol", type=float, default=1e-5, help="stop on relative change (1e-5)")
    f.add_argument("--tv", choices=["iso", "aniso"], default="iso", help="2D TV form")
    f.add_argument("--tv-k", type=float, default=0.5,
                   help="weight of TV along k for video/spectral/depth (default 0.5)")
    f.add_argument("--prox-iters", type=int, default=3, help="inner TV prox iterations")
    f.add_argument("--no-restart", action="store_true", help="disable adaptive restart")
    f.add_argument("--out", required=True, help="output TIFF (previews are written beside it)")
    f.set_defaults(func=run_fista)
    from app.commands.plan import register_auto
    from app.commands.recon_udn import register_udn

    register_udn(methods)
    register_auto(methods)


def add_input_arguments(p: argparse.ArgumentParser) -> None:
    """Inputs shared by every reconstruction method."""
    p.add_argument("--model", choices=["2d", "video", "spectral", "depth"], default="2d")
    p.add_argument("--psf", help="PSF file (2d, video, spectral)")
    p.add_argument("--psf-stack", help="depth: multi-page TIFF, (K,H,W) array or a folder")
    p.add_argument("--meas", required=True, help="measurement file")
    p.add_argument("--mask", help="erasure / dead-pixel mask (1 = measured)")
    p.add_argument("--shutter", help="video: shutter function M (K, rows) (.npy/.npz/.tif)")
    p.add_argument("--filters", help="spectral: filter cube (K, H, W) (.npy/.npz/.mat/.tif)")
    p.add_argument("--downsample", type=int, default=1, help="box downsampling factor")
    p.add_argument("--dark", help="dark level: a number, 'auto' or a dark-frame file")
    p.add_argument("--psf-dark", help="dark level of the PSF (default: same as --dark)")
    p.add_argument("--rgb", action="store_true", help="reconstruct colour channels")
    p.add_argument("--field", default="sensor", help="scene field: sensor, full (2x) or HxW")
    p.add_argument("--float64", action="store_true", help="compute in float64")


def load_problem(args: argparse.Namespace) -> dict[str, Any]:
    """Load and check the inputs named on the command line; build the forward model."""
    import numpy as np
    import torch

    from drivers.timing import downsample_rows
    from recon.formats import file_hash
    from recon.io import (
        box_downsample,
        check_pair,
        downsample_masked,
        load_measurement,
        load_psf,
        load_psf_stack,
        normalise,
    )
    from recon.models import build_model

    channels = "rgb" if args.rgb else "gray"
    dark = parse_dark(args.dark)
    psf_dark = parse_dark(args.psf_dark) if args.psf_dark is not None else dark
    raw_mask = None
    if args.mask:
        raw_mask = load_array(args.mask, "mask", key="mask").astype(np.float64)
        if raw_mask.ndim == 3 and raw_mask.shape[0] == 1:
            raw_mask = raw_mask[0]
        if raw_mask.ndim != 2:
            raise ValueError(f"mask {args.mask} must be a 2D (H, W) array, got shape "
                             f"{raw_mask.shape}")
    if raw_mask is None or args.downsample == 1:
        meas = load_measurement(args.meas, dark=dark, downsample=args.downsample,
                                channels=channels)
    else:  # erased pixels must not be averaged into the coarse pixels
        full = load_measurement(args.meas, dark=dark, channels=channels, normalise=None)
        meas, _ = downsample_masked(full, raw_mask, args.downsample)
        if not np.any(meas > 0):
            raise ValueError(f"measurement file {args.meas} is all zero on its measured pixels")
        meas = normalise(meas, "max").astype(np.float32)
    if args.model == "depth":
        if not args.psf_stack:
            raise ValueError("--model depth needs --psf-stack")
        psf = load_psf_stack(args.psf_stack, dark=psf_dark, downsample=args.downsample)
        check_pair(psf, meas, psf_is_stack=True)
        psf_files = [args.psf_stack]
    else:
        if not args.psf:
            raise ValueError(f"--model {args.model} needs --psf")
        psf = load_psf(args.psf, dark=psf_dark, downsample=args.downsample, channels=channels)
        check_pair(psf, meas)
        psf_files = [args.psf]
    sensor = (int(meas.shape[-2]), int(meas.shape[-1]))
    mask = None
    if raw_mask is not None:
        # a coarse pixel is measured when any of its sensor pixels is (see downsample_masked)
        mask = (box_downsample(raw_mask > 0.5, args.downsample) > 0).astype(np.float32)
        if mask.shape != sensor:
            raise ValueError(f"mask {args.mask} has shape {mask.shape} after downsampling by "
                             f"{args.downsample}; the measurement has {sensor}")
    shutter = filters = None
    if args.model == "video":
        if not args.shutter:
            raise ValueError("--model video needs --shutter (a (K, rows) shutter function)")
        shutter = load_array(args.shutter, "shutter", key="shutter").astype(np.float64)
        if shutter.ndim == 2 and args.downsample > 1 and shutter.shape[1] != sensor[0]:
            shutter = downsample_rows(shutter, args.downsample)
    elif args.shutter:
        raise ValueError("--shutter is only for --model video")
    if args.model == "spectral":
        if not args.filters:
            raise ValueError("--model spectral needs --filters (a (K, H, W) filter cube)")
        filters = load_array(args.filters, "filter cube", key="filters").astype(np.float64)
        if filters.ndim == 3 and args.downsample > 1 and filters.shape[1:] != sensor:
            filters = box_downsample(filters, args.downsample)
    elif args.filters:
        raise ValueError("--filters is only for --model spectral")
    dtype = torch.float64 if args.float64 else torch.float32
    field = parse_field(args.field, sensor)
    model = build_model(args.model, psf, channels=meas.shape[0], mask=mask, shutter=shutter,
                        filters=filters, field=field, dtype=dtype)
    if args.model == "depth" and meas.shape[0] != 1:
        raise ValueError("the depth model takes a grayscale measurement")
    inputs = {"psf": psf_files, "meas": args.meas, "mask": args.mask, "shutter": args.shutter,
              "filters": args.filters}
    hashes = {"psf": file_hash(psf_files[0]) if Path(psf_files[0]).is_file() else None,
              "meas": file_hash(args.meas)}
    return {"model": model, "meas": meas, "psf": psf, "inputs": inputs, "hashes": hashes,
            "dtype": dtype}


def run_fista(args: argparse.Namespace) -> int:
    """Run FISTA-TV and save the result with its metadata."""
    import torch

    from recon.fista import Fista
    from recon.io import save_reconstruction
    from recon.tv import TV

    prob = load_problem(args)
    model = prob["model"]
    tv = TV(isotropic=args.tv == "iso", weight_k=args.tv_k if model.k > 1 else 0.0)
    solver = Fista(model.op, torch.as_tensor(prob["meas"], dtype=prob["dtype"]), tau=args.tau,
                   tv=tv, max_iter=args.iters, tol=args.tol, restart=not args.no_restart,
                   prox_iters=args.prox_iters)
    bar = ProgressBar(args.iters, "fista")
    t0 = time.perf_counter()
    last = None
    for step in solver.steps():
        last = step
        bar.update(step.iteration, f"objective {step.objective:.4g}")
    bar.close()
    wall = time.perf_counter() - t0
    kind = {"2d": "image", "video": "video", "spectral": "spectral", "depth": "depth"}[args.model]
    meta = {
        "method": "fista-tv", "model": args.model, "parameters": solver.params,
        "iterations": solver.iteration, "stop_reason": solver.reason.value if solver.reason else
        "max_iter", "wall_time_s": round(wall, 3),
        "final": {"objective": last.objective, "residual": last.residual} if last else None,
        "inputs": prob["inputs"], "input_hashes": prob["hashes"],
        "preprocessing": {"downsample": args.downsample, "dark": args.dark, "rgb": args.rgb,
                          "field": list(model.info["field"])},
    }
    paths = save_reconstruction(args.out, solver.x.float().cpu().numpy(), meta, kind=kind)
    summary = {"out": [str(p) for p in paths], "iterations": solver.iteration,
               "stop_reason": meta["stop_reason"], "wall_time_s": meta["wall_time_s"],
               "residual": last.residual if last else None}
    print(json.dumps(summary), file=sys.stdout)
    return 0
