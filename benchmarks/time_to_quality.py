"""Time to quality: FISTA-TV and ADMM-TV against LenslessPiCam's ADMM on the same case.

The protocol's im408 scene (tutorial PSF at 1/8 scale, unit sum, measurement normalised to
max 1, noise 0.01) at 0 % and 90 % erasures. tau is the project's default choice for the
measurement (:func:`recon.autotau.choose_tau`, held-out pixels), the same for every method.
Each method runs ``--iters`` iterations on one torch thread; every ``--every`` iterations the
estimate is scored (PSNR after a least-squares gain fit, outside the timed region). Reported:
each method's best PSNR, the time to come within 0.1 dB of it, and the time to reach fixed
PSNR levels (LenslessPiCam's best minus 1, 0.5 and 0.1 dB).

LenslessPiCam (``lensless`` package, https://github.com/LCAV/LenslessPiCam) is NOT a
dependency: install it for this benchmark only with ``pip install --no-deps lensless``; its
column is skipped with the reason when it does not import. It has no erasure mask: its
x-update divides by ``pad(1) + mu1``; for the masked case that divisor is set to
``pad(mask) + mu1`` (and the data multiplied by the mask), which is the exact masked ADMM.
Its penalties are set to ours (mu1 = s, mu2 = mu3 = 0.01 s max|H|^2, s from
``recon.admm.penalty_scale``; with the unit-sum PSF max|H|^2 = 1); its TV is circular on the
padded grid (ours: only differences inside the field).

    lenslesscam bench time-to-quality [--iters 500]   (prints the table; docs/auto-tau.md quotes it)
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable
from typing import Any

from app.commands._options import POSITIVE_INT

ERASURES = (0.0, 0.9)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of ``lenslesscam bench time-to-quality``."""
    p.add_argument("--iters", type=POSITIVE_INT, default=500, help="iterations per method")
    p.add_argument("--every", type=POSITIVE_INT, default=10, help="score every N iterations")
    p.add_argument("--scene", default="im408", help="lensed scene (im408, im740, im65)")
    p.add_argument("--threads", type=POSITIVE_INT, default=None,
                   help="torch threads (default: the global --threads, else the thread "
                   "policy, recon.threads)")


def _trace(step: Callable[[], None], estimate: Callable[[], Any], score: Callable[[Any], float],
           iters: int, every: int) -> list[tuple[int, float, float]]:
    """[(iteration, seconds, PSNR)] with the scoring outside the timed region."""
    out = []
    elapsed = 0.0
    for i in range(1, iters + 1):
        t0 = time.perf_counter()
        step()
        elapsed += time.perf_counter() - t0
        if i % every == 0 or i == iters:
            out.append((i, elapsed, score(estimate())))
    return out


def _lensless(psf: Any, meas: Any, mask: Any, tau: float, mu: tuple[float, float, float]
              ) -> tuple[Callable[[], None], Callable[[], Any]]:
    import torch
    from lensless import ADMM

    hw = tuple(psf.shape[-2:])
    p4 = torch.as_tensor(psf, dtype=torch.float32).reshape(1, *hw, 1)
    m4 = (torch.ones(1, *hw, 1) if mask is None
          else torch.as_tensor(mask, dtype=torch.float32).reshape(1, *hw, 1))
    rec = ADMM(p4, mu1=mu[0], mu2=mu[1], mu3=mu[2], tau=tau)
    rec.set_data(torch.as_tensor(meas, dtype=torch.float32).reshape(1, *hw, 1) * m4)
    rec.reset()
    rec._X_divmat = 1.0 / (rec._convolver._pad(m4) + rec._mu1)  # the masked x-update
    it = [0]

    def step() -> None:
        rec._update(it[0])
        it[0] += 1

    def estimate() -> Any:
        return rec._form_image().detach().numpy().reshape(hw)

    return step, estimate


def run(args: argparse.Namespace) -> int:
    """Run the three methods at each erasure level and print the tables."""
    import os

    import torch

    from benchmarks._cli import bench_threads, machine_text
    from recon import samples
    from recon.admm import Admm
    from recon.autotau import choose_tau
    from recon.fista import Fista
    from recon.metrics import gain_fit, psnr
    from recon.models import build_model
    from recon.simulate import simulate

    choice = bench_threads(args)
    psf = samples.tutorial_psf()
    scene = samples.lensed_scene(args.scene)
    lensless_version = "unknown"
    try:
        import lensless

        lensless_why = ""
        from importlib.metadata import PackageNotFoundError, version

        try:
            lensless_version = version("lensless")
        except PackageNotFoundError:
            lensless_version = str(getattr(lensless, "__version__", "unknown"))
    except ImportError as exc:
        lensless_why = f"LenslessPiCam not importable ({exc}); `pip install --no-deps lensless`"
    lines = [machine_text(choice) + (f" LenslessPiCam (lensless) {lensless_version}, driven "
                                     "through its private API." if not lensless_why else "")]
    for er in ERASURES:
        sim = simulate(build_model("2d", psf), scene, erasure=er, noise=0.01, seed=0)
        model = build_model("2d", psf, mask=sim.mask)
        b = torch.as_tensor(sim.meas)
        choice = choose_tau(model, b, max_iter=args.iters, min_iter=min(100, args.iters),
                            patience=max(10, min(100, args.iters)))
        tau = choice.tau

        def score(x: Any, sim: Any = sim) -> float:
            return psnr(sim.truth, gain_fit(sim.truth, x.reshape(sim.truth.shape))[0])

        traces: dict[str, list[tuple[int, float, float]]] = {}
        fista = Fista(model.op, b, tau=tau, max_iter=10**9, tol=0.0)
        traces["FISTA-TV (ours)"] = _trace(fista.step, lambda f=fista: f.x.numpy(), score,
                                           args.iters, args.every)
        admm = Admm(model, b, tau=tau, max_iter=10**9, tol=0.0)
        traces["ADMM-TV (ours)"] = _trace(admm.step, lambda a=admm: a.x.numpy(), score,
                                          args.iters, args.every)
        if not lensless_why:
            step, est = _lensless(psf, sim.meas[0], sim.mask, tau,
                                  (admm.mu1, admm.mu2, admm.mu3))
            traces["LenslessPiCam ADMM"] = _trace(step, est, score, args.iters, args.every)
        best_l = max(p for _, _, p in traces.get("LenslessPiCam ADMM", [(0, 0.0, math.nan)]))
        levels = [best_l - 1.0, best_l - 0.5, best_l - 0.1] if math.isfinite(best_l) else []
        lines.append(f"\n**{er:.0%} erasures, noise 0.01, tau {tau:.3g} (auto), "
                     f"{args.iters} iterations, {args.threads} thread(s), load "
                     f"{os.getloadavg()[0]:.1f}**\n")
        head = ("| method | best PSNR (dB) | at iteration | time to best - 0.1 dB (s) | "
                "ms / iteration | " + " | ".join(f"time to {v:.2f} dB (s)" for v in levels)
                + " |")
        lines += [head, "|" + "---|" * (head.count("|") - 1)]
        for name, tr in traces.items():
            best_i, _, best_p = max(tr, key=lambda r: r[2])
            t_q = next(t for _, t, p in tr if p >= best_p - 0.1)
            per_it = tr[-1][1] / tr[-1][0]
            reach = []
            for v in levels:
                hit = next((t for _, t, p in tr if p >= v), None)
                reach.append("never" if hit is None else f"{hit:.2f}")
            lines.append(f"| {name} | {best_p:.2f} | {best_i} | {t_q:.2f} | {per_it * 1e3:.1f}"
                         f" | " + " | ".join(reach) + " |")
        if lensless_why:
            lines.append(f"\nLenslessPiCam column skipped: {lensless_why}")
    text = "\n".join(lines)
    print(text)
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    add_arguments(parser)
    sys.exit(run(parser.parse_args()))
