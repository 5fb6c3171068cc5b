"""``lenslesscam bench NAME``: benchmarks that print a table (see BENCHMARKS)."""

from __future__ import annotations

import functools
import importlib
from collections.abc import Callable
from typing import Any

#: benchmark name -> module with ``add_arguments(parser)`` and ``run(args) -> int``
BENCHMARKS = {
    "fista": "benchmarks.bench_fista",
    "udn": "benchmarks.bench_udn",
    "protocol": "benchmarks.sim_protocol",
    "time-to-quality": "benchmarks.time_to_quality",
    "preview": "benchmarks.bench_preview",
    "plan": "benchmarks.plan_cases",
    "udn-video": "benchmarks.udn_video",
    "udn-vs-fista": "benchmarks.udn_vs_fista",
    "real-pairs": "benchmarks.real_pairs",
    "tau-rules": "benchmarks.tau_rules",
    "admm-penalty": "benchmarks.admm_penalty",
    "batch": "benchmarks.bench_batch",
}


def register(sub: Any) -> None:
    """Add ``bench`` with one subcommand per benchmark module that is importable."""
    p = sub.add_parser("bench", help="benchmarks (print tables)")
    which = p.add_subparsers(dest="bench", metavar="BENCHMARK", required=True)
    for name, module in BENCHMARKS.items():
        try:
            mod = importlib.import_module(module)
        except ImportError:
            continue
        summary = (mod.__doc__ or "").strip().splitlines()[0]
        # argparse %-formats help strings (a "99%" must reach it as "99%%"), not descriptions
        q = which.add_parser(name, help=summary.replace("%", "%%"),
                             description=summary + _duration(mod))
        mod.add_arguments(q)
        q.set_defaults(func=_terminate_as_interrupt(mod.run))


def _duration(mod: Any) -> str:
    """The default run's time a benchmark module states (its ``DURATION``), as a sentence."""
    text = getattr(mod, "DURATION", None)
    return f" Default run: {text}." if text else ""


def _terminate_as_interrupt(run: Callable[[Any], int]) -> Callable[[Any], int]:
    """``run`` with SIGTERM and SIGHUP raising KeyboardInterrupt, as Ctrl-C does.

    The CLI's handler (:class:`app.commands._common.TerminateAsInterrupt`): a benchmark stopped
    by ``kill``, ``timeout`` or a scheduler runs its ``finally`` clean-ups (its load processes,
    its worker pools, its camera) and exits 130, as on Ctrl-C.
    """

    @functools.wraps(run)
    def guarded(args: Any) -> int:
        from app.commands._common import TerminateAsInterrupt

        with TerminateAsInterrupt():
            return run(args)

    return guarded
