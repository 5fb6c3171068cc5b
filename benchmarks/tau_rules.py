"""The automatic tau's two rules side by side: smallest held-out error against one standard error.

Both picks come from one :func:`recon.autotau.choose_tau` search per case (the same held-out
pixels, the same taus tried). ``min`` takes the tau of the smallest held-out error; ``1se``
(the default) the largest tau, going up from it, whose held-out error is within one standard
error of the minimum's (paired over the held-out pixels, the held-out blocks as the sampling
unit: the "one-standard-error rule" of cross-validation, which prefers the more regularised
setting the held-out data cannot tell apart from the best). ``--block N`` sets the side of
the held-out blocks (``recon.holdout``; 1: single scattered pixels, the design before). Each
case: both choices, FISTA-TV from all measured pixels with each (its tau and iteration count),
and an oracle grid of taus at the iteration limit, scored against the truth (PSNR after a
least-squares gain fit).

Cases: ``real`` the four real DiffuserCam pairs of ``../shared/data/dlmd`` at 1/4 resolution in
colour (as ``bench real-pairs`` reads them), ``sim`` the simulation protocol (tutorial PSF at
1/8 scale, the three lensed scenes, noise 0 and 0.01), at the erasure levels given.

    lenslesscam bench tau-rules [--cases real sim] [--erasures 0 0.5 0.9 0.99] [--block N]
        [--out FILE]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Iterator
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

#: version of the records of ``--results`` (format ``lenslesscam.bench.tau-rules``)
RESULTS_VERSION = 1
#: the keys every record of ``--results`` has
REQUIRED = ("case", "min", "1se", "oracle", "block", "settings")

GRID = (1e-7, 1e-6, 3e-6, 1e-5, 3e-5, 1e-4, 3e-4, 1e-3)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of ``lenslesscam bench tau-rules``."""
    p.add_argument("--cases", nargs="+", choices=["real", "sim"], default=["real", "sim"],
                   help="real DiffuserCam pairs and/or the simulation protocol (both)")
    p.add_argument("--erasures", nargs="+", type=FRACTION, default=[0.0, 0.5, 0.9, 0.99],
                   help="erasure levels (0 0.5 0.9 0.99)")
    p.add_argument("--iters", type=POSITIVE_INT, default=500,
                   help="iteration limit of the search and the oracle grid (500, the default)")
    p.add_argument("--block", type=POSITIVE_INT, default=None,
                   help="side in pixels of the held-out blocks (default: recon.holdout's, 4 px "
                   "on sensors of 32 to 159 px, 1/32 of the shorter side above; 1: single "
                   "pixels, the search before blocks); at most the side at which the held-out "
                   "10 %% of the pixels span 2 blocks (38 px on sim's 150x200)")
    p.add_argument("--threads", type=POSITIVE_INT, default=None,
                   help="torch threads (default: the global --threads, else the thread "
                   "policy, recon.threads)")
    p.add_argument("--data", default=None, help="the dlmd folder (default: the shared one)")
    p.add_argument("--results", default=None,
                   help="also append each case as JSON lines here; the cases it already holds "
                   "(same settings) are not run again")
    p.add_argument("--out", default=None, help="write the Markdown table here")
    add_overwrite_option(p)


def _sensor_shapes(args: argparse.Namespace) -> dict[str, tuple[int, int]]:
    """(H, W) of the sensor of each kind of case run (cheap: no model is built)."""
    shapes: dict[str, tuple[int, int]] = {}
    if "real" in args.cases:
        from benchmarks import real_pairs as rp

        name = rp.PAIRS[0]
        pair = rp.load_pair(name, rp.pair_files(name, rp.data_dir(args.data)), 4)
        shapes["real"] = tuple(pair.truth.shape[1:])  # type: ignore[assignment]
    if "sim" in args.cases:
        from recon import samples

        shapes["sim"] = tuple(samples.tutorial_psf().shape[-2:])  # type: ignore[assignment]
    return shapes


def block_limit(h: int, w: int) -> int:
    """The largest ``--block`` side on an ``h`` x ``w`` sensor: the held-out share of the pixels
    (choose_tau's ``holdout``, 10 %) must span at least 2 blocks, or the held-out error has no
    standard error (one block: infinite, and the 1se rule takes the largest tau) and a block
    the size of the sensor holds out everything."""
    import inspect

    from recon.autotau import choose_tau

    holdout = float(inspect.signature(choose_tau).parameters["holdout"].default)
    return max(1, math.isqrt(int(holdout * h * w / 2)))


def check_block(block: int | None, shapes: dict[str, tuple[int, int]]) -> None:
    """Refuse a ``--block`` side larger than a sensor run allows (:func:`block_limit`)."""
    if block is None:
        return
    for kind, (h, w) in shapes.items():
        limit = block_limit(h, w)
        if block > limit:
            raise ValueError(
                f"--block {block} is larger than the {kind} cases' {h}x{w} sensor allows: at "
                f"most {limit} px (the held-out 10 % of the pixels must span 2 blocks or more)")


def erasures(args: argparse.Namespace) -> list[float]:
    """``--erasures``, each once (a repeat would run, and count, the same cases twice)."""
    return list(dict.fromkeys(args.erasures))


def labels(args: argparse.Namespace) -> list[str]:
    """The labels of the cases :func:`_cases` yields, in its order (nothing is loaded)."""
    from benchmarks.real_pairs import PAIRS
    from recon import samples

    out = []
    if "real" in args.cases:
        out += [f"real {name} {er:.0%}" for name in PAIRS for er in erasures(args)]
    if "sim" in args.cases:
        out += [f"sim {name} {er:.0%} noise {noise:g}" for noise in (0.0, 0.01)
                for er in erasures(args) for name in samples.lensed_scene_names()]
    return out


def _cases(args: argparse.Namespace, skip: frozenset[str] | set[str] = frozenset()
           ) -> Iterator[tuple[str, Any, Any, Any]]:
    """(label, model, measurement, truth) of every case but those labelled in ``skip``."""
    import numpy as np
    import torch

    from recon.models import build_model

    if "real" in args.cases and any(x.startswith("real ") and x not in skip
                                    for x in labels(args)):
        from benchmarks import real_pairs as rp

        folder = rp.data_dir(args.data)
        for name in rp.PAIRS:
            if all(f"real {name} {er:.0%}" in skip for er in erasures(args)):
                continue
            pair = rp.load_pair(name, rp.pair_files(name, folder), 4)
            h, w = pair.truth.shape[1:]
            for er in erasures(args):
                if f"real {name} {er:.0%}" in skip:
                    continue
                mask = rp.sensor_mask(pair, er)
                b = (pair.meas * mask).astype(np.float32)
                yield (f"real {name} {er:.0%}", build_model("2d", pair.psf, mask=mask,
                                                            field=(h, w)),
                       torch.as_tensor(b), pair.truth)
    if "sim" in args.cases:
        from recon import samples
        from recon.simulate import simulate

        psf = samples.tutorial_psf()
        for noise in (0.0, 0.01):
            for er in erasures(args):
                for name in samples.lensed_scene_names():
                    if f"sim {name} {er:.0%} noise {noise:g}" in skip:
                        continue
                    sim = simulate(build_model("2d", psf), samples.lensed_scene(name),
                                   erasure=er, noise=noise, seed=0)
                    yield (f"sim {name} {er:.0%} noise {noise:g}",
                           build_model("2d", psf, mask=sim.mask), torch.as_tensor(sim.meas),
                           sim.truth)


def _psnr(model: Any, b: Any, truth: Any, tau: float, iters: int) -> float:
    from benchmarks.real_pairs import psnr_only
    from recon.fista import Fista

    s = Fista(model.op, b, tau=tau, max_iter=iters, tol=0.0)
    s.run()
    return psnr_only(truth, s.x.detach().numpy())


def run_case(model: Any, b: Any, truth: Any, iters: int, block: int | None = None
             ) -> dict[str, Any]:
    """Both rules' picks (one search), their reconstructions and the oracle grid on one case."""
    from recon.autotau import choose_tau

    t0 = time.perf_counter()
    c = choose_tau(model, b, max_iter=iters, min_iter=min(100, iters),  # as `resolve` does
                   patience=max(min(100, iters), 10), check_every=min(10, iters), block=block)
    search_s = round(time.perf_counter() - t0, 2)
    st = c.settings
    picks = {"min": (st["tau_min_error"], st["iterations_min_error"]),
             "1se": (st["tau_one_se"], st["iterations_one_se"])}
    out: dict[str, Any] = {"search_s": search_s, "block": st["holdout_block"]}
    for rule, (tau, its) in picks.items():
        out[rule] = {"tau": tau, "iterations": its}
    out["min"]["psnr"] = _psnr(model, b, truth, *picks["min"])
    out["1se"]["psnr"] = (out["min"]["psnr"] if picks["1se"] == picks["min"]
                          else _psnr(model, b, truth, *picks["1se"]))
    grid = {t: _psnr(model, b, truth, t, iters) for t in GRID}
    best = max(grid, key=grid.__getitem__)
    out["oracle"] = {"tau": best, "psnr": grid[best]}
    return out


def table(rows: list[dict[str, Any]]) -> str:
    """Per-case rows and a summary per case kind."""
    lines = ["| case | min: tau / it | min PSNR | 1se: tau / it | 1se PSNR | oracle tau | "
             "oracle PSNR |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        m, s, o = r["min"], r["1se"], r["oracle"]
        lines.append(f"| {r['case']} | {m['tau']:.2g} / {m['iterations']} | {m['psnr']:.2f} | "
                     f"{s['tau']:.2g} / {s['iterations']} | {s['psnr']:.2f} | {o['tau']:.0e} | "
                     f"{o['psnr']:.2f} |")
    lines.append("")
    for kind in ("real", "sim"):
        rs = [r for r in rows if r["case"].startswith(kind)]
        if not rs:
            continue
        n = len(rs)
        d = [r["1se"]["psnr"] - r["min"]["psnr"] for r in rs]
        miss = {k: [r["oracle"]["psnr"] - r[k]["psnr"] for r in rs] for k in ("min", "1se")}
        lines.append(
            f"{kind} ({n} cases): mean PSNR min {sum(r['min']['psnr'] for r in rs) / n:.2f}, "
            f"1se {sum(r['1se']['psnr'] for r in rs) / n:.2f}, oracle "
            f"{sum(r['oracle']['psnr'] for r in rs) / n:.2f} dB; 1se - min: mean "
            f"{sum(d) / n:+.3f} dB, {sum(x > 0.005 for x in d)} better, "
            f"{sum(x < -0.005 for x in d)} worse (range {min(d):+.2f} .. {max(d):+.2f}); "
            f"miss of the oracle: min mean {sum(miss['min']) / n:.2f} (worst "
            f"{max(miss['min']):.2f}), 1se mean {sum(miss['1se']) / n:.2f} (worst "
            f"{max(miss['1se']):.2f}) dB")
    return "\n".join(lines) + "\n"


def resumed(args: argparse.Namespace, name: str, required: tuple[str, ...],
            settings: dict[str, Any], version: int = RESULTS_VERSION
            ) -> dict[str, dict[str, Any]]:
    """The finished cases of ``--results`` by label (a later record of a case wins).

    A record of other ``settings`` (or of none: an older run) is refused in one line: it
    would be skipped as done, and mixed into the table.
    """
    if not args.results:
        return {}
    done: dict[str, dict[str, Any]] = {}
    for r in read_records(args.results, "--results", name, version, required):
        if r.get("settings") != settings:
            diff = ", ".join(f"{k} {r['settings'].get(k)} not {v}" for k, v in settings.items()
                             if r["settings"].get(k) != v) if isinstance(
                r.get("settings"), dict) else "no settings"
            raise ValueError(f"--results {args.results} holds a case run with other settings "
                             f"({r['case']}: {diff}): give another --results file (or those "
                             "settings)")
        done[r["case"]] = r
    return done


def run(args: argparse.Namespace) -> int:
    """Run the cases not yet in ``--results`` and print the table of them all."""
    check_outputs(args, {"--out": args.out}, appended={"--results": args.results},
                  inputs={"--data": args.data})
    check_block(args.block, _sensor_shapes(args))
    choice = bench_threads(args)
    settings = {"iters": args.iters, "block": args.block, "threads": choice.threads}
    wanted = labels(args)
    done = {k: v for k, v in resumed(args, "tau-rules", REQUIRED, settings).items()
            if k in wanted}
    t0 = time.perf_counter()
    n_new = 0
    for label, model, b, truth in _cases(args, skip=set(done)):
        row = {"case": label, **run_case(model, b, truth, args.iters, args.block),
               "settings": settings}
        print(f"{label}: min {row['min']['psnr']:.2f}, 1se {row['1se']['psnr']:.2f}, oracle "
              f"{row['oracle']['psnr']:.2f} dB", file=sys.stderr, flush=True)
        append_jsonl(args.results, tagged("tau-rules", RESULTS_VERSION, row))
        done[label] = row
        n_new += 1
    rows = [done[k] for k in wanted if k in done]
    text = (f"Automatic tau, smallest held-out error (min) against one standard error (1se); "
            f"{args.iters} iterations, held-out blocks of "
            f"{'the default side (recon.holdout)' if args.block is None else f'{args.block} px'}"
            f" (side used: {sorted({r['block'] for r in rows})} px), "
            f"oracle grid {', '.join(f'{t:g}' for t in GRID)}; "
            f"{time.perf_counter() - t0:.0f} s ({len(rows)} cases"
            f"{f', {len(rows) - n_new} from --results' if len(rows) > n_new else ''}). "
            f"{machine_text(choice)}\n\n" + table(rows))
    print_and_write(text, args.out)
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    add_arguments(parser)
    sys.exit(run(parser.parse_args()))
