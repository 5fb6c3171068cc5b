"""``--tau`` / ``--iters`` with ``auto`` defaults, shared by every reconstruction command.

``auto`` (the default) chooses from the measurement alone (:mod:`recon.autotau`, held-out
measured pixels); a number is used exactly. The choice and its rule are printed on stderr and
returned as metadata for the result file.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from app.commands._options import POSITIVE_INT


def tau_type(text: str) -> float | None:
    """``type=`` for ``--tau``: ``auto`` (None) or a finite number >= 0."""
    from recon.autotau import parse_tau

    try:
        return parse_tau(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("tau ")) from None


def iters_type(text: str) -> int | None:
    """``type=`` for ``--iters``: ``auto`` (None) or an integer >= 1 (``POSITIVE_INT``).

    At most 2**62 in magnitude, as every integer option.
    """
    if text.strip().lower() == "auto":
        return None
    try:
        return int(POSITIVE_INT(text))
    except argparse.ArgumentTypeError as exc:
        raise argparse.ArgumentTypeError(f"must be 'auto' or {str(exc)[len('must be '):]}"
                                         ) from None


def add_tau_arguments(p: argparse.ArgumentParser, *, iters: bool = True) -> None:
    """``--tau`` (default auto) and, with ``iters``, ``--iters`` (default auto)."""
    p.add_argument("--tau", type=tau_type, default=None, metavar="TAU|auto",
                   help="TV weight; 'auto' (default) chooses it from held-out measured pixels")
    if iters:
        p.add_argument("--iters", type=iters_type, default=None, metavar="N|auto",
                       help="iterations; 'auto' (default): where the held-out error starts "
                       "to rise at the chosen tau, else 500")


def resolve_tau(args: argparse.Namespace, model: Any, b: Any, tv: Any = None,
                *, tau_only: bool = False) -> tuple[float, int, dict[str, Any]]:
    """(tau, iterations, metadata) for this command line; prints the automatic choice.

    ``tau_only``: the iteration count is not chosen here (the solver is not FISTA): with
    ``--iters auto`` it is the automatic search's limit.
    """
    from recon.autotau import AUTO_MAX_ITER, resolve

    tau = args.tau
    iters = getattr(args, "iters", None)
    if tau_only and iters is None:
        if tau is not None:
            return tau, AUTO_MAX_ITER, {"tau": tau, "tau_rule": "given",
                                        "iterations": AUTO_MAX_ITER, "iterations_rule": "limit"}
        # the limit passed as given: the same search (its limit is AUTO_MAX_ITER either way),
        # and a refusal that asks for --tau alone, the one setting this solver takes from it
        tau, _, meta = resolve(model, b, None, AUTO_MAX_ITER, tv=tv,
                               log=lambda s: print(s, file=sys.stderr),
                               iterations_why="the limit: the search's count is FISTA's, "
                               "this solver stops on its own tolerance")
        meta.update(iterations=AUTO_MAX_ITER, iterations_rule="limit")
        return tau, AUTO_MAX_ITER, meta
    return resolve(model, b, tau, iters, tv=tv, log=lambda s: print(s, file=sys.stderr),
                   precondition=getattr(args, "precondition", "auto"),
                   iterations_why="--iters as given")


def tau_search_s(tau_meta: dict[str, Any]) -> float | None:
    """Seconds the automatic tau's search took (None: tau and iterations were given).

    Reported beside ``wall_time_s``, which is the reconstruction alone in every command.
    """
    auto = tau_meta.get("auto")
    cost = auto.get("cost_s") if isinstance(auto, dict) else None
    return None if cost is None else round(float(cost), 3)
