"""The simulation protocol: the no-flag default (tau auto) against the oracle tau and a reference.

Tutorial PSF at 1/8 scale (dark-subtracted, clipped, unit sum), the three lensed scenes as
grayscale ground truth (150x200), erasures 0/50/90/95/99 %, Gaussian noise 0 and 0.01 on the
measurement normalised to max 1. Per case (scene, erasure, noise):

- **auto**: what ``recon fista`` does with no flags: :func:`recon.autotau.choose_tau` on the
  measurement alone, then FISTA-TV from all measured pixels with the chosen tau and iterations;
- **oracle**: the best PSNR over the tau grid ``ORACLE_TAUS`` at ``--iters`` (500) iterations
  (default restart rule);
- **monotone**: the restart rule before the gradient rule (function-value test, monotone; FISTA
  momentum) at the oracle tau, ``--iters`` iterations;
- **unpreconditioned**: the previous default (POGM momentum, gradient restart, no Fourier
  preconditioner) at the oracle tau;
- **fista**: the default before that (FISTA momentum, gradient restart, no preconditioner);
- **reference** (unless ``--no-reference``): an accurate FISTA-TV at the oracle tau, 1000
  iterations with 50 inner prox iterations, FISTA momentum and no restart, plus the same with
  ``--iters``
  iterations (the convergence check at an equal iteration count).

PSNR/SSIM after a least-squares gain fit against the truth. Each finished case is appended to
a JSON-lines file (``--cache``), so an interrupted run resumes and a partial run can be tabled;
a cached case whose automatic choice used scattered held-out pixels (before the blocks of
``recon.holdout``) has that choice rerun, the rest kept (nothing else depends on it).

    lenslesscam bench protocol [--out docs/simulation-protocol.md] [--iters 500]
    lenslesscam bench protocol --momentum-check   (the momentum ablation)
    lenslesscam bench protocol --convergence-check   (why 500 iterations are not enough
                                                      on the noise-free cases)
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from app.commands._options import POSITIVE_INT, add_overwrite_option
from benchmarks._cli import (
    append_jsonl,
    bench_threads,
    check_outputs,
    command_line,
    machine_text,
    read_records,
    tagged,
)

#: version of the records of ``--cache`` (format ``lenslesscam.bench.protocol``)
RESULTS_VERSION = 1
#: the keys every record of ``--cache`` has
REQUIRED = ("scene", "erasure", "noise", "iters", "auto", "oracle")

CASE_VERSION = 3  # cached cases of another version (solver defaults, columns) are not reused
ORACLE_TAUS = (1e-8, 3e-8, 1e-7, 3e-7, 1e-6, 3e-6, 1e-5, 3e-5, 1e-4, 3e-4)
ERASURES = (0.0, 0.5, 0.9, 0.95, 0.99)
NOISES = (0.0, 0.01)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of ``lenslesscam bench protocol``."""
    p.add_argument("--iters", type=POSITIVE_INT, default=500, help="iteration limit per run (500)")
    p.add_argument("--threads", type=POSITIVE_INT, default=None,
                   help="torch threads (default: the global --threads, else the thread "
                   "policy, recon.threads); cached cases of another count are run again")
    p.add_argument("--out", default=None, help="write the Markdown tables here")
    p.add_argument("--cache", default="protocol-cases.jsonl",
                   help="JSON lines of finished cases (resumed; default protocol-cases.jsonl)")
    p.add_argument("--quick", action="store_true", help="two erasure levels, noise 0.01 only")
    p.add_argument("--no-reference", action="store_true",
                   help="skip the accurate reference runs (the most expensive part)")
    p.add_argument("--restart-check", action="store_true",
                   help="instead: restart rules and momenta (monotone, gradient, none; FISTA, "
                   "POGM) against an accurate FISTA run (500 iterations x 50 inner prox steps) "
                   "at tau 3e-5, noise 0.01, "
                   "erasures 99 %% and 0 %%")
    p.add_argument("--momentum-check", action="store_true",
                   help="instead: momenta (FISTA, POGM; gradient restart or none) against the "
                   "reference (1000 FISTA iterations x 50 inner prox steps) on nine cases at "
                   "fixed tau")
    p.add_argument("--convergence-check", action="store_true",
                   help="instead: the normal operator's spectrum, the default's PSNR at 500 / "
                   "700 / 1000 / 1500 iterations against the reference on the three noise-free "
                   "0 %% cases, a Fourier-preconditioned forward-backward step at several "
                   "kappa, and ADMM-TV at several rho")
    p.add_argument("--prox-check", action="store_true",
                   help="instead: FISTA-TV's rise rule for the inexact TV prox (recon.fista "
                   "PLAIN_RISE): objective and PSNR after --iters iterations with the rule, "
                   "without it and with 50 inner prox steps, on im408 (noise 0.01) at 0, 90 "
                   "and 99 %% erasures and tau 1e-4 to 1e-2; then recon fista's default "
                   "(automatic tau) with and without the rule at 99 %% erasures")
    p.add_argument("--hand", action="store_true",
                   help="instead: the real DiffuserCam-Tutorial hand (no truth): the held-out "
                   "error over tau and the automatic choice")
    add_overwrite_option(p)


def _score(truth: Any, x: Any) -> tuple[float, float]:
    from recon.metrics import gain_fit, psnr, ssim

    est = gain_fit(truth, x)[0]
    return psnr(truth, est), ssim(truth, est)


def _fista(model: Any, b: Any, tau: float, iters: int, **kw: Any) -> tuple[Any, float]:
    from recon.fista import Fista

    t0 = time.perf_counter()
    solver = Fista(model.op, b, tau=tau, max_iter=iters, tol=0.0, **kw)
    for _ in solver.steps():
        pass
    return solver.x.numpy(), time.perf_counter() - t0


def simulate_case(psf: Any, scene: Any, erasure: float, noise: float, seed: int = 0) -> Any:
    """One protocol case: (the simulation, its forward model with the erasure mask, b)."""
    import torch

    from recon.models import build_model
    from recon.simulate import simulate

    sim = simulate(build_model("2d", psf), scene, erasure=erasure, noise=noise, seed=seed)
    return sim, build_model("2d", psf, mask=sim.mask), torch.as_tensor(sim.meas)


def run_case(psf: Any, scene: Any, erasure: float, noise: float, iters: int,
             reference: bool = True, seed: int = 0) -> dict[str, Any]:
    """Simulate one case and run auto, the oracle grid, the old rule and the reference."""
    case = simulate_case(psf, scene, erasure, noise, seed)
    sim, model, b = case
    out: dict[str, Any] = {"auto": run_auto(case, iters)}
    grid = {}
    for tau in ORACLE_TAUS:
        x, _ = _fista(model, b, tau, iters)
        grid[tau] = _score(sim.truth, x)
    best = max(grid, key=lambda t: grid[t][0])
    out["oracle"] = {"tau": best, "psnr_ssim": grid[best],
                     "grid": [[t, *v] for t, v in grid.items()]}
    x, _ = _fista(model, b, best, iters, restart="monotone")
    out["monotone"] = {"psnr_ssim": _score(sim.truth, x)}
    x, _ = _fista(model, b, best, iters, precondition="off")
    out["unpreconditioned"] = {"psnr_ssim": _score(sim.truth, x)}
    x, _ = _fista(model, b, best, iters, momentum="fista", precondition="off")
    out["fista"] = {"psnr_ssim": _score(sim.truth, x)}
    if reference:
        out.update(run_reference(case, best, iters))
    return out


def run_auto(case: Any, iters: int) -> dict[str, Any]:
    """``recon fista``'s default on one case (:func:`simulate_case`): the automatic choice,
    then FISTA-TV with it."""
    from recon.autotau import choose_tau

    sim, model, b = case
    # as `recon fista` does (recon.autotau.resolve), also below 100 iterations
    choice = choose_tau(model, b, max_iter=iters, min_iter=min(100, iters),
                        patience=max(min(100, iters), 10), check_every=min(10, iters))
    x, wall = _fista(model, b, choice.tau, choice.iterations)
    return {"tau": choice.tau, "iterations": choice.iterations, "psnr_ssim": _score(
        sim.truth, x), "search_s": choice.cost_s, "recon_s": wall,
        "search_iterations": choice.total_iterations,
        "holdout_block": choice.settings["holdout_block"],
        "curve": [[t, e] for t, e, _ in choice.curve]}


def run_reference(case: Any, tau: float, iters: int) -> dict[str, Any]:
    """The accurate reference at ``tau`` on one case (:func:`simulate_case`): 1000 and
    ``iters`` iterations, 50 inner prox steps."""
    sim, model, b = case
    acc = {"restart": "none", "prox_iters": 50, "momentum": "fista", "precondition": "off"}
    x, wall = _fista(model, b, tau, 1000, **acc)
    out: dict[str, Any] = {"reference": {"psnr_ssim": _score(sim.truth, x), "wall_s": wall}}
    x, _ = _fista(model, b, tau, iters, **acc)
    out["reference_same_iters"] = {"psnr_ssim": _score(sim.truth, x)}
    return out


def _mean(v: list[float]) -> float:
    return sum(v) / len(v) if v else math.nan


def tables(cases: list[dict[str, Any]]) -> str:
    """Markdown tables from the cached cases: per level, then the summary."""
    levels: dict[tuple[float, float], list[dict[str, Any]]] = {}
    for c in cases:
        levels.setdefault((c["noise"], c["erasure"]), []).append(c)
    ref = all("reference" in c for c in cases)
    head = ("| noise | erasures | scenes | auto PSNR | oracle PSNR | auto SSIM | oracle SSIM | "
            "worst miss (dB) | auto tau (median) | oracle tau (median) | auto iterations | "
            "search s |")
    if ref:
        head += (" reference 1000x50 PSNR | ref 500x50 PSNR | unpreconditioned (previous default) "
                 "PSNR | FISTA momentum PSNR | monotone rule PSNR |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for (noise, er), cs in sorted(levels.items()):
        def m(key: str, i: int, cs: list[dict[str, Any]] = cs) -> float:
            return _mean([c[key]["psnr_ssim"][i] for c in cs])

        miss = max(c["oracle"]["psnr_ssim"][0] - c["auto"]["psnr_ssim"][0] for c in cs)
        taus_a = sorted(c["auto"]["tau"] for c in cs)
        taus_o = sorted(c["oracle"]["tau"] for c in cs)
        row = (f"| {noise:g} | {er:.0%} | {len(cs)} | {m('auto', 0):.2f} | {m('oracle', 0):.2f} "
               f"| {m('auto', 1):.3f} | {m('oracle', 1):.3f} | {miss:.2f} | "
               f"{taus_a[len(taus_a) // 2]:.2g} | {taus_o[len(taus_o) // 2]:.2g} | "
               f"{_mean([c['auto']['iterations'] for c in cs]):.0f} | "
               f"{_mean([c['auto']['search_s'] for c in cs]):.1f} |")
        if ref:
            row += (f" {m('reference', 0):.2f} | {m('reference_same_iters', 0):.2f} | "
                    f"{m('unpreconditioned', 0):.2f} | {m('fista', 0):.2f} | "
                    f"{m('monotone', 0):.2f} |")
        lines.append(row)
    misses = [c["oracle"]["psnr_ssim"][0] - c["auto"]["psnr_ssim"][0] for c in cases]
    summary = [
        "",
        f"Over {len(cases)} cases: auto {_mean([c['auto']['psnr_ssim'][0] for c in cases]):.2f} "
        f"dB / SSIM {_mean([c['auto']['psnr_ssim'][1] for c in cases]):.3f}, oracle "
        f"{_mean([c['oracle']['psnr_ssim'][0] for c in cases]):.2f} dB / SSIM "
        f"{_mean([c['oracle']['psnr_ssim'][1] for c in cases]):.3f}; auto misses the oracle by "
        f"{_mean(misses):.2f} dB on average, by more than 0.5 dB in "
        f"{sum(v > 0.5 for v in misses)} cases, more than 1.5 dB in "
        f"{sum(v > 1.5 for v in misses)}; worst {max(misses):.2f} dB; auto beats the grid in "
        f"{sum(v < 0 for v in misses)} cases.",
    ]
    if ref:
        gap = [c["reference"]["psnr_ssim"][0] - c["oracle"]["psnr_ssim"][0] for c in cases]
        gap_eq = [c["reference_same_iters"]["psnr_ssim"][0] - c["oracle"]["psnr_ssim"][0]
                  for c in cases]
        def below(key: str, sel: list[dict[str, Any]]) -> str:
            g = [c["reference"]["psnr_ssim"][0] - c[key]["psnr_ssim"][0] for c in sel]
            return f"{_mean(g):.2f} dB (worst {max(g):.2f})" if g else "n/a"

        noisy = [c for c in cases if c["noise"] > 0]
        clean = [c for c in cases if c["noise"] == 0]
        summary.append(
            "At the oracle tau, the default after 500 iterations is "
            f"{_mean(gap):.2f} dB below the reference (1000 FISTA iterations x 50 inner prox "
            f"steps; worst {max(gap):.2f} dB) and {_mean(gap_eq):.2f} dB below the same reference "
            f"stopped at 500 iterations (worst {max(gap_eq):.2f} dB).")
        summary.append(
            "Below the reference, mean (worst) over the noise-free / noisy cases: default "
            f"{below('oracle', clean)} / {below('oracle', noisy)}; without the preconditioner "
            f"(previous default) {below('unpreconditioned', clean)} / "
            f"{below('unpreconditioned', noisy)}; FISTA momentum, no preconditioner "
            f"{below('fista', clean)} / {below('fista', noisy)}; "
            f"monotone rule {below('monotone', clean)} / {below('monotone', noisy)}.")
    return "\n".join(lines + summary)


def restart_table(iters: int, tau: float = 3e-5) -> str:
    """PSNR, final objective and restarts of each restart rule against an accurate run."""
    from recon import samples
    from recon.fista import Fista

    psf = samples.tutorial_psf()
    off = {"precondition": "off"}
    rules: dict[str, dict[str, Any]] = {"monotone": {"restart": "monotone"},
             "FISTA gradient": {"restart": "gradient", "momentum": "fista", **off},
             "FISTA none": {"restart": "none", "momentum": "fista", **off},
             "POGM gradient": {"restart": "gradient", **off},
             "POGM none": {"restart": "none", **off},
             "POGM gradient, preconditioned (default)": {},
             "accurate": {"restart": "none", "prox_iters": 50, "momentum": "fista",
                          "precondition": "off"}}
    lines = ["| erasures | scene | " + " | ".join(f"{r} PSNR / objective / restarts"
                                                 for r in rules) + " |",
             "|---|---|" + "---|" * len(rules)]
    for er in (0.99, 0.0):
        for name in samples.lensed_scene_names():
            sim, model, b = simulate_case(psf, samples.lensed_scene(name), er, 0.01)
            cells = []
            for kw in rules.values():
                solver = Fista(model.op, b, tau=tau, max_iter=iters, tol=0.0, **kw)
                n = sum(st.restarted for st in solver.steps())
                cells.append(f"{_score(sim.truth, solver.x.numpy())[0]:.2f} / "
                             f"{solver.objective:.4g} / {n}")
            lines.append(f"| {er:.0%} | {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


@contextlib.contextmanager
def _rise_rule(rise: float, made: list[Any] | None = None) -> Iterator[None]:
    """FISTA-TV with its rise rule at ``rise`` (``math.inf``: off) for the block, every solver
    made in it appended to ``made`` (to count the times the rule fired: ``prox_raises``)."""
    from recon import fista as fista_mod

    saved, init = fista_mod.PLAIN_RISE, fista_mod.Fista.__init__

    def recording_init(self: Any, *a: Any, **k: Any) -> None:
        init(self, *a, **k)
        if made is not None:
            made.append(self)

    fista_mod.PLAIN_RISE = rise
    fista_mod.Fista.__init__ = recording_init  # type: ignore[method-assign]
    try:
        yield
    finally:
        fista_mod.PLAIN_RISE = saved
        fista_mod.Fista.__init__ = init  # type: ignore[method-assign]


def prox_table(iters: int) -> str:
    """The rise rule of FISTA-TV's plain phase (recon.fista ``PLAIN_RISE``): a plain step that
    raises the objective 10 % above its lowest doubles the inner TV iterations. Per case: the
    objective and PSNR after ``iters`` iterations with the rule (the default), with the rule
    off, and with 50 inner iterations (the rule cannot fire: 50 is above its cap); then
    ``recon fista``'s default (the automatic choice and its run) with and without the rule."""
    from recon import samples
    from recon.fista import PLAIN_RISE, Fista

    psf = samples.tutorial_psf()
    lines = ["| erasures | tau | default: objective / PSNR / inner iterations at the end | "
             "rule off | 50 inner iterations |", "|---|---|---|---|---|"]
    for er in (0.0, 0.9, 0.99):
        sim, model, b = simulate_case(psf, samples.lensed_scene("im408"), er, 0.01)
        for tau in (1e-4, 1e-3, 1e-2):
            cells = []
            for rise, kw in ((PLAIN_RISE, {}), (math.inf, {}), (PLAIN_RISE, {"prox_iters": 50})):
                with _rise_rule(rise):
                    solver = Fista(model.op, b, tau=tau, max_iter=iters, tol=0.0, **kw)
                    solver.run()
                cells.append(f"{solver.objective:.4g} / "
                             f"{_score(sim.truth, solver.x.numpy())[0]:.2f} / "
                             f"{solver.prox_iters}")
            lines.append(f"| {er:.0%} | {tau:g} | " + " | ".join(cells) + " |")
    # at 99 % erasures, where the rule fires most
    lines += ["", "| scene | noise | automatic tau / iterations / PSNR | rule off | "
              "times the rule fired (search and run) |", "|---|---|---|---|---|"]
    for name in samples.lensed_scene_names():
        for noise in NOISES:
            case = simulate_case(psf, samples.lensed_scene(name), 0.99, noise)
            res = []
            for rise in (PLAIN_RISE, math.inf):
                made: list[Any] = []
                with _rise_rule(rise, made):
                    auto = run_auto(case, iters)
                res.append((f"{auto['tau']:.3g} / {auto['iterations']} / "
                            f"{auto['psnr_ssim'][0]:.3f}", sum(s.prox_raises for s in made)))
            lines.append(f"| {name} | {noise:g} | {res[0][0]} | {res[1][0]} | {res[0][1]} |")
    return "\n".join(lines)


MOMENTUM_CASES = (("im408", 0.0, 0.0, 1e-6), ("im740", 0.0, 0.0, 1e-6), ("im65", 0.0, 0.0, 1e-6),
                  ("im408", 0.5, 0.0, 3e-6), ("im740", 0.9, 0.0, 3e-6), ("im65", 0.99, 0.0, 3e-6),
                  ("im408", 0.0, 0.01, 1e-4), ("im740", 0.9, 0.01, 3e-5),
                  ("im65", 0.99, 0.01, 1e-5))


def _fixed_tau_case(psf: Any, name: str, erasure: float, noise: float, tau: float,
                    keep: bool = False) -> Any:
    """One fixed-tau case: the simulation, its model, the measurement and the reference PSNR
    (1000 FISTA iterations x 50 inner prox steps, no restart); with ``keep`` also the
    reference's estimate."""
    from recon import samples

    sim, model, b = simulate_case(psf, samples.lensed_scene(name), erasure, noise)
    ref_x = _fista(model, b, tau, 1000, restart="none", prox_iters=50, momentum="fista",
                   precondition="off")[0]
    ref = _score(sim.truth, ref_x)[0]
    return (sim, model, b, ref, ref_x) if keep else (sim, model, b, ref)


def _objective_of(model: Any, b: Any, tau: float, x: Any) -> float:
    """FISTA-TV's objective 0.5 ||A x - b||^2 + tau TV(x) at ``x`` (x >= 0 assumed)."""
    import torch

    from recon.fista import Fista

    return Fista(model.op, b, tau=tau, x0=torch.as_tensor(x), max_iter=0).objective


KAPPAS = (0.3, 0.1, 0.03, 0.01)
KAPPAS_ALL = (0.1, 0.03)
RHOS = (0.001, 0.01, 0.1)


def momentum_table(iters: int) -> str:
    """PSNR after ``iters`` iterations minus the reference's, per variant and case."""
    from recon import samples
    from recon.fista import Fista

    psf = samples.tutorial_psf()
    off = {"precondition": "off"}
    variants: dict[str, dict[str, Any]] = {
        "FISTA 1/L, gradient restart": {"momentum": "fista", **off},
        "FISTA 1/L, no restart": {"momentum": "fista", "restart": "none", **off},
        "POGM 1/L, no restart": {"restart": "none", **off},
        "POGM 1/L, gradient restart (previous default)": {**off},
        "FISTA, gradient restart, preconditioned": {"momentum": "fista"},
        "POGM, gradient restart, preconditioned (default)": {},
    }
    cols = [f"{n} {er:.0%} {'noisy' if nz else 'clean'} tau {t:g}"
            for n, er, nz, t in MOMENTUM_CASES]
    cells: dict[str, list[float]] = {v: [] for v in variants}
    refs = []
    for name, er, noise, tau in MOMENTUM_CASES:
        sim, model, b, ref = _fixed_tau_case(psf, name, er, noise, tau)
        refs.append(ref)
        for v, kw in variants.items():
            solver = Fista(model.op, b, tau=tau, max_iter=iters, tol=0.0, **kw)
            for _ in solver.steps():
                pass
            if solver.guard_resets:
                raise AssertionError(f"divergence guard fired: {v}, {name} {er} {noise}")
            cells[v].append(_score(sim.truth, solver.x.numpy())[0] - ref)
    clean = [i for i, c in enumerate(MOMENTUM_CASES) if c[2] == 0]
    noisy = [i for i, c in enumerate(MOMENTUM_CASES) if c[2] > 0]
    lines = ["| variant | " + " | ".join(cols) + " | mean clean | mean noisy |",
             "|---|" + "---|" * (len(cols) + 2),
             "| reference PSNR (dB) | " + " | ".join(f"{r:.2f}" for r in refs) + " | | |"]
    for v, d in cells.items():
        lines.append(f"| {v} | " + " | ".join(f"{x:+.2f}" for x in d) + " | "
                     f"{_mean([d[i] for i in clean]):+.2f} | {_mean([d[i] for i in noisy]):+.2f} |")
    return "\n".join(lines)


def convergence_table() -> str:
    """The noise-free 0 % cases: spectrum, the plain step's PSNR over iterations, the Fourier
    preconditioner at several damping levels (the solver's, recon.fista), ADMM-TV."""
    import numpy as np

    from recon import samples
    from recon.admm import Admm
    from recon.fista import relative_spectrum
    from recon.models import build_model
    from recon.operators import Conv2D

    psf = samples.tutorial_psf()
    lines = []
    probe = build_model("2d", psf)
    conv = next(o for o in probe.op.ops if isinstance(o, Conv2D))
    r = np.sort(relative_spectrum(conv).double().numpy().ravel())[::-1]
    lines.append("Spectrum of the convolution on the padded grid (|H(f)|^2 / max): largest "
                 + ", ".join(f"{v:.2f}" for v in r[1:7]) + " after the DC; quantiles 99.9 % "
                 f"{np.quantile(r, 0.999):.4f}, 99 % {np.quantile(r, 0.99):.4f}, 50 % "
                 f"{np.quantile(r, 0.5):.1e}; power-iteration L of the cropped operator "
                 f"{probe.op.lipschitz():.3f} (unit-sum PSF)")
    pre_cols = " | ".join(f"preconditioned kappa {k:g}, 500" for k in KAPPAS)
    adm_cols = " | ".join(f"ADMM-TV rho {r:g}, 500" for r in RHOS)
    lines += ["", "PSNR minus the reference's (dB); objective relative to the reference's in "
              "brackets (+ = higher, i.e. worse)", "",
              "| case (noise 0, 0 %, tau 1e-6) | reference 1000x50 PSNR | "
              "unpreconditioned at 500 | "
              f"700 | 1000 | 1500 | {pre_cols} | {adm_cols} |",
              "|---|---|---|---|---|---|" + "---|" * (len(KAPPAS) + len(RHOS))]
    for name, er, noise, tau in MOMENTUM_CASES[:3]:
        sim, model, b, ref, ref_x = _fixed_tau_case(psf, name, er, noise, tau, keep=True)
        at: dict[int, float] = {}
        for n in (500, 700, 1000, 1500):  # separate runs: POGM's last step depends on max_iter
            at[n] = _score(sim.truth, _fista(model, b, tau, n, precondition="off")[0])[0] - ref
        f_ref = _objective_of(model, b, tau, ref_x)
        cells = []
        for kappa in KAPPAS:
            x = _fista(model, b, tau, 500, precondition=kappa)[0]
            cells.append(f"{_score(sim.truth, x)[0] - ref:+.2f} "
                         f"({_objective_of(model, b, tau, x) / f_ref - 1:+.1e})")
        for rho in RHOS:
            admm = Admm(model, b, tau=tau, max_iter=500, tol=0.0, rho=rho)
            for _ in admm.steps():
                pass
            cells.append(f"{_score(sim.truth, admm.x.numpy())[0] - ref:+.2f}")
        lines.append(f"| {name} | {ref:.2f} | " + " | ".join(f"{at[n]:+.2f}" for n in at)
                     + " | " + " | ".join(cells) + " |")
    lines += ["", "All nine fixed-tau cases of the momentum check, 500 iterations: PSNR minus the "
              "reference's (objective relative to the reference's)", "",
              "| case | tau | reference PSNR | unpreconditioned | " + " | ".join(
                  f"preconditioned kappa {k:g}" for k in KAPPAS_ALL) + " |",
              "|---|---|---|---|" + "---|" * len(KAPPAS_ALL)]
    for name, er, noise, tau in MOMENTUM_CASES:
        sim, model, b, ref, ref_x = _fixed_tau_case(psf, name, er, noise, tau, keep=True)
        f_ref = _objective_of(model, b, tau, ref_x)
        plain = _fista(model, b, tau, 500, precondition="off")[0]
        cells = [f"{_score(sim.truth, plain)[0] - ref:+.2f}"]
        for kappa in KAPPAS_ALL:
            x = _fista(model, b, tau, 500, precondition=kappa)[0]
            cells.append(f"{_score(sim.truth, x)[0] - ref:+.2f} "
                         f"({_objective_of(model, b, tau, x) / f_ref - 1:+.1e})")
        lines.append(f"| {name} {er:.0%} {'noisy' if noise else 'clean'} | {tau:g} | "
                     f"{ref:.2f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def hand_table(iters: int) -> str:
    """The tutorial hand at 1/8 scale: held-out error over tau, the choice marked."""
    import torch

    from recon import samples
    from recon.autotau import choose_tau
    from recon.models import build_model

    psf = samples.tutorial_psf()
    meas = samples.tutorial_measurement()
    model = build_model("2d", psf)
    choice = choose_tau(model, torch.as_tensor(meas).reshape(model.meas_shape), max_iter=iters)
    best = min(e for _, e, _ in choice.curve)
    lines = [f"{choice.describe()}; {choice.total_iterations} iterations in all.", "",
             "| tau | held-out MSE | relative to the best | best at iteration | |",
             "|---|---|---|---|---|"]
    for t, e, i in choice.curve:
        bar = "#" * max(1, round(40 * min(1.0, (e / best - 1.0) / 0.5))) if e > best else ""
        mark = "**chosen**" if t == choice.tau else bar
        lines.append(f"| {t:.3g} | {e:.4g} | +{100 * (e / best - 1):.2f} % | {i} | {mark} |")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Run (or resume) the protocol and print (and optionally write) the tables."""
    import os

    tables_only = (args.restart_check or args.hand or args.momentum_check
                   or args.convergence_check or args.prox_check)
    if tables_only and args.out:
        raise ValueError("--out: the Markdown is written by the protocol run only, not with "
                         "--restart-check, --momentum-check, --convergence-check, "
                         "--prox-check or --hand "
                         "(their table is printed)")
    check_outputs(args, {"--out": args.out},
                  appended=None if tables_only else {"--cache": args.cache})
    if args.restart_check:
        bench_threads(args)
        print(restart_table(args.iters))
        return 0
    if args.hand:
        bench_threads(args)
        print(hand_table(args.iters))
        return 0
    if args.momentum_check:
        bench_threads(args)
        print(momentum_table(args.iters))
        return 0
    if args.prox_check:
        bench_threads(args)
        print(prox_table(args.iters))
        return 0
    if args.convergence_check:
        bench_threads(args)
        print(convergence_table())
        return 0

    from recon import samples

    choice = bench_threads(args)
    psf = samples.tutorial_psf()
    scenes = {n: samples.lensed_scene(n) for n in samples.lensed_scene_names()}
    erasures = (0.0, 0.9) if args.quick else ERASURES
    noises = (0.01,) if args.quick else NOISES
    cache = Path(args.cache)
    done: dict[tuple[str, float, float], dict[str, Any]] = {}
    for c in read_records(cache, "--cache", "protocol", RESULTS_VERSION, REQUIRED):
        # a case of another thread count is run again: the 'search s' column compares them
        if (c.get("iters") == args.iters and c.get("version") == CASE_VERSION
                and c.get("threads") == choice.threads):
            done[(c["scene"], c["erasure"], c["noise"])] = c
    t_all = time.perf_counter()
    for noise in sorted(noises, reverse=True):  # noisy cases first: they stop early
        for er in erasures:
            for name, scene in scenes.items():
                if (name, er, noise) in done:
                    c = done[(name, er, noise)]
                    redo_auto = "holdout_block" not in c["auto"]  # scattered held-out pixels
                    if not redo_auto and (args.no_reference or "reference" in c):
                        continue
                    case = simulate_case(psf, scene, er, noise)
                    if redo_auto:  # the rest of the case does not depend on the held-out design
                        c["auto"] = run_auto(case, args.iters)
                    if not (args.no_reference or "reference" in c):
                        c.update(run_reference(case, c["oracle"]["tau"], args.iters))
                    # the later line wins when read back
                    append_jsonl(cache, tagged("protocol", RESULTS_VERSION, c))
                    continue
                t0 = time.perf_counter()
                res = run_case(psf, scene, er, noise, args.iters,
                               reference=not args.no_reference)
                c = {"scene": name, "erasure": er, "noise": noise, "iters": args.iters,
                     "version": CASE_VERSION,
                     "threads": choice.threads, "wall_s": time.perf_counter() - t0,
                     "load": os.getloadavg()[0], **res}
                done[(name, er, noise)] = c
                # one line per finished case (append only)
                append_jsonl(cache, tagged("protocol", RESULTS_VERSION, c))
                print(f"noise {noise:g} erasure {er:.0%} {name}: auto "
                      f"{res['auto']['psnr_ssim'][0]:.2f} dB (tau {res['auto']['tau']:.2g}, "
                      f"{res['auto']['iterations']} it), oracle "
                      f"{res['oracle']['psnr_ssim'][0]:.2f} dB (tau {res['oracle']['tau']:g})",
                      file=sys.stderr)
    cases = [c for c in done.values() if c["noise"] in noises and c["erasure"] in erasures]
    table = tables(cases)
    print(table)
    if args.out:
        from recon.atomic import atomic_write_bytes

        header = (
            "# Simulation protocol: the default (tau auto) against the oracle tau\n\n"
            "Tutorial PSF at 1/8 scale (150x200, dark-subtracted, clipped, unit sum); the three\n"
            "lensed scenes (im408, im740, im65) as grayscale ground truth; measurement normalised\n"
            "to max 1, then Gaussian noise, then erasures (exactly round(f*N) pixels).\n"
            "**auto** is what `recon fista` does with no flags (tau and iterations chosen from\n"
            "held-out measured pixels, `recon/autotau.py`, then FISTA-TV from all measured\n"
            f"pixels); **oracle** the best PSNR over tau in {', '.join(map(str, ORACLE_TAUS))}\n"
            f"at {args.iters} iterations. PSNR/SSIM after a least-squares gain fit. 'search s'\n"
            f"is the automatic choice's own time per case (the reconstruction excluded), on\n"
            f"{choice.threads} torch thread(s) (every case of the table).\n"
            f"{machine_text(choice)}\n\n"
            f"Produced by `{command_line('protocol', args, add_arguments)}` "
            f"({time.perf_counter() - t_all:.0f} s in the last "
            "session; finished cases are cached in the JSON-lines file `--cache`).\n\n"
        )
        atomic_write_bytes(args.out, (header + table + "\n").encode())
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    add_arguments(parser)
    sys.exit(run(parser.parse_args()))
