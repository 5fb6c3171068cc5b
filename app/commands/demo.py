"""``lenslesscam demo``: reconstruct the bundled real DiffuserCam measurement of a hand."""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from app.commands._common import fit_command_threads
from app.commands._options import add_overwrite_option, check_command_outputs
from app.commands._tau import iters_type, resolve_tau, tau_search_s, tau_type


def register(sub: Any) -> None:
    """Add ``demo``."""
    p = sub.add_parser("demo", help="reconstruct a bundled real measurement (hand, or 3D USAF)")
    p.add_argument("--scene", choices=["hand", "depth"], default="hand",
                   help="hand: DiffuserCam-Tutorial 2D; depth: DiffuserCam 3D USAF target")
    p.add_argument("--out", default=None,
                   help="output folder (default: the user's data folder, "
                   "$XDG_DATA_HOME/lenslesscam/demo; printed on use)")
    p.add_argument("--tau", type=tau_type, default=None, metavar="TAU|auto",
                   help="TV weight (hand: 'auto', chosen from held-out pixels as by recon "
                   "fista; depth: 3e-3)")
    p.add_argument("--iters", type=iters_type, default=None, metavar="N|auto",
                   help="iterations (hand: 'auto'; depth: 500)")
    p.add_argument("--open", action="store_true", help="open the preview in an image viewer")
    add_overwrite_option(p)
    p.set_defaults(func=run)


#: Planes of the bundled (1/2-scale, 22-plane) stack used by the depth demo: 2..9, i.e. the
#: original planes 4..19. With all 22 planes FISTA-TV piles the light into the last few planes
#: (their PSFs are the widest) and the bars blur; docs/reconstructions.md shows both.
DEPTH_PLANES = slice(2, 10)


def run(args: argparse.Namespace) -> int:
    """FISTA-TV on a bundled real measurement; writes TIFF + PNG previews."""
    from app.locations import default_demo_dir
    from recon.io import reconstruction_paths

    if args.out is None:
        args.out = str(default_demo_dir())
        print(f"demo: writing to {args.out} (--out DIR to choose another folder)",
              file=sys.stderr)
    name, kind = ("usaf3d.tif", "depth") if args.scene == "depth" else ("hand.tif", "image")
    check_command_outputs(args, reconstruction_paths(Path(args.out) / name, kind))
    if args.scene == "depth":
        return run_depth(args)
    return run_hand(args)


def _check(check_explains: Any, solver: Any, model: Any, b: Any) -> None:
    """The result check of every reconstruction command, with the demo's own options."""
    check_explains(
        solver.x, model, b, method="fista-tv", iterations=solver.iteration,
        reason=solver.reason.value if solver.reason else "max_iter", tau=float(solver.tau),
        tv=solver.tv, refuse_hint="an extreme --tau can hold the solver at 0",
        flat_hint="it needs more --iters", objective_hint="it needs more --iters",
        who="lenslesscam demo")


def run_depth(args: argparse.Namespace) -> int:
    """3D: the tilted USAF target with the measured PSF stack (depth model, 3D TV)."""
    import torch

    from app.commands.recon import check_explains
    from recon import samples
    from recon.fista import Fista
    from recon.io import save_reconstruction
    from recon.models import build_model
    from recon.tv import TV

    tau = 3e-3 if args.tau is None else args.tau
    iters = 500 if args.iters is None else args.iters
    stack = samples.depth_psf_stack()[DEPTH_PLANES]
    meas = samples.depth_measurement()
    model = build_model("depth", stack)
    fit_command_threads(args, model.scene_shape)
    t0 = time.perf_counter()
    solver = Fista(model.op, torch.as_tensor(meas), tau=tau, tv=TV(weight_k=1.0),
                   max_iter=iters, tol=1e-7)
    res = solver.run()
    wall = time.perf_counter() - t0
    _check(check_explains, solver, model, torch.as_tensor(meas))
    planes = samples.depth_planes()[DEPTH_PLANES]
    meta = {"method": "fista-tv", "model": "depth", "parameters": solver.params,
            "iterations": res.iterations, "stop_reason": res.reason.value,
            "wall_time_s": round(wall, 3), "threads": _threads(args),
            "original_planes": [list(p) for p in planes],
            "inputs": {"psf_stack": "sample:depth_psf_stack", "meas": "sample:depth_measurement"},
            "source": "DiffuserCam 3D example (Waller Lab, BSD-3-Clause), 1/2 scale"}
    paths = save_reconstruction(Path(args.out) / "usaf3d.tif", res.x.numpy(), meta, kind="depth")
    print(json.dumps({"out": [str(p) for p in paths], "iterations": res.iterations,
                      "wall_time_s": round(wall, 2)}))
    _maybe_open(args, paths[-1])
    return 0


def _threads(args: argparse.Namespace) -> str:
    """The torch thread count and why (``--threads`` or recon.threads' choice)."""
    choice = getattr(args, "thread_choice", None)
    if choice is not None:
        return str(choice)
    import torch

    return f"{torch.get_num_threads()} torch thread(s)"


def _maybe_open(args: argparse.Namespace, path: Path) -> None:
    if not args.open:
        return
    viewer = shutil.which("xdg-open")
    if viewer and os.environ.get("DISPLAY"):
        subprocess.Popen([viewer, str(path)])
    else:
        print(f"no display or viewer: open {path} yourself")


def run_hand(args: argparse.Namespace) -> int:
    """FISTA-TV on the DiffuserCam-Tutorial hand at 1/8 scale; writes TIFF + PNG."""
    import torch

    from app.commands.recon import check_explains
    from recon import samples
    from recon.fista import Fista
    from recon.io import save_reconstruction
    from recon.models import build_model
    from recon.tv import TV

    psf = samples.tutorial_psf()
    meas = samples.tutorial_measurement()
    model = build_model("2d", psf)
    fit_command_threads(args, model.scene_shape)
    b = torch.as_tensor(meas)
    tv = TV()
    tau, iters, tau_meta = resolve_tau(args, model, b, tv)  # auto unless --tau/--iters given
    t0 = time.perf_counter()  # the reconstruction alone, as recon fista's wall_time_s
    solver = Fista(model.op, b, tau=tau, tv=tv, max_iter=iters)
    res = solver.run()
    wall = time.perf_counter() - t0
    _check(check_explains, solver, model, b)  # the result check of every command
    meta = {"method": "fista-tv", "model": "2d", "parameters": solver.params,
            "regularisation": tau_meta, "iterations": res.iterations,
            "stop_reason": res.reason.value,
            "wall_time_s": round(wall, 3), "tau_search_s": tau_search_s(tau_meta),
            "threads": _threads(args),
            "inputs": {"psf": "sample:tutorial_psf", "meas": "sample:tutorial_measurement"},
            "source": "DiffuserCam-Tutorial (Waller Lab, BSD-3-Clause), 1/8 scale"}
    paths = save_reconstruction(Path(args.out) / "hand.tif", res.x.numpy(), meta, kind="image")
    print(json.dumps({"out": [str(p) for p in paths], "iterations": res.iterations,
                      "tau": tau, "tau_rule": tau_meta["tau_rule"],
                      "wall_time_s": round(wall, 2),
                      "tau_search_s": tau_search_s(tau_meta)}))
    _maybe_open(args, paths[1])
    return 0
