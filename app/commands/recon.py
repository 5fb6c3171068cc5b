"""``lenslesscam recon fista|udn``: reconstruct a measurement."""

from __future__ import annotations

import argparse
import json
import math
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
    integer,
)
from app.commands._tau import add_tau_arguments, resolve_tau, tau_search_s

#: the most inner TV iterations a step may be asked for: the automatic doubling stops at 48,
#: and 10^6 ran 49 s for two steps of an 18x25 image without a word
MAX_PROX_ITERS = 1000


def register(sub: Any) -> None:
    """Add ``recon`` and its methods."""
    p = sub.add_parser("recon", help="reconstruct a measurement (fista, admm, udn or auto)")
    methods = p.add_subparsers(dest="method", metavar="METHOD", required=True)
    f = methods.add_parser("fista", help="FISTA with total variation and non-negativity")
    _add_tv_solver_arguments(
        f, "stop when the relative change of the iterate falls below this (default 1e-5); "
        "with the default --prox-iters 3 the change can level off above it (on the tutorial "
        "sample at tau 1e-4 it hovers between 1e-4 and 3e-5 for thousands of iterations), so "
        "the run goes to --iters and its stop_detail says so; --prox-iters 20 converged there "
        "in 481 (a 90 %% erased case still levelled off at 8e-5 with 20)")
    f.add_argument("--tv-k", type=NONNEG, default=None,
                   help="weight of TV along k for video/spectral/depth (default 0.5; a 2d "
                        "model has no k: said and ignored)")
    f.add_argument("--prox-iters", type=integer(1, MAX_PROX_ITERS), default=3,
                   help="inner TV prox iterations per step (default 3; more cost more per step "
                   "and lower the floor of the relative change, see --tol); a step that raises "
                   "the objective 10 %% above its lowest doubles them, up to 48 (the metadata's "
                   "parameters.prox_iters_final)")
    f.add_argument("--no-restart", action="store_true",
                   help="disable the gradient restart of the (POGM) momentum")
    f.add_argument("--precondition", type=_precondition, default="auto",
                   help="Fourier preconditioning of the first iterations: auto (default: "
                   "damping level 0.1 where it speeds the step up), off, or a level in (0, 1]")
    f.set_defaults(func=run_fista)
    a = methods.add_parser("admm", help="ADMM-TV (2d model, with or without a mask)")
    _add_tv_solver_arguments(
        a, "stop when the relative change of v and the residuals of ADMM's splittings (M v = "
        "x, D v = u, v = w, relative to ||M v|| and ||v||) are all below this (default 1e-5)",
        only_2d="recon admm")
    a.add_argument("--rho", type=POSITIVE, default=0.01,
                   help="the TV and non-negativity penalties relative to max|H|^2 times the "
                   "data penalty (default 0.01)")
    a.add_argument("--penalty", type=_penalty, default="auto",
                   help="the data penalty (the scale of all three): auto (default: from tau "
                   "and the measured share of the sensor, recon.admm.penalty_scale) or a "
                   "number > 0 (1: the fixed penalty before)")
    a.set_defaults(func=run_admm)
    from app.commands.plan import register_auto
    from app.commands.recon_udn import register_udn

    register_udn(methods)
    register_auto(methods)


_KAPPA = finite_float(0, 1, lo_open=True)


def _penalty(text: str) -> str | float:
    """``--penalty``: auto or a number > 0."""
    return "auto" if text == "auto" else POSITIVE(text)


def _precondition(text: str) -> str | float:
    """``--precondition``: auto, off or a damping level in (0, 1]."""
    if text in ("auto", "off"):
        return text
    try:
        return _KAPPA(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"must be auto, off or a number > 0 and <= 1, got {text!r}") from None


def _add_tv_solver_arguments(p: argparse.ArgumentParser, tol_help: str,
                             only_2d: str | None = None) -> None:
    """Inputs, tau/iterations, tolerance, TV form and output: shared by fista and admm."""
    add_input_arguments(p, only_2d=only_2d)
    add_tau_arguments(p)
    p.add_argument("--tol", type=NONNEG, default=1e-5, help=tol_help)
    p.add_argument("--tv", choices=["iso", "aniso"], default="iso", help="2D TV form")
    p.add_argument("--out", required=True, help="output TIFF (previews are written beside it)")
    add_overwrite_option(p)


def _only_2d(command: str) -> Callable[[str], str]:
    """``--model`` of a command that handles the 2d model alone (2d, or a refusal).

    The refusal says where the other models are reconstructed.
    """

    def parse(text: str) -> str:
        if text == "2d":
            return text
        others = ("video", "spectral", "depth")
        if text in others:
            raise argparse.ArgumentTypeError(f"{command} handles the 2d model only, not "
                                             f"{text}; use recon fista (or recon udn)")
        raise argparse.ArgumentTypeError(f"must be 2d (recon fista also takes "
                                         f"{', '.join(others)}), got {text!r}")
    return parse


def add_input_arguments(p: argparse.ArgumentParser, *, float64: bool = True,
                        only_2d: str | None = None) -> None:
    """Inputs shared by every reconstruction method.

    ``float64``: offer ``--float64`` (the UDN's network runs in float32 or bf16, its
    ``--precision``). ``only_2d``: the name of a command that handles the 2d model alone
    (``recon admm``): its ``--model`` takes 2d, and its help lists neither the other models nor
    their inputs (``--psf-stack``, ``--shutter``, ``--filters`` stay, unlisted, so that a
    stack given is named with the model it implies).
    """
    if only_2d:
        p.add_argument("--model", type=_only_2d(only_2d), default=None, metavar="2d",
                       help="forward model: 2d, the only one this method handles (recon "
                       "fista takes video, spectral and depth too)")
    else:
        p.add_argument("--model", choices=["2d", "video", "spectral", "depth"], default=None,
                       help="forward model: 2d, video (rolling shutter), spectral (filter "
                       "array), depth (PSF stack) (default: depth with --psf-stack, else 2d)")
    hide = argparse.SUPPRESS if only_2d else None
    p.add_argument("--psf", help="PSF file" if only_2d else "PSF file (2d, video, spectral)")
    p.add_argument("--psf-stack",
                   help=hide or "depth: multi-page TIFF, (K,H,W) array or a folder")
    p.add_argument("--meas", required=True, help="measurement file")
    p.add_argument("--mask", help="erasure / dead-pixel mask (1 = measured)")
    p.add_argument("--shutter",
                   help=hide or "video: shutter function M (K, rows) (.npy/.npz/.tif)")
    p.add_argument("--filters",
                   help=hide or "spectral: filter cube (K, H, W) (.npy/.npz/.mat/.tif)")
    p.add_argument("--downsample", type=POSITIVE_INT, default=1, help="box downsampling factor")
    from app.commands._inputs import add_dark_arguments

    add_dark_arguments(p)
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
        if args.tv_k is not None and model.k == 1:  # it was ignored without a word
            print(f"recon fista: warning: --tv-k {args.tv_k:g} weighs TV along k, which a "
                  "model with one frame (K = 1) does not have: ignored", file=sys.stderr)
        weight_k = 0.5 if args.tv_k is None else args.tv_k
        tv = TV(isotropic=args.tv == "iso", weight_k=weight_k if model.k > 1 else 0.0)
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
        solver = Admm(model, b, tau=tau, tv=tv, max_iter=iters, tol=args.tol, rho=args.rho,
                      penalty=args.penalty)
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
    changes: list[float] = []
    for step in solver.steps():
        last = step
        changes.append(step.rel_change)
        bar.update(step.iteration, f"objective {step.objective:.4g}")
    bar.close()
    wall = time.perf_counter() - t0
    _check_explains(solver, prob.model, b, method, prob.kind)
    stop_reason = solver.reason.value if solver.reason else "max_iter"
    prox_iters = getattr(solver, "prox_iters", None)  # FISTA's, as the run ended (may grow)
    detail = plateau_detail(changes, args.tol, method, prox_iters
                            ) if stop_reason == "max_iter" else None
    meta = {
        "method": method, "model": prob.kind, "parameters": solver.params,
        "regularisation": tau_meta, "iterations": solver.iteration,
        "stop_reason": stop_reason, **({"stop_detail": detail} if detail else {}),
        "wall_time_s": round(wall, 3), "tau_search_s": tau_search_s(tau_meta),
        "final": {"objective": last.objective, "residual": last.residual} if last else None,
        "inputs": {k: v["path"] for k, v in prob.inputs.items()},
        "input_hashes": {k: v for k, v in prob.hashes.items() if v is not None},
        "preprocessing": {**prob.metadata, "rgb": args.rgb},
    }
    paths = save_reconstruction(args.out, solver.x.float().cpu().numpy(), meta, kind=kind)
    summary = {"out": [str(p) for p in paths], "iterations": solver.iteration,
               "tau": tau, "tau_rule": tau_meta["tau_rule"],
               "stop_reason": meta["stop_reason"], **({"stop_detail": detail} if detail else {}),
               "wall_time_s": meta["wall_time_s"],
               "tau_search_s": tau_search_s(tau_meta),
               "residual": last.residual if last else None}
    print(json.dumps(summary), file=sys.stdout)
    return 0


def plateau_detail(changes: list[float], tol: float, method: str,
                   prox_iters: int | None = None) -> str | None:
    """One line when a run that stopped at its iteration limit had its change level off above tol.

    ``changes``: the relative change of every iteration. Levelled off: over the last half of
    a run of at least 100 iterations, the median change of the last quarter is above ``tol``
    and above 0.8 times that of the quarter before (a change still falling as 1/k drops to
    0.71 of it, as 1/k^2 to 0.51). None otherwise, and for ``tol`` 0 (no tolerance to reach).
    """
    import statistics

    n = len(changes)
    if tol <= 0 or n < 100:
        return None
    q = n // 4
    last = statistics.median(changes[-q:])
    before = statistics.median(changes[-2 * q:-q])
    if not (math.isfinite(last) and last > tol and last > 0.8 * before):
        return None
    why = (f"FISTA's inexact TV prox ({prox_iters} inner iterations) sets that floor: more --iters "
           f"will not reach --tol; more --prox-iters (for example {max(20, 2 * prox_iters)}) "
           "lower it"
           if method.startswith("fista") else "more --iters may not reach --tol")
    return (f"the relative change levelled off near {last:.2g} (median of the last {q} "
            f"iterations; {before:.2g} in the {q} before), above --tol {tol:g}: {why}")


def _check_explains(solver: Any, model: Any, b: Any, method: str, kind: str = "2d") -> None:
    """:func:`check_explains` for the result of a ``recon fista`` / ``recon admm`` solver."""
    admm = method.startswith("admm")
    k1 = getattr(model, "k", 1) == 1  # one frame: no TV along k to weigh
    extreme = ("--penalty, --rho" if admm else
               "--precondition" if kind == "2d" or k1 else "--tv-k, --precondition")
    objective_hint = (
        "ADMM's fixed penalty enforces a large tau slowly (its splitting D v = u holds only in "
        "the limit, and tau multiplies what is left of it): raise --penalty or --rho (at tau 1e6 "
        "on the tutorial sample rho 1 left a spread of 0.02 % of the mean, 0.01 one of 79 %) "
        "or --iters (or lower --tol), or use recon fista" if admm else
        "at a large tau FISTA's inexact TV prox can keep it from settling (its inner "
        "iterations grow by themselves up to 48, or --prox-iters if larger): raise "
        f"--prox-iters or --iters, or a setting ({extreme}) holds the solver back")
    check_explains(
        solver.x, model, b, method=method, iterations=solver.iteration,
        reason=solver.reason.value if solver.reason else "max_iter",
        tau=float(solver.tau), tv=solver.tv,
        refuse_hint=f"an extreme setting ({extreme}) can hold the solver at 0",
        flat_hint=f"it needs more --iters, or a setting ({extreme}) holds the solver back",
        objective_hint=objective_hint)


#: a relative residual this far above a flat image's, or less, is not reported: within the
#: solvers' convergence and round-off (a 1-pixel grid's results, "converged" at tol 1e-5, sat
#: 3e-6 (FISTA) and 8e-6 (ADMM) above the exact flat fit, in float32 and in float64 alike)
RESIDUAL_SLACK = 1e-4


def check_explains(x: Any, model: Any, b: Any, *, method: str, iterations: int, reason: str,
                   tau: float | None = None, tv: Any = None, refuse_hint: str,
                   flat_hint: str, objective_hint: str | None = None,
                   who: str = "lenslesscam recon") -> None:
    """Refuse a result that explains none of the measurement; warn at one a flat image beats.

    The one check of every reconstruction command (``recon fista``, ``recon admm``,
    ``recon auto``) on its result ``x`` for the forward model ``model`` and measurement ``b``.

    For a non-negative PSF and measurement a small constant image always beats 0, so a
    residual ||A x - b|| / ||b|| of 1 or more is a run that went nowhere (an extreme setting,
    such as an ADMM rho of 1e30, left x at about 0); it is not written: ValueError naming
    ``refuse_hint``.

    A constant image has no total variation, so the best one (a least-squares level c >= 0)
    is a point of the objective whose value is its data term alone: a solved problem's data
    residual, and its objective 0.5 ||A x - b||^2 + tau TV(x), are at most that constant's.
    A result whose residual is above it has not got past a flat image (too few iterations,
    or an ADMM rho of 1e3 or more that holds x near 0): a warning with ``flat_hint``. A result
    whose residual is below it but whose objective is above (with ``tau`` and ``tv``) has not
    minimised its objective (ADMM at a huge tau: a non-flat image where the minimum is
    flat): a warning with ``objective_hint``. Both are written. Differences within 0.1 % of
    the flat image's value, or within the solvers' convergence and round-off
    (``RESIDUAL_SLACK`` of ||b||), are not reported.
    """
    import torch

    with torch.no_grad():
        x = x.to(dtype=b.dtype)
        norm_b = max(float(torch.linalg.vector_norm(b)), 1e-300)
        r = model.op.apply(x) - b
        res = float(torch.linalg.vector_norm(r)) / norm_b
        a1 = model.op.apply(torch.ones_like(x))
        level = max(0.0, float((a1 * b).sum()) / max(float((a1 * a1).sum()), 1e-300))
        res_flat = float(torch.linalg.vector_norm(level * a1 - b)) / norm_b
    floor = RESIDUAL_SLACK
    its = f"{iterations} iteration{'s' if iterations != 1 else ''}"
    if res >= 1.0:
        raise ValueError(
            f"{method}: the result explains none of the measurement (relative residual "
            f"{res:.6g} after {its}, stop reason {reason}; an all-zero "
            f"image does as well), nothing written; {refuse_hint}")
    if res > res_flat * (1 + 1e-3) + floor:
        print(f"{who}: warning: {method}: the result explains the measurement less "
              f"well than a flat image (relative residual {res:.4g} against {res_flat:.4g} "
              f"after {its}, stop reason {reason}); {flat_hint}",
              file=sys.stderr)
        return
    if tau is None or tv is None or tau <= 0 or objective_hint is None:
        return
    # objectives over 0.5 ||b||^2: the data terms are half the squared relative residuals
    obj = 0.5 * res * res + tau * float(tv.value(x)) / (norm_b * norm_b)
    obj_flat = 0.5 * res_flat * res_flat
    if obj > obj_flat * (1 + 1e-3) + 0.5 * floor * floor:
        scale = norm_b * norm_b
        print(f"{who}: warning: {method}: the result has not minimised its objective "
              f"0.5 ||A x - b||^2 + tau TV(x): {obj * scale:.4g} against {obj_flat * scale:.4g} "
              f"for a flat image (which has no TV), at tau {tau:.3g} after {its}, stop reason "
              f"{reason}; {objective_hint}", file=sys.stderr)
