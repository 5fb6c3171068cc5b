"""``lenslesscam bench NAME``: benchmarks that print a table (see BENCHMARKS)."""

from __future__ import annotations

import importlib
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
        # argparse %-formats help strings: a "99%" in a docstring must reach it as "99%%"
        summary = (mod.__doc__ or "").strip().splitlines()[0].replace("%", "%%")
        q = which.add_parser(name, help=summary, description=summary)
        mod.add_arguments(q)
        q.set_defaults(func=mod.run)
