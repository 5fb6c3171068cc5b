"""``lenslesscam recon fista|udn``: reconstruct a measurement."""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from typing import Any

from app.commands._common import ProgressBar, fit_command_threads
from app.commands._inputs import add_layout_arguments, problem_spec
from app.commands._options import (
    NONNEG,
    POSITIVE,
    POSITIVE_INT,
    add_overwrite_option,
    check_command_outputs,
    finite_float,
)
from app.commands._tau import add_tau_arguments, resolve_tau, tau_search_s


def register(sub: Any) -> None:
    """Add ``recon`` and its methods."""
    p = sub.add_parser("recon", help="reconstruct a measurement (FISTA-TV or UDN)")
    methods = p.add_subparsers(dest="method", metavar="METHOD", required=True)
    f = methods.add_parser("fista", help="FISTA with total variation and non-negativity")
    _add_tv_solver_arguments(f)
    f.add_argument("--tv-k", type=NONNEG, default=0.5,
                   help="weight of TV along k for video/spectral/depth (default 0.5)")
    f.add_argument("--prox-iters", type=POSITIVE_INT, default=3, help="inner TV prox iterations")
    f.add_argument("--no-restart", action="store_true",
                   help="disable the gradient restart of the (POGM) momentum")
    f.add_argument("--precondition", type=_precondition, default="auto",
                   help="Fourier preconditioning of the first iterations: auto (default: "
                   "damping level 0.1 where it speeds the step up), off, or a level in (0, 1]")
    f.set_defaults(func=run_fista)
    a = methods.add_parser("admm", help="ADMM-TV (2d model, with or without a mask)")
    _add_tv_solver_arguments(a)
    a.add_argument("--rho", type=POSITIVE, default=0.01,
                   help="ADMM penalty relative to max|H|^2 (default 0.01)")
    a.set_defaults(func=run_admm)
    from app.commands.plan import register_auto
    from app.commands.recon_udn import register_udn

    register_udn(methods)
    register_auto(methods)


_KAPPA = finite_float(0, 1, lo_open=True)


def _precondition(text: str) -> str | float:
    """``--precondition``: auto, off or a damping level in (0, 1]."""
    if text in ("auto", "off"):
        return text
    try:
        return _KAPPA(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"must be auto, off or a number > 0 and <= 1, got {text!r}") from None


def _add_tv_solver_arguments(p: argparse.ArgumentParser) -> None:
    """Inputs, tau/iterations, tolerance, TV form and output: shared by fista and admm."""
    add_input_arguments(p)
    add_tau_arguments(p)
    p.add_argument("--tol", type=NONNEG, default=1e-5, help="stop on relative change (1e-5)")
    p.add_argument("--tv", choices=["iso", "aniso"], default="iso", help="2D TV form")
    p.add_argument("--out", required=True, help="output TIFF (previews are written beside it)")
    add_overwrite_option(p)


def add_input_arguments(p: argparse.ArgumentParser, *, float64: bool = True) -> None:
    """Inputs shared by every reconstruction method.

    ``float64``: offer ``--float64`` (the UDN's network runs in float32 or bf16, its
    ``--precision``).
    """
    p.add_argument("--model", choices=["2d", "video", "spectral", "depth"], default=None,
                   help="forward model: 2d, video (rolling shutter), spectral (filter "
                   "array), depth (PSF stack) (default: depth with --psf-stack, else 2d)")
    p.add_argument("--psf", help="PSF file (2d, video, spectral)")
    p.add_argument("--psf-stack", help="depth: multi-page TIFF, (K,H,W) array or a folder")
    p.add_argument("--meas", required=True, help="measurement file")
    p.add_argument("--mask", help="erasure / dead-pixel mask (1 = measured)")
    p.add_argument("--shutter", help="video: shutter function M (K, rows) (.npy/.npz/.tif)")
    p.add_argument("--filters", help="spectral: filter cube (K, H, W) (.npy/.npz/.mat/.tif)")
    p.add_argument("--downsample", type=POSITIVE_INT, default=1, help="box downsampling factor")
    p.add_argument("--dark", help="dark level: a number, 'auto' or a dark-frame file")
    p.add_argument("--psf-dark", help="dark level of the PSF: a number, 'auto' or a dark-frame "
                   "file (default: the --dark level; leave it out for a calibrated PSF file, "
                   "which is dark-subtracted already, or give 0)")
    p.add_argument("--rgb", action="store_true", help="reconstruct colour channels")
    p.add_argument("--field", default="sensor", help="scene field: sensor, full (2x) or HxW")
    if float64:
        p.add_argument("--float64", action="store_true", help="compute in float64")
    add_layout_arguments(p)


def model_kind(args: argparse.Namespace) -> str:
    """The model ``--model`` names, or, left out, the one the inputs imply.

    As ``recon auto`` and :func:`app.commands._inputs.problem_spec` infer it: depth for
    ``--psf-stack``, else 2d.
    """
    return str(getattr(args, "model", None) or ("depth" if getattr(args, "psf_stack", None)
                                                 else "2d"))


def load_problem(args: argparse.Namespace) -> Any:
    """Load and check the inputs named on the command line (:func:`recon.problem.load_problem`)."""
    import torch

    from recon.problem import load_problem as _load

    dtype = torch.float64 if getattr(args, "float64", False) else torch.float32
    return _load(problem_spec(args), dtype=dtype)


def run_fista(args: argparse.Namespace) -> int:
    """Run FISTA-TV and save the result with its metadata."""
    from recon.fista import Fista
    from recon.tv import TV

    kind = {"2d": "image", "video": "video", "spectral": "spectral",
            "depth": "depth"}[model_kind(args)]

    def make(model: Any, b: Any) -> tuple[Any, Any, int, dict[str, Any]]:
        tv = TV(isotropic=args.tv == "iso", weight_k=args.tv_k if model.k > 1 else 0.0)
        tau, iters, tau_meta = resolve_tau(args, model, b, tv)
        solver = Fista(model.op, b, tau=tau, tv=tv, max_iter=iters, tol=args.tol,
                       restart="none" if args.no_restart else "gradient",
                       prox_iters=args.prox_iters, precondition=args.precondition)
        return solver, tau, iters, tau_meta

    return _solve_and_save(args, "fista-tv", kind, make)


def run_admm(args: argparse.Namespace) -> int:
    """Run ADMM-TV and save the result with its metadata (tau auto: chosen as for FISTA)."""
    from recon.admm import Admm
    from recon.tv import TV

    if model_kind(args) != "2d":
        raise ValueError(f"recon admm handles --model 2d (with or without --mask), not "
                         f"{model_kind(args)}; use recon fista")

    def make(model: Any, b: Any) -> tuple[Any, Any, int, dict[str, Any]]:
        tv = TV(isotropic=args.tv == "iso")
        # the held-out search runs FISTA (same objective, so the same tau); ADMM's iteration
        # count is the limit unless given
        tau, iters, tau_meta = resolve_tau(args, model, b, tv, tau_only=True)
        solver = Admm(model, b, tau=tau, tv=tv, max_iter=iters, tol=args.tol, rho=args.rho)
        return solver, tau, iters, tau_meta

    return _solve_and_save(args, "admm-tv", "image", make)


def _solve_and_save(args: argparse.Namespace, method: str, kind: str,
                    make: Callable[[Any, Any], tuple[Any, Any, int, dict[str, Any]]]) -> int:
    """Load, solve and save: the one path of ``recon fista`` and ``recon admm``.

    ``make(model, b)`` builds the solver and returns ``(solver, tau, iterations, tau_meta)``;
    the run shows a progress bar, the result is saved with its metadata and a one-line JSON
    summary is printed.
    """
    import torch

    from recon.io import reconstruction_paths, save_reconstruction

    check_command_outputs(args, reconstruction_paths(args.out, kind))
    prob = load_problem(args)
    fit_command_threads(args, prob.model.scene_shape)  # small grids: one thread
    dtype = torch.float64 if args.float64 else torch.float32
    b = torch.as_tensor(prob.meas, dtype=dtype)
    solver, tau, iters, tau_meta = make(prob.model, b)
    bar = ProgressBar(iters, method.split("-")[0])
    t0 = time.perf_counter()
    last = None
    for step in solver.steps():
        last = step
        bar.update(step.iteration, f"objective {step.objective:.4g}")
    bar.close()
    wall = time.perf_counter() - t0
    _check_explains(solver, prob.model, b, method, prob.kind)
    meta = {
        "method": method, "model": prob.kind, "parameters": solver.params,
        "regularisation": tau_meta, "iterations": solver.iteration,
        "stop_reason": solver.reason.value if solver.reason else "max_iter",
        "wall_time_s": round(wall, 3), "tau_search_s": tau_search_s(tau_meta),
        "final": {"objective": last.objective, "residual": last.residual} if last else None,
        "inputs": {k: v["path"] for k, v in prob.inputs.items()},
        "input_hashes": {k: v for k, v in prob.hashes.items() if v is not None},
        "preprocessing": {**prob.metadata, "rgb": args.rgb},
    }
    paths = save_reconstruction(args.out, solver.x.float().cpu().numpy(), meta, kind=kind)
    summary = {"out": [str(p) for p in paths], "iterations": solver.iteration,
               "tau": tau, "tau_rule": tau_meta["tau_rule"],
               "stop_reason": meta["stop_reason"], "wall_time_s": meta["wall_time_s"],
               "tau_search_s": tau_search_s(tau_meta),
               "residual": last.residual if last else None}
    print(json.dumps(summary), file=sys.stdout)
    return 0


def _check_explains(solver: Any, model: Any, b: Any, method: str, kind: str = "2d") -> None:
    """Refuse a result that explains none of the measurement; warn at one a flat image beats.

    For a non-negative PSF and measurement a small constant image always beats 0, so a
    residual ||A x - b|| / ||b|| of 1 or more is a run that went nowhere (an extreme setting,
    such as an ADMM rho of 1e30, left x at about 0); it is not written.

    A constant image has no total variation, so the best one (a least-squares level c >= 0)
    is a point of the objective whose value is its data term alone: a solved problem's data
    residual is at most that constant's. A result above it has not got past a flat image (too
    few iterations, or an ADMM rho of 1e3 or more that holds x near 0); it is written, with a
    warning that says so.
    """
    import torch

    with torch.no_grad():
        x = solver.x.to(dtype=b.dtype)
        norm_b = float(torch.linalg.vector_norm(b))
        res = float(torch.linalg.vector_norm(model.op.apply(x) - b)) / norm_b
        a1 = model.op.apply(torch.ones_like(x))
        level = max(0.0, float((a1 * b).sum()) / max(float((a1 * a1).sum()), 1e-300))
        res_flat = float(torch.linalg.vector_norm(level * a1 - b)) / norm_b
    reason = solver.reason.value if solver.reason else "max_iter"
    extreme = ("--rho" if method.startswith("admm") else
               "--precondition" if kind == "2d" else "--tv-k, --precondition")
    if res >= 1.0:
        raise ValueError(
            f"{method}: the result explains none of the measurement (relative residual "
            f"{res:.6g} after {solver.iteration} iterations, stop reason {reason}; an all-zero "
            f"image does as well), nothing written; an extreme setting ({extreme}) can hold "
            "the solver at 0")
    if res > res_flat * (1 + 1e-3):
        print(f"lenslesscam recon: warning: {method}: the result explains the measurement less "
              f"well than a flat image (relative residual {res:.4g} against {res_flat:.4g} "
              f"after {solver.iteration} iterations, stop reason {reason}); it needs more "
              f"--iters, or a setting ({extreme}) holds the solver back", file=sys.stderr)
