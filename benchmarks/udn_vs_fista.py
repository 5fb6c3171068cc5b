"""UDN against best-tau FISTA-TV on the simulation protocol at 99% erasures (noise 0.01).

Protocol (as ``benchmarks/sim_protocol.py``): the tutorial PSF (dark-subtracted, clipped, unit
sum) at 1/8 scale (150x200) or, with ``--scale 16``, box-downsampled once more (75x100); the
three lensed scenes as grayscale ground truth at the same size; measurement normalised to max 1,
Gaussian noise 0.01, then 99% of the pixels erased. PSNR after a least-squares gain fit.

- FISTA-TV: tau from the protocol's grid and the iteration count from its checkpoints, both
  chosen to maximise the mean PSNR over the scenes *using the ground truth*.
- UDN: one configuration for every scene (``--channels``, ``--scales``, ``--skip``,
  ``--headroom``, lr 0.01, input noise 0.05, EMA 0.99), run with ``--seeds`` seeds whose
  estimates are averaged (an ensemble: each seed holds out its own pixels). Two ways of
  stopping are reported:

  * *same rule as FISTA*: the iteration count (one of the ``--eval-every`` checkpoints) that
    maximises the mean PSNR over the scenes, chosen on the ground truth exactly as FISTA's
    tau and iteration count are;
  * *held-out choice*: no ground truth at all. Each seed holds out its own random pixels;
    the iteration count (per scene) is the checkpoint where the seeds' held-out prediction
    errors, pooled, are least (a cross-validation over all the seeds' held-out pixels). The
    estimate each seed picks from its own few held-out pixels alone is shown beside it.

    python -m benchmarks.udn_vs_fista --scale 16 --out docs/udn-vs-fista.md
    lenslesscam bench udn-vs-fista --scale 16
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from typing import Any

from app.commands._options import (
    FRACTION,
    NONNEG,
    NONNEG_INT,
    POSITIVE,
    POSITIVE_INT,
    add_overwrite_option,
)
from benchmarks._cli import bench_threads, check_outputs, command_line, machine_text

#: the default run's time (``--help``; docs/udn.md: 13 CPU minutes per scene, 4 x 3000 iterations)
DURATION = ("long: docs/udn.md gives 13 CPU minutes per scene for 4 seeds x 3000 iterations; "
            "the default runs 3 scenes")

TAUS = (1e-6, 1e-5, 3e-5, 1e-4, 3e-4, 1e-3, 3e-3)
FISTA_CHECKPOINTS = (50, 100, 200, 300, 500)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options."""
    p.add_argument("--scale", type=int, choices=[8, 16], default=16,
                   help="1/8 (150x200) or 1/16 (75x100) of the sensor (16)")
    p.add_argument("--erasure", type=FRACTION, default=0.99,
                   help="fraction of erased pixels (0.99)")
    p.add_argument("--noise", type=NONNEG, default=0.01,
                   help="Gaussian noise sigma, max = 1 (0.01)")
    p.add_argument("--iters", type=POSITIVE_INT, default=2000,
                   help="UDN iterations per seed (2000)")
    p.add_argument("--seeds", type=POSITIVE_INT, default=4, help="UDN ensemble size (4)")
    p.add_argument("--channels", type=POSITIVE_INT, default=64, help="UDN channels (64)")
    p.add_argument("--scales", type=POSITIVE_INT, default=5, help="UDN scales (5)")
    p.add_argument("--skip", type=NONNEG_INT, default=0, help="UDN skip channels (0)")
    p.add_argument("--headroom", type=POSITIVE, default=3.0,
                   help="factor on the UDN's initial least-squares gain (3)")
    p.add_argument("--tv-weight", type=NONNEG, default=0.0, help="UDN TV loss weight (0)")
    p.add_argument("--lr", type=POSITIVE, default=0.01, help="UDN learning rate (0.01)")
    p.add_argument("--ema", type=FRACTION, default=0.99, help="UDN EMA decay (0.99)")
    p.add_argument("--holdout", type=FRACTION, default=0.1, help="UDN held-out fraction (0.1)")
    p.add_argument("--eval-every", type=POSITIVE_INT, default=100, help="UDN checkpoints (100)")
    p.add_argument("--fista-iters", type=POSITIVE_INT, default=500,
                   help="FISTA iterations per tau (500); scored at the checkpoints "
                   f"{', '.join(map(str, FISTA_CHECKPOINTS))} below it and at the last")
    p.add_argument("--threads", type=POSITIVE_INT, default=None,
                   help="torch threads per process (default: the global --threads, else the "
                   "thread policy's count, recon.threads, divided among the --jobs processes)")
    jobs = min(2, os.cpu_count() or 1)
    p.add_argument("--jobs", type=POSITIVE_INT, default=jobs,
                   help=f"UDN runs in parallel processes (default min(2, CPU count): {jobs} here)")
    p.add_argument("--device", default="cpu", help="torch device of the UDN runs (auto, cpu, cuda)")
    p.add_argument("--scenes", nargs="+", default=None, help="subset of the lensed scenes")
    p.add_argument("--out", default=None, help="write the Markdown here")
    add_overwrite_option(p)


def make_data(scale: int, names: list[str] | None, erasure: float,
              noise: float) -> tuple[Any, dict[str, Any]]:
    """The PSF (H, W) and one simulated measurement per scene."""
    import numpy as np

    from recon import samples
    from recon.io import box_downsample
    from recon.models import build_model
    from recon.simulate import simulate

    psf = samples.tutorial_psf()  # (1, 150, 200), unit sum
    scenes = {n: samples.lensed_scene(n) for n in (names or samples.lensed_scene_names())}
    if scale == 16:
        psf = box_downsample(psf, 2)
        psf = (psf / psf.sum()).astype(np.float32)
        scenes = {n: box_downsample(s, 2).astype(np.float32) for n, s in scenes.items()}
    sims = {n: simulate(build_model("2d", psf[0]), s, erasure=erasure, noise=noise, seed=0)
            for n, s in scenes.items()}
    return psf[0], sims


def score(truth: Any, est: Any) -> float:
    """PSNR after a least-squares gain fit."""
    from recon.metrics import gain_fit, psnr

    return float(psnr(truth, gain_fit(truth, est)[0]))


def fista_checkpoints(iters: int) -> list[int]:
    """The iteration counts FISTA is scored at: :data:`FISTA_CHECKPOINTS` below ``iters``, and
    ``iters`` itself (so a limit below the first checkpoint is scored at its last iteration)."""
    return sorted({c for c in FISTA_CHECKPOINTS if c < iters} | {iters})


def run_fista(psf: Any, sims: dict[str, Any], iters: int,
              taus: tuple[float, ...] = TAUS) -> dict[str, Any]:
    """Best (tau, checkpoint of :func:`fista_checkpoints`) by mean PSNR over the scenes."""
    import torch

    from recon.fista import Fista
    from recon.models import build_model

    checkpoints = fista_checkpoints(iters)
    best: dict[str, Any] | None = None
    for tau in taus:
        per: dict[str, dict[int, tuple[float, float]]] = {}
        for name, sim in sims.items():
            model = build_model("2d", psf, mask=sim.mask)
            solver = Fista(model.op, torch.as_tensor(sim.meas), tau=tau, max_iter=iters, tol=0.0)
            t0 = time.perf_counter()
            per[name] = {}
            for step in solver.steps():
                if step.iteration in checkpoints or solver.done:
                    per[name][step.iteration] = (score(sim.truth, solver.x.numpy()),
                                                 time.perf_counter() - t0)
            last = per[name][max(per[name])]
            for c in checkpoints:  # a run that stopped early: its last estimate from there on
                if c not in per[name]:
                    per[name][c] = last
        for c in checkpoints:
            mean = sum(per[n][c][0] for n in sims) / len(sims)
            if best is None or mean > best["mean"]:
                best = {"mean": mean, "tau": tau, "iterations": c,
                        "psnr": {n: per[n][c][0] for n in sims},
                        "wall": {n: per[n][c][1] for n in sims}}
    if best is None:  # no tau given
        raise ValueError("run_fista: no tau to try")
    return best


def udn_member(task: dict[str, Any]) -> dict[str, Any]:
    """One UDN run (one scene, one seed): its estimates at the checkpoints and its own choice.

    Runs in a worker process; rebuilds the (seeded, deterministic) simulation itself.
    """

    from recon.models import build_model
    from recon.threads import apply_threads
    from recon.udn.network import NetworkConfig
    from recon.udn.runner import UDNConfig, UDNRunner, resolve_device

    apply_threads(task["threads"])
    psf, sims = make_data(task["scale"], [task["scene"]], task["erasure"], task["noise"])
    sim = sims[task["scene"]]
    device = resolve_device(task["device"])
    model = build_model("2d", psf, mask=sim.mask, device=device)
    net = NetworkConfig(scales=task["scales"], channels=task["channels"],
                        skip_channels=task["skip"])
    cfg = UDNConfig(max_iter=task["iters"], holdout=task["holdout"], patience=10**9,
                    min_iter=0, lr=task["lr"], reg_noise=0.05, ema=task["ema"],
                    seed=task["seed"],
                    headroom=task["headroom"], tv_weight=task["tv_weight"])
    runner = UDNRunner(model, sim.meas, network=net, config=cfg)
    checkpoints: dict[int, Any] = {}
    walls: dict[int, float] = {}
    heldout: dict[int, float] = {}
    for s in runner.steps():
        if s.iteration % task["eval_every"] == 0 or runner.done:
            checkpoints[s.iteration] = runner.final_estimate()
            walls[s.iteration] = runner.elapsed_s
            heldout[s.iteration] = float(s.heldout if s.heldout is not None else "nan")
    return {
        "scene": task["scene"], "seed": task["seed"], "checkpoints": checkpoints,
        "walls": walls, "heldout": heldout, "selected": runner.best_estimate(),
        "selected_iteration": runner.best_iteration, "iterations": runner.iteration,
        "wall": runner.elapsed_s, "heldout_pixels": runner.n_heldout,
        "fitted_pixels": runner.n_fit,
    }


def run_udn(sims: dict[str, Any], args: argparse.Namespace) -> dict[str, Any]:
    """All scenes x seeds; the ensemble's PSNR per checkpoint and of the held-out choices."""
    import numpy as np

    base = {k: getattr(args, k) for k in ("scale", "erasure", "noise", "iters", "channels",
                                          "scales", "skip", "headroom", "tv_weight", "holdout",
                                          "lr", "ema", "eval_every", "threads", "device")}
    tasks = [dict(base, scene=n, seed=s) for n in sims for s in range(args.seeds)]
    if args.jobs > 1:
        import multiprocessing

        ctx = multiprocessing.get_context("spawn")  # no forked torch thread pools
        with ProcessPoolExecutor(max_workers=args.jobs, mp_context=ctx) as pool:
            members = list(pool.map(udn_member, tasks))
    else:
        members = [udn_member(t) for t in tasks]
    out: dict[str, Any] = {}
    for n, sim in sims.items():
        ms = [m for m in members if m["scene"] == n]
        its = sorted(set.intersection(*(set(m["checkpoints"]) for m in ms)))
        curve = {t: score(sim.truth, np.mean([m["checkpoints"][t] for m in ms], axis=0))
                 for t in its}
        pooled = {t: float(np.mean([m["heldout"][t] for m in ms])) for t in its}
        t_cv = min(its, key=lambda t: pooled[t])
        out[n] = {
            "curve": curve, "cv_iteration": t_cv, "cv": curve[t_cv],
            "walls": {t: sum(m["walls"][t] for m in ms) for t in its},
            "selected": score(sim.truth, np.mean([m["selected"] for m in ms], axis=0)),
            "selected_iterations": [m["selected_iteration"] for m in ms],
            "selected_wall": sum(m["walls"][min(t for t in its if t >= m["selected_iteration"])]
                                 for m in ms),
            "members": [score(sim.truth, m["checkpoints"][its[-1]]) for m in ms],
            "iterations": max(m["iterations"] for m in ms),
            "wall": sum(m["wall"] for m in ms),
            "heldout_pixels": ms[0]["heldout_pixels"], "fitted_pixels": ms[0]["fitted_pixels"],
        }
    return out


def pick_iteration(udn: dict[str, Any]) -> int:
    """The checkpoint with the best mean ensemble PSNR over the scenes (FISTA's rule)."""
    names = list(udn)
    its = sorted(set.intersection(*(set(udn[n]["curve"]) for n in names)))
    return max(its, key=lambda t: sum(udn[n]["curve"][t] for n in names))


def run(args: argparse.Namespace) -> int:
    """Run both methods on the scenes and print / write the table."""
    check_outputs(args, {"--out": args.out})
    if not 0 < args.holdout < 1:
        raise ValueError(f"--holdout must be in (0, 1) (the held-out choice needs held-out "
                         f"pixels), got {args.holdout}")
    chosen_here = args.threads is None and getattr(args, "thread_choice", None) is None
    choice = bench_threads(args)  # one count, passed to every worker process
    if chosen_here and args.jobs > 1:  # the policy's count is for one process: shared by
        # --jobs of them (2 x 2 threads on 2 cores is oversubscribed, up to 50x slower)
        args.threads = max(1, choice.threads // args.jobs)
    t_all = time.perf_counter()
    psf, sims = make_data(args.scale, args.scenes, args.erasure, args.noise)
    fista = run_fista(psf, sims, args.fista_iters)
    print(f"FISTA-TV: tau {fista['tau']:g}, {fista['iterations']} iterations, mean PSNR "
          f"{fista['mean']:.2f} dB", file=sys.stderr)
    udn = run_udn(sims, args)
    t_best = pick_iteration(udn)
    names = list(sims)
    h, w = psf.shape
    lines = [
        "| scene | FISTA-TV PSNR (dB) | FISTA iterations | FISTA wall (s) | UDN, same rule as "
        "FISTA (dB) | iterations x seeds | wall (s) | UDN, held-out choice (dB) | iterations x "
        "seeds | wall (s) | each seed's own held-out choice: ensemble (dB), iterations | single "
        "seeds at the end (dB) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for n in names:
        u = udn[n]
        lines.append(
            f"| {n} | {fista['psnr'][n]:.2f} | {fista['iterations']} | {fista['wall'][n]:.2f} | "
            f"{u['curve'][t_best]:.2f} | {t_best} x {args.seeds} | {u['walls'][t_best]:.0f} | "
            f"{u['cv']:.2f} | {u['cv_iteration']} x {args.seeds} | "
            f"{u['walls'][u['cv_iteration']]:.0f} | {u['selected']:.2f}: "
            f"{', '.join(map(str, u['selected_iterations']))} | "
            f"{', '.join(f'{p:.2f}' for p in u['members'])} |")
    mean_same = sum(udn[n]["curve"][t_best] for n in names) / len(names)
    mean_cv = sum(udn[n]["cv"] for n in names) / len(names)
    mean_sel = sum(udn[n]["selected"] for n in names) / len(names)
    lines.append(f"| **mean** | **{fista['mean']:.2f}** | | | **{mean_same:.2f}** | | | "
                 f"**{mean_cv:.2f}** | | | {mean_sel:.2f} | |")
    table = "\n".join(lines)
    its = sorted(udn[names[0]]["curve"])
    curve_lines = ["| UDN iterations per seed | " + " | ".join(map(str, its)) + " |",
                   "|---|" + "---|" * len(its)]
    for n in names:
        curve_lines.append(f"| {n} | " + " | ".join(f"{udn[n]['curve'][t]:.2f}" for t in its)
                           + " |")
    curve = "\n".join(curve_lines)

    def verdict(label: str, value: float) -> str:
        word = "beats" if value > fista["mean"] else "does not beat"
        return (f"UDN ({label}) {word} best-tau FISTA-TV: {value:.2f} vs {fista['mean']:.2f} dB "
                f"mean PSNR.")

    verdicts = [verdict("same rule as FISTA", mean_same), verdict("held-out choice", mean_cv),
                verdict("each seed's own held-out choice", mean_sel)]
    print(table)
    print(curve)
    print("\n".join(verdicts))
    if args.out:
        from recon.atomic import atomic_write_bytes

        u0 = udn[names[0]]
        per_iter = u0["wall"] / max(u0["iterations"] * args.seeds, 1)
        cmd = command_line("udn-vs-fista", args, add_arguments)
        text = (
            "# UDN vs FISTA-TV on the simulation protocol\n\n"
            f"Tutorial PSF at 1/{args.scale} scale ({h}x{w}), the lensed scenes "
            f"({', '.join(names)}) as grayscale truth, Gaussian noise {args.noise:g}, "
            f"{args.erasure:.0%} of the pixels erased ({u0['fitted_pixels'] + u0['heldout_pixels']}"
            f" measured of {h * w}). PSNR after a least-squares gain fit. "
            + ("1/16 scale because a 1/8-scale run (4x the pixels) does not fit a CPU budget "
               "(docs/udn.md)." if args.scale == 16 else "")
            + "\n\n"
            f"- FISTA-TV: tau {fista['tau']:g} and {fista['iterations']} iterations, both chosen "
            f"on the ground truth to maximise the mean PSNR (tau grid "
            f"{', '.join(f'{t:g}' for t in TAUS)}; checkpoints "
            f"{', '.join(map(str, fista_checkpoints(args.fista_iters)))}).\n"
            f"- UDN: {args.scales} scales x {args.channels} channels, skip channels "
            f"{args.skip}, output gain headroom {args.headroom:g}, TV weight {args.tv_weight:g}, "
            f"lr {args.lr:g}, input noise 0.05, "
            f"EMA {args.ema:g}; {args.seeds} seeds averaged, each holding out "
            f"{u0['heldout_pixels']} of the measured pixels (its own). The same configuration "
            "for every scene.\n"
            f"  - *same rule as FISTA*: the iteration count that maximises the mean PSNR over "
            f"the scenes (checkpoints every {args.eval_every}), chosen on the ground truth like "
            f"FISTA's: {t_best} per seed.\n"
            "  - *held-out choice*: no ground truth; per scene, the iteration count where the "
            "seeds' held-out prediction errors, pooled, are least (cross-validation over "
            f"{args.seeds} x {u0['heldout_pixels']} pixels). Beside it, the average of what each "
            "seed picks from its own held-out pixels alone (noisier: few pixels).\n"
            "- UDN wall is the sum over the seeds (they are independent runs, in parallel "
            f"here on {args.jobs} processes).\n\n"
            f"{table}\n\n**{verdicts[0]}**  \n**{verdicts[1]}**  \n{verdicts[2]}\n\n"
            "The ensemble's PSNR against the iterations per seed:\n\n"
            f"{curve}\n\n"
            f"Device {args.device}, {args.threads} torch thread(s) per process; UDN "
            f"{per_iter * 1000:.0f} ms per iteration and seed. {machine_text(choice)} "
            f"Total {time.perf_counter() - t_all:.0f} s.\n\n"
            f"Produced by `{cmd}`.\n"
        )
        atomic_write_bytes(args.out, text.encode())
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    add_arguments(parser)
    sys.exit(run(parser.parse_args()))
