"""ADMM-TV's penalty: the automatic scale against the former fixed one, by distance to the minimum.

ADMM and FISTA minimise the same objective, so a solver setting is judged by how near its
result comes to the minimum in a given number of iterations, not by a truth. Each case: tau
from the automatic search (``recon.autotau.choose_tau``, as ``recon admm`` takes it); the
minimum's objective from FISTA-TV at 3000 iterations (or the lowest any run below reached, where
one went lower); then FISTA-TV and ADMM-TV with the penalty scale of
``recon.admm.penalty_scale`` (``auto``) and with the former fixed scale 1, each scored at 100,
200 and 500 iterations: the objective of the returned estimate over the minimum's, minus 1,
and the PSNR against the truth (after a gain fit), which the scale does not aim at but a user
sees.

Cases as ``bench tau-rules``: ``real`` the four real DiffuserCam pairs of ``../shared/data/dlmd``
at 1/4 resolution in colour, ``sim`` the simulation protocol (tutorial PSF at 1/8 scale, the
three lensed scenes, noise 0 and 0.01), at the erasure levels given.

    lenslesscam bench admm-penalty [--cases real sim] [--erasures 0 0.5 0.9 0.95 0.99]
        [--out FILE]
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

from app.commands._options import FRACTION, POSITIVE_INT, add_overwrite_option
from benchmarks._cli import (
    append_jsonl,
    bench_threads,
    check_outputs,
    machine_text,
    print_and_write,
    read_records,
    tagged,
)

#: version of the records of ``--results`` (format ``lenslesscam.bench.admm-penalty``)
RESULTS_VERSION = 1
#: the keys every record of ``--results`` has
REQUIRED = ("case", "erasure", "tau", "penalty", "reference", "fista", "admm_auto", "admm_fixed")

#: iterations at which each run is scored
MARKS = (100, 200, 500)
#: FISTA-TV iterations of the reference minimum
REFERENCE_ITERS = 3000


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of ``lenslesscam bench admm-penalty``."""
    p.add_argument("--cases", nargs="+", choices=["real", "sim"], default=["real", "sim"],
                   help="real DiffuserCam pairs and/or the simulation protocol (both)")
    p.add_argument("--erasures", nargs="+", type=FRACTION, default=[0.0, 0.5, 0.9, 0.95, 0.99],
                   help="erasure levels (0 0.5 0.9 0.95 0.99)")
    p.add_argument("--threads", type=POSITIVE_INT, default=None,
                   help="torch threads (default: the global --threads, else the thread "
                   "policy, recon.threads)")
    p.add_argument("--data", default=None, help="the dlmd folder (default: the shared one)")
    p.add_argument("--results", default=None,
                   help="also append each case as JSON lines here; the cases it already holds "
                   "(same settings) are not run again")
    p.add_argument("--out", default=None, help="write the Markdown table here")
    p.add_argument("--table-only", action="store_true",
                   help="run nothing: make the table from the cases in --results")
    add_overwrite_option(p)


def objective(model: Any, b: Any, x: Any, tau: float) -> float:
    """0.5 ||mask (A x - b)||^2 + tau TV(x): the objective both solvers minimise."""
    from recon.tv import TV

    r = model.op.apply(x) - b
    if model.mask is not None:
        r = r * model.mask
    return 0.5 * float((r.double() ** 2).sum()) + tau * TV().value(x)


def _scored(solver: Any, model: Any, b: Any, truth: Any, tau: float, ref: float
            ) -> dict[str, list[float]]:
    """Run ``solver`` to the last mark; objective over ``ref`` minus 1 and PSNR at each mark."""
    from benchmarks.real_pairs import psnr_only

    out: dict[str, list[float]] = {"gap": [], "psnr": []}
    for step in solver.steps():
        if step.iteration in MARKS:
            x = solver.x.detach()
            out["gap"].append(objective(model, b, x, tau) / ref - 1)
            out["psnr"].append(psnr_only(truth, x.numpy()))
    return out


RUNS = ("fista", "admm_auto", "admm_fixed")


def rereference(row: dict[str, Any]) -> dict[str, Any]:
    """The gaps against the lowest objective seen, where a run went below FISTA-TV's 3000th
    iteration (its inexact TV prox can leave it above the minimum at a large tau); ``reference``
    becomes that objective. A row already so referenced is returned unchanged."""
    lowest = min(0.0, *(g for k in RUNS for g in row[k]["gap"]))
    if lowest == 0.0:
        return row
    out = {**row, "reference": row["reference"] * (1 + lowest),
           "reference_note": f"a run went {-lowest:.2g} below FISTA-TV's 3000th iteration"}
    for k in RUNS:
        out[k] = {**row[k], "gap": [(1 + g) / (1 + lowest) - 1 for g in row[k]["gap"]]}
    return out


def run_case(model: Any, b: Any, truth: Any) -> dict[str, Any]:
    """tau, the reference minimum and the three runs of one case."""
    from recon.admm import Admm
    from recon.autotau import choose_tau
    from recon.fista import Fista

    tau = float(choose_tau(model, b).tau)
    ref_run = Fista(model.op, b, tau=tau, max_iter=REFERENCE_ITERS, tol=0.0)
    ref_run.run()
    ref = objective(model, b, ref_run.x.detach(), tau)
    last = max(MARKS)
    auto = Admm(model, b, tau=tau, max_iter=last, tol=0.0)
    row: dict[str, Any] = {"tau": tau, "reference": ref, "penalty": auto.penalty}
    row["fista"] = _scored(Fista(model.op, b, tau=tau, max_iter=last, tol=0.0), model, b, truth,
                           tau, ref)
    row["admm_auto"] = _scored(auto, model, b, truth, tau, ref)
    row["admm_fixed"] = _scored(Admm(model, b, tau=tau, max_iter=last, tol=0.0, penalty=1.0),
                                model, b, truth, tau, ref)
    return rereference(row)


def table(rows: list[dict[str, Any]]) -> str:
    """Per-case rows, then means per case kind and erasure level."""
    import numpy as np

    def cell(r: dict[str, Any], key: str, i: int) -> str:
        return f"{r[key]['gap'][i]:.2g} / {r[key]['psnr'][i]:.2f}"

    head = ["case", "tau", "penalty (auto)"] + [
        f"{name}, {m} it: gap / PSNR" for name in ("FISTA-TV", "ADMM auto", "ADMM fixed 1")
        for m in MARKS[1:]]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    rows = [rereference(r) for r in {r["case"]: r for r in rows}.values()]  # a case once
    for r in rows:
        cells = [cell(r, key, i) for key in RUNS
                 for i in range(1, len(MARKS))]
        lines.append(f"| {r['case']} | {r['tau']:.2g} | {r['penalty']:.3g} | "
                     + " | ".join(cells) + " |")
    lines += ["", "Mean PSNR (dB) at 500 iterations and median gap (objective over the minimum's, "
              "minus 1) per kind and erasure level:", "",
              "| cases | n | FISTA-TV | ADMM auto | ADMM fixed 1 | gap FISTA-TV | gap ADMM auto | "
              "gap ADMM fixed 1 |", "|---|---|---|---|---|---|---|---|"]
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        kind = r["case"].split()[0]
        noise = " noise-free" if r["case"].endswith("noise 0") else ""
        groups.setdefault(f"{kind}{noise} {r['erasure']:.0%}", []).append(r)
    for name, rs in groups.items():
        psnr = [float(np.mean([r[k]["psnr"][-1] for r in rs])) for k in RUNS]
        gap = [float(np.median([r[k]["gap"][-1] for r in rs])) for k in RUNS]
        lines.append(f"| {name} | {len(rs)} | " + " | ".join(f"{p:.2f}" for p in psnr) + " | "
                     + " | ".join(f"{g:.2g}" for g in gap) + " |")
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    """Run the cases and print the table."""
    from benchmarks.tau_rules import _cases, labels, resumed

    if args.table_only:
        if not args.results:
            raise ValueError("--table-only needs --results (the cases to tabulate)")
        if args.threads is not None:
            raise ValueError("--table-only makes the table of the cases in --results as they "
                             "ran: --threads cannot apply to them")
        check_outputs(args, {"--out": args.out}, inputs={"--results": args.results})
        wanted = set(labels(args))  # --cases and --erasures choose the cases of the table
        rows = [r for r in read_records(args.results, "--results", "admm-penalty",
                                        RESULTS_VERSION, REQUIRED) if r["case"] in wanted]
        if not rows:
            print(f"lenslesscam bench: error: no results in {args.results} for these --cases "
                  "and --erasures", file=sys.stderr)
            return 1
        text = (f"ADMM-TV's penalty scale, automatic (recon.admm.penalty_scale) against the "
                f"former fixed 1; the cases of {args.results}\n\n" + table(rows))
        print_and_write(text, args.out)
        return 0
    check_outputs(args, {"--out": args.out}, appended={"--results": args.results},
                  inputs={"--data": args.data})
    choice = bench_threads(args)
    settings = {"reference_iters": REFERENCE_ITERS, "marks": list(MARKS),
                "threads": choice.threads}
    wanted = labels(args)
    done = {k: v for k, v in resumed(args, "admm-penalty", REQUIRED, settings,
                                          RESULTS_VERSION).items()
            if k in wanted}
    t0 = time.perf_counter()
    for label, model, b, truth in _cases(args, skip=set(done)):
        erasure = float(label.split("%")[0].split()[-1]) / 100
        row = {"case": label, "erasure": erasure, **run_case(model, b, truth),
               "settings": settings}
        done[label] = row
        print(f"{label}: tau {row['tau']:.2g}, penalty {row['penalty']:.3g}; PSNR at "
              f"{MARKS[-1]}: FISTA {row['fista']['psnr'][-1]:.2f}, ADMM auto "
              f"{row['admm_auto']['psnr'][-1]:.2f}, fixed {row['admm_fixed']['psnr'][-1]:.2f} dB",
              file=sys.stderr, flush=True)
        append_jsonl(args.results, tagged("admm-penalty", RESULTS_VERSION, row))
    rows = [done[k] for k in wanted if k in done]
    text = (f"ADMM-TV's penalty scale, automatic (recon.admm.penalty_scale) against the former "
            f"fixed 1; tau from the automatic search; the minimum from FISTA-TV at "
            f"{REFERENCE_ITERS} iterations or the lowest objective a run reached; "
            f"{time.perf_counter() - t0:.0f} s ({len(rows)} cases). "
            f"{machine_text(choice)}\n\n" + table(rows))
    print_and_write(text, args.out)
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    add_arguments(parser)
    sys.exit(run(parser.parse_args()))
