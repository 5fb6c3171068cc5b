"""The simulation protocol: best-tau FISTA-TV PSNR/SSIM per erasure and noise level.

Tutorial PSF at 1/8 scale (dark-subtracted, clipped, unit sum), the three lensed scenes as
grayscale ground truth (150x200), erasures 0/50/90/95/99 %, Gaussian noise 0 and 0.01 on the
measurement normalised to max 1. For each level, tau is chosen from a grid to maximise the mean
PSNR over the three scenes (gain-fitted), and the best iteration count among the checkpoints is
reported with it.

    lenslesscam bench protocol [--out docs/simulation-protocol.md] [--iters 500]
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

TAUS = (1e-6, 1e-5, 3e-5, 1e-4, 3e-4, 1e-3, 3e-3)
ERASURES = (0.0, 0.5, 0.9, 0.95, 0.99)
NOISES = (0.0, 0.01)
CHECKPOINTS = (50, 100, 200, 300, 500, 1000)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of ``lenslesscam bench protocol``."""
    p.add_argument("--iters", type=int, default=500, help="iteration limit per run (500)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", default=None, help="write the Markdown table here")
    p.add_argument("--quick", action="store_true", help="two erasure levels, noise 0.01 only")


def run_case(psf: Any, scene: Any, erasure: float, noise: float, tau: float, iters: int,
             seed: int = 0) -> dict[str, Any]:
    """Simulate one case and run FISTA-TV; PSNR/SSIM at each checkpoint (gain-fitted)."""
    import torch

    from recon.fista import Fista
    from recon.metrics import gain_fit, psnr, ssim
    from recon.models import build_model
    from recon.simulate import simulate

    sim = simulate(build_model("2d", psf), scene, erasure=erasure, noise=noise, seed=seed)
    model = build_model("2d", psf, mask=sim.mask)
    solver = Fista(model.op, torch.as_tensor(sim.meas), tau=tau, max_iter=iters, tol=0.0)
    out: dict[str, Any] = {"checkpoints": {}}
    t0 = time.perf_counter()
    for step in solver.steps():
        if step.iteration in CHECKPOINTS or solver.done:
            est = gain_fit(sim.truth, solver.x.numpy())[0]
            out["checkpoints"][step.iteration] = (psnr(sim.truth, est), ssim(sim.truth, est),
                                                  time.perf_counter() - t0)
    # a run that stopped early (converged or stalled) keeps its estimate at later checkpoints
    last = out["checkpoints"][max(out["checkpoints"])]
    for c in CHECKPOINTS:
        if c <= iters and c not in out["checkpoints"]:
            out["checkpoints"][c] = last
    out["checkpoints"] = {c: v for c, v in out["checkpoints"].items() if c in CHECKPOINTS}
    out["iterations"] = solver.iteration
    return out


def run(args: argparse.Namespace) -> int:
    """Run the protocol and print (and optionally write) the table."""
    import torch

    from recon import samples

    torch.set_num_threads(args.threads)
    psf = samples.tutorial_psf()
    scenes = {n: samples.lensed_scene(n) for n in samples.lensed_scene_names()}
    erasures = (0.0, 0.9) if args.quick else ERASURES
    noises = (0.01,) if args.quick else NOISES
    rows = []
    t_all = time.perf_counter()
    for noise in noises:
        for er in erasures:
            best: tuple[float, ...] | None = None
            for tau in TAUS:
                per_scene = {n: run_case(psf, s, er, noise, tau, args.iters)
                             for n, s in scenes.items()}
                its = sorted(next(iter(per_scene.values()))["checkpoints"])
                for it in its:
                    ps = [per_scene[n]["checkpoints"][it][0] for n in scenes]
                    ss = [per_scene[n]["checkpoints"][it][1] for n in scenes]
                    ts = [per_scene[n]["checkpoints"][it][2] for n in scenes]
                    mean_p = sum(ps) / len(ps)
                    if best is None or mean_p > best[0]:
                        best = (mean_p, sum(ss) / len(ss), tau, it, sum(ts) / len(ts), *ps)
            assert best is not None
            rows.append((noise, er, *best))
            print(f"noise {noise:g} erasure {er:.0%}: PSNR {best[0]:.2f} dB, SSIM {best[1]:.3f}, "
                  f"tau {best[2]:g}, {best[3]} iterations", file=sys.stderr)
    names = list(scenes)
    lines = [
        "| noise | erasures | best tau | iterations | wall (s) | mean PSNR (dB) | mean SSIM | "
        + " | ".join(f"PSNR {n}" for n in names) + " |",
        "|---|---|---|---|---|---|---|" + "---|" * len(names),
    ]
    for noise, er, p, s, tau, it, t, *ps in rows:
        lines.append(f"| {noise:g} | {er:.0%} | {tau:g} | {it} | {t:.2f} | {p:.2f} | {s:.3f} | "
                     + " | ".join(f"{v:.2f}" for v in ps) + " |")
    table = "\n".join(lines)
    print(table)
    if args.out:
        from recon.formats import atomic_write_bytes

        header = (
            "# Simulation protocol: FISTA-TV, best tau per level\n\n"
            "Tutorial PSF at 1/8 scale (150x200, dark-subtracted, clipped, unit sum); the three\n"
            "lensed scenes (im408, im740, im65) as grayscale ground truth; measurement normalised\n"
            "to max 1, then Gaussian noise, then erasures (exactly round(f*N) pixels, seed 1).\n"
            f"tau grid {', '.join(f'{t:g}' for t in TAUS)}; PSNR/SSIM after a least-squares gain\n"
            f"fit, at checkpoints {', '.join(map(str, CHECKPOINTS))} (limit {args.iters}); the\n"
            "best (tau, iterations) maximises the mean PSNR over the three scenes. Wall time is\n"
            f"per scene on {args.threads} torch threads (2-core machine).\n\n"
            f"Produced by `lenslesscam bench protocol --threads {args.threads} --out "
            f"docs/simulation-protocol.md` in {time.perf_counter() - t_all:.0f} s.\n\n"
            "Without noise the best tau is the smallest on the grid and the best iteration count\n"
            "is the limit: the noise-free problem is still improving at 500 iterations (see\n"
            "ARCHITECTURE.md), so those rows are lower bounds.\n\n"
        )
        atomic_write_bytes(args.out, (header + table + "\n").encode())
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    add_arguments(parser)
    sys.exit(run(parser.parse_args()))
