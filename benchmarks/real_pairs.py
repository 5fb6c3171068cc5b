"""Real pairs: UDN against FISTA-TV and ADMM-TV on real DiffuserCam measurements with truth.

The four pairs of ``../shared/data/dlmd`` (measurement + aligned lensed truth + the estimated
effective PSF), in colour, at a reduced resolution (``--downsample 4``: 67x120, ``2``: 135x240),
with synthetic erasures of the measured pixels (0, 50, 90, 95, 99 %, one fixed seed per
level). The pairs are read through the project's loader (``recon.problem``) as a user would
read them: BGR files, stored upside-down (all flipped alike), the PSF on the padded 540x960
grid with zero shift at its centre (the sensor is embedded in the centre of that grid, the
rest masked out); the truth is the scene on the sensor-size field.

Methods, all scored against the lensed truth after a least-squares gain fit (PSNR, SSIM,
MS-SSIM with as many scales as the size allows):

- FISTA-TV, *automatic tau*: ``recon.autotau.choose_tau`` (held-out measured pixels choose
  tau and the iteration count, at most ``--fista-iters``), then the run on all measured pixels;
- FISTA-TV, *oracle tau*: the best (tau, iteration checkpoint) of the grid by PSNR against the
  truth (it uses the ground truth);
- ADMM-TV at the oracle tau;
- UDN (``recon.udn``), its iteration chosen without ground truth: held-out pixels (the
  runner's own ``best``), and the running variance of the output (ES-WMV, Wang et al. 2021,
  on the EMA estimate, window ``--wmv-window``), beside its final estimate; and a blend of
  the UDN with the automatic-tau FISTA result, the weight chosen on the UDN's held-out
  pixels (against a FISTA run at that tau that did not see them either).

Each case is appended to ``--results`` (JSON lines) as soon as it is done, so a long run can be
turned into the table at any time with ``--table-only``. ``--error-analysis`` adds where the
error against the truth is (by band of scale, and after removing a shading learned from the
other pairs: :func:`error_analysis`), from the images each case keeps.

    lenslesscam bench real-pairs --downsample 4 --udn-iters 500 --out docs/real-pairs.md

Each results record carries the format ``lenslesscam.bench.real-pairs`` (version
:data:`RESULTS_VERSION`) and its provenance; a file of another benchmark is refused.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections import deque
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from app.commands._options import (
    FRACTION,
    NONNEG,
    NONNEG_INT,
    POSITIVE,
    POSITIVE_INT,
    add_overwrite_option,
)
from benchmarks._cli import (
    append_jsonl,
    bench_threads,
    check_outputs,
    command_line,
    machine_text,
    read_records,
    tagged,
)

#: version of the records of ``--results`` (format ``lenslesscam.bench.real-pairs``)
RESULTS_VERSION = 1
#: the default run's time (``--help``; docs/udn.md: 2.5-3.5 minutes of UDN per case at 1/4
#: resolution, 1 thread; 1 h 19 min for the 20 cases)
DURATION = ("long on a 2-core CPU: 20 cases, each FISTA-TV and ADMM-TV grids and at the default "
            "300 UDN iterations 18-260 s of UDN with the load (docs/udn.md); --udn-iters 3000: "
            "hours")

PAIRS = ("im65", "im408", "im740", "im1000")
ERASURES = (0.0, 0.5, 0.9, 0.95, 0.99)
TAUS = (1e-5, 3e-5, 1e-4, 3e-4, 1e-3, 3e-3, 1e-2)
FISTA_CHECKPOINTS = (100, 200)
BLEND_WEIGHTS = (0.0, 0.25, 0.5, 0.75, 1.0)
#: the UDN iterations at which the held-out error of its mix with FISTA-TV is checked
MIX_EVERY = 10
#: the UDN iterations whose estimates are averaged (iterate averaging along one run)
SNAPSHOT_EVERY = 500
#: UDN variants of ``--lever`` (see make_runner)
LEVERS = ("none", "precondition", "channel-gain", "block-holdout", "deep-decoder", "sensor-gain",
          "fista-input")
#: ``sensor-gain``: control points of the smooth gain field per colour channel along the
#: measured extent's shorter side (bilinear between them, so it varies over about a quarter
#: of that side: the scale of the shading in the error analysis)
SENSOR_GAIN_POINTS = 5
#: ``sensor-gain``: the field stays within [1 / this, this] (a free field fitted the scene's
#: own smooth envelope: 0.15-1.48 on im65 at 0 %, 3.3 dB lost; the field FISTA-TV's oracle
#: result asks for on the same pair lies within 0.77-1.02)
SENSOR_GAIN_MAX = 1.25


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options."""
    p.add_argument("--downsample", type=int, choices=[1, 2, 4], default=4,
                   help="4: 67x120, 2: 135x240, 1: the dataset's 270x480 (4)")
    p.add_argument("--pairs", nargs="+", default=None, choices=list(PAIRS),
                   help="which dlmd pairs to run (default all; with --table-only: the cases "
                   "of the table)")
    p.add_argument("--erasures", nargs="+", type=FRACTION, default=None,
                   help="erasure fractions to test (default 0 0.5 0.9 0.95 0.99; with "
                   "--table-only: the cases of the table)")
    p.add_argument("--fista-iters", type=POSITIVE_INT, default=max(FISTA_CHECKPOINTS),
                   help="FISTA iteration limit")
    # UDN settings: None = the default of recon.udn (NetworkConfig / UDNConfig), filled in
    # by run() (not here: building the CLI must not import torch)
    p.add_argument("--udn-iters", type=POSITIVE_INT, default=300, help="UDN iterations (300)")
    p.add_argument("--channels", type=POSITIVE_INT, default=None, help="UDN channels")
    p.add_argument("--scales", type=POSITIVE_INT, default=None, help="UDN scales")
    p.add_argument("--skip", type=NONNEG_INT, default=None, help="UDN skip channels")
    p.add_argument("--headroom", type=POSITIVE, default=None, help="UDN gain headroom")
    p.add_argument("--lr", type=POSITIVE, default=None, help="UDN learning rate")
    p.add_argument("--ema", type=FRACTION, default=None, help="UDN EMA decay")
    p.add_argument("--tv-weight", type=NONNEG, default=None, help="UDN TV loss weight")
    p.add_argument("--reg-noise", type=NONNEG, default=None,
                   help="UDN input regularisation noise std")
    p.add_argument("--holdout", type=FRACTION, default=0.1,
                   help="held-out fraction of the measured pixels (0.1)")
    p.add_argument("--wmv-window", type=POSITIVE_INT, default=50, help="ES-WMV window (50)")
    p.add_argument("--warm-start", type=NONNEG_INT, default=0, metavar="N",
                   help="first fit the UDN's output to the automatic-tau FISTA-TV result of "
                   "the fitted pixels for N iterations (0: none)")
    p.add_argument("--seeds", type=POSITIVE_INT, default=1,
                   help="UDN seeds: with N > 1, also the ensemble, the average of the N seeds' "
                   "held-out choices (each seed holds out its own pixels; recon.udn.ensemble)")
    p.add_argument("--lever", choices=LEVERS, default="none",
                   help="a UDN variant measured here, not in recon.udn: 'precondition' "
                   "multiplies the gradient of the output by FISTA's Fourier preconditioner; "
                   "'channel-gain' gives each colour channel its own learnable output gain; "
                   "'block-holdout' holds out whole blocks of the sensor; 'deep-decoder' "
                   "replaces the network by a deep decoder; 'sensor-gain' learns a smooth "
                   "gain field on the sensor with the network; 'fista-input' feeds the network the "
                   "automatic-tau FISTA-TV result of the fitted pixels as the first channels of "
                   "its input (none)")
    p.add_argument("--no-udn", action="store_true", help="FISTA and ADMM only")
    p.add_argument("--threads", type=POSITIVE_INT, default=None,
                   help="torch threads (default: the global --threads, else the thread "
                   "policy, recon.threads); a results file holds one count")
    p.add_argument("--device", default="cpu",
                   help="where FISTA, ADMM and the UDN run: cpu, cuda, cuda:N, mps or auto "
                   "(cpu; the scores are computed on the CPU either way)")
    p.add_argument("--data", default=None, help="the dlmd folder (default: the shared one)")
    p.add_argument("--results", default="real-pairs.jsonl",
                   help="JSON lines, one per case, appended (real-pairs.jsonl)")
    p.add_argument("--figure", default=None, help="write the PNG figure here")
    p.add_argument("--time-threads", type=POSITIVE_INT, default=0, metavar="N",
                   help="only time N UDN iterations per setting at 1 and 2 torch threads "
                   "(interleaved, 3 rounds) on the first pair, and print the seconds per "
                   "iteration; on a GPU (--device cuda) float32 against bf16 instead of threads, "
                   "and N FISTA-TV iterations")
    p.add_argument("--table-only", action="store_true",
                   help="do not run: make the table (and figure) from --results")
    p.add_argument("--out", default=None, help="write the Markdown here")
    p.add_argument("--error-analysis", action="store_true",
                   help="also where the error against the truth is, from the kept images: "
                   "by band of scale (fine / mid / smooth, beside the truth's own content), "
                   "and the PSNR once the shading learned from the other pairs is removed "
                   "(leave one pair out)")
    add_overwrite_option(p)


# ---------------------------------------------------------------------------------------------
# data
# ---------------------------------------------------------------------------------------------


@dataclass
class Pair:
    """One pair at the reconstruction resolution, upright RGB (as ``recon.problem`` loads it).

    ``psf`` (3, Ph, Pw) on the padded grid; ``meas`` (3, Ph, Pw) the measurement (max 1)
    embedded in its window of the padded grid; ``window`` (Ph, Pw) 1 where the sensor is;
    ``truth`` (3, h, w) the lensed image on the sensor-size field; ``origin`` the window's
    first row and column.
    """

    name: str
    psf: Any
    meas: Any
    window: Any
    truth: Any
    origin: tuple[int, int]


def data_dir(path: str | None = None) -> Path:
    """The dlmd folder."""
    if path is not None:
        return Path(path)
    from recon.samples import shared_data_dir

    base = shared_data_dir()
    if base is None:
        raise FileNotFoundError("no shared data folder found (LENSLESSCAM_SHARED_DATA, "
                                "shared/data or ../shared/data): set LENSLESSCAM_SHARED_DATA "
                                "or pass --data")
    return base / "dlmd"


def pair_files(name: str, folder: Path) -> dict[str, Path]:
    """The dataset's files of one pair: ``measurement``, ``truth``, ``psf``."""
    return {"measurement": folder / f"diffuser_{name}.npy",
            "truth": folder / f"lensed_{name}.npy",
            "psf": folder / "psf_estimated_padded_bgr.npy"}


def load_pair(name: str, files: dict[str, Path], downsample: int) -> Pair:
    """Read a pair in the dataset's layout through the project's loader (recon.problem).

    BGR files, stored upside-down (flipped here, all alike, so the arrays are upright RGB),
    the PSF on the padded grid (the loader embeds the sensor in its centre and masks the rest).
    """
    import numpy as np

    from recon.problem import ProblemSpec, load_problem

    spec = ProblemSpec(meas=str(files["measurement"]), psf=str(files["psf"]),
                       truth=str(files["truth"]), downsample=downsample, color="rgb",
                       channel_order="bgr", flip_rows=True, field="sensor")
    prob = load_problem(spec)
    if prob.mask is None or prob.truth is None:
        raise ValueError(f"{name}: expected a padded-grid PSF and a truth")
    rows = np.flatnonzero(prob.mask.any(axis=1))
    cols = np.flatnonzero(prob.mask.any(axis=0))
    return Pair(name, prob.psf, prob.meas, prob.mask, prob.truth[:, 0],
                (int(rows[0]), int(cols[0])))


def erasure_seed(erasure: float) -> int:
    """The fixed seed of an erasure level."""
    return 1000 + round(erasure * 1000)


def sensor_mask(pair: Pair, erasure: float) -> Any:
    """The measured pixels (Ph, Pw): the window minus the erased fraction of it."""
    import numpy as np

    from recon.simulate import erasure_mask

    h, w = pair.truth.shape[1:]
    r0, c0 = pair.origin
    mask = np.zeros_like(pair.window)
    mask[r0:r0 + h, c0:c0 + w] = erasure_mask((h, w), erasure, seed=erasure_seed(erasure))
    return mask


# ---------------------------------------------------------------------------------------------
# scoring
# ---------------------------------------------------------------------------------------------


def ms_ssim_scales(shape: tuple[int, ...]) -> int:
    """As many MS-SSIM scales (at most 5) as the image size allows."""
    from recon.metrics import ms_ssim_min_size

    n = 5
    while n > 1 and min(shape[-2:]) < ms_ssim_min_size(n):
        n -= 1
    return n


def scores(truth: Any, est: Any) -> dict[str, float | None]:
    """PSNR, SSIM, MS-SSIM after a least-squares gain fit (scene (C, H, W) or (C, 1, H, W))."""
    import inspect

    import numpy as np

    from recon.metrics import gain_fit, ms_ssim, psnr, ssim

    e = np.asarray(est, dtype=np.float32).reshape(truth.shape)
    g = gain_fit(truth, e)[0]
    out: dict[str, float | None] = {"psnr": psnr(truth, g), "ssim": ssim(truth, g)}
    n = ms_ssim_scales(truth.shape)
    if "scales" in inspect.signature(ms_ssim).parameters:
        out["ms_ssim"] = ms_ssim(truth, g, scales=n)  # type: ignore[call-arg]
        out["ms_ssim_scales"] = n
    else:  # recon.metrics without fewer scales: only where 5 fit
        out["ms_ssim"] = ms_ssim(truth, g) if n == 5 else None
        out["ms_ssim_scales"] = 5 if n == 5 else None
    return out


def psnr_only(truth: Any, est: Any) -> float:
    """PSNR after a gain fit."""
    import numpy as np

    from recon.metrics import gain_fit, psnr

    e = np.asarray(est, dtype=np.float32).reshape(truth.shape)
    return float(psnr(truth, gain_fit(truth, e)[0]))


# ---------------------------------------------------------------------------------------------
# methods
# ---------------------------------------------------------------------------------------------


def _fista(model: Any, b: Any, tau: float, iters: int) -> dict[int, tuple[Any, float]]:
    """FISTA-TV estimates (C, 1, h, w) and wall times at the checkpoints."""
    import torch

    from recon.fista import Fista

    solver = Fista(model.op, torch.as_tensor(b), tau=tau, max_iter=iters, tol=0.0)
    out: dict[int, tuple[Any, float]] = {}
    t0 = time.perf_counter()
    for step in solver.steps():
        if step.iteration in FISTA_CHECKPOINTS or step.iteration == iters or solver.done:
            out[step.iteration] = (solver.x.detach().cpu().numpy().copy(),
                                   time.perf_counter() - t0)
    last = max(out)
    for c in FISTA_CHECKPOINTS:
        if c <= iters and c not in out:
            out[c] = out[last]
    return out


def _heldout_err(model: Any, x: Any, b: Any, heldout: Any) -> float:
    """Mean squared prediction error on the held-out pixels."""
    import numpy as np
    import torch

    with torch.no_grad():
        xt = torch.as_tensor(np.asarray(x, dtype=np.float32)).to(model.op.device)
        pred = model.op.apply(xt).cpu().numpy()
    r = (pred - b)[heldout]
    return float(np.mean(r * r))


def _fitted_pixels_fista(pair: Pair, b: Any, fit: Any, args: argparse.Namespace,
                         min_iter: int) -> Any:
    """FISTA-TV with the automatic tau from a UDN run's fitted pixels only: the image its warm
    start and its blend use, so that nothing tuned on its held-out pixels reaches them."""
    import torch

    from recon.autotau import choose_tau
    from recon.models import build_model

    model = build_model("2d", pair.psf, mask=fit, field=tuple(pair.truth.shape[1:]),
                        device=args.device)
    bf = b * fit
    choice = choose_tau(model, torch.as_tensor(bf), max_iter=args.fista_iters,
                        min_iter=min_iter, holdout=args.holdout, seed=0)
    return _fista(model, bf, choice.tau, choice.iterations)[choice.iterations][0]


def run_case(pair: Pair, erasure: float, args: argparse.Namespace,
             keep: dict[str, Any]) -> dict[str, Any]:
    """Every method on one (pair, erasure level); returns the row, fills ``keep`` with images."""
    import numpy as np
    import torch

    from recon.admm import Admm
    from recon.models import build_model
    from recon.trade import peak_mb_since, peak_start
    from recon.udn.network import NetworkConfig
    from recon.udn.runner import UDNConfig, describe_device

    truth = pair.truth
    h, w = truth.shape[1:]
    mask = sensor_mask(pair, erasure)
    b = (pair.meas * mask).astype(np.float32)
    model = build_model("2d", pair.psf, mask=mask, field=(h, w), device=args.device)
    row: dict[str, Any] = {"pair": pair.name, "erasure": erasure, "shape": [3, h, w],
                           "measured": int(mask.sum()), "device": describe_device(args.device)}

    # the held-out pixels: the UDN runner's own (so FISTA's tau and the blend use the same)
    net = NetworkConfig(channels=args.channels, scales=args.scales, skip_channels=args.skip)
    cfg = UDNConfig(max_iter=args.udn_iters, holdout=args.holdout, patience=10**9, min_iter=0,
                    headroom=args.headroom, lr=args.lr, ema=args.ema, tv_weight=args.tv_weight,
                    reg_noise=args.reg_noise, seed=0, average_every=SNAPSHOT_EVERY)
    runner = make_runner(model, b, net, cfg, args.lever)
    heldout = runner.heldout.cpu().numpy()
    fit_mask = (runner.fit.cpu().numpy()).astype(np.float32)
    row["heldout_pixels"] = int(heldout.sum())

    # FISTA-TV over the tau grid on all measured pixels (the oracle picks from it)
    from recon.autotau import choose_tau

    grid: dict[float, dict[int, tuple[Any, float]]] = {}
    base = peak_start(args.device)
    for tau in TAUS:
        grid[tau] = _fista(model, b, tau, args.fista_iters)
    row["fista_peak_mb"] = peak_mb_since(base)
    last = args.fista_iters
    cps = sorted({c for c in FISTA_CHECKPOINTS if c <= last} | {last})
    best = max(((t, c) for t in TAUS for c in cps),
               key=lambda tc: psnr_only(truth, grid[tc[0]][tc[1]][0]))
    t_or, c_or = best
    x_or, wall_or = grid[t_or][c_or]
    row["fista_oracle"] = dict(scores(truth, x_or), tau=t_or, iterations=c_or, wall_s=wall_or)
    # automatic tau (recon.autotau, issue 9: its own held-out pixels), then the run on all
    # measured pixels with the chosen tau and iteration count
    t0 = time.perf_counter()
    auto = choose_tau(model, torch.as_tensor(b), max_iter=args.fista_iters,
                      min_iter=min(cps), holdout=args.holdout, seed=0)
    t_auto = auto.tau
    auto_run = _fista(model, b, t_auto, auto.iterations)
    x_auto = auto_run[auto.iterations][0]
    row["fista_auto"] = dict(scores(truth, x_auto), tau=t_auto, iterations=auto.iterations,
                             wall_s=time.perf_counter() - t0, rule=auto.rule,
                             note="wall: the tau search and the final run")
    row["fista_tau_curve"] = {f"{t:g}": psnr_only(truth, grid[t][last][0]) for t in TAUS}
    keep["truth"], keep["fista_auto"], keep["fista_oracle"] = truth, x_auto, x_or

    # ADMM-TV at the oracle tau
    base = peak_start(args.device)
    admm = Admm(model, torch.as_tensor(b), tau=t_or, max_iter=args.fista_iters, tol=0.0)
    t0 = time.perf_counter()
    for _ in admm.steps():
        pass
    row["admm"] = dict(scores(truth, admm.x.detach().cpu().numpy()), tau=t_or,
                       iterations=args.fista_iters, wall_s=time.perf_counter() - t0,
                       peak_mb=peak_mb_since(base))

    if args.no_udn:
        return row
    # FISTA-TV from the UDN's fitted pixels only, its tau chosen on them too (for the warm
    # start and the blend weight, chosen on the UDN's held-out pixels, which it must not see)
    x_fit = _fitted_pixels_fista(pair, b, fit_mask, args, min(cps))
    if args.lever == "fista-input":
        fista_input(runner, x_fit)
    base = peak_start(args.device)
    if args.warm_start:
        row["udn_warm_start"] = {"iterations": args.warm_start,
                                 "mse": runner.warm_start(x_fit, args.warm_start)}
    # the running variance of the estimate (ES-WMV) where the estimate is (on a GPU: there)
    window: deque[Any] = deque(maxlen=args.wmv_window)
    wmv_best: tuple[float, int, Any] | None = None
    curve: dict[int, float] = {}
    curve_wall: dict[int, float] = {}
    hcurve: dict[int, float] = {}
    wmv_curve: dict[int, float] = {}
    # the averaged recipe's own stop: the held-out error of the half-and-half mix of the
    # network's estimate and FISTA-TV of the fitted pixels (neither saw the held-out pixels)
    xf_t = torch.as_tensor(np.asarray(x_fit, dtype=np.float32)).to(runner.device)
    mix_best: tuple[float, int, Any] | None = None
    mix_hcurve: dict[int, float] = {}
    mix_curve: dict[int, float] = {}
    for s in runner.steps():
        # the runner's estimate (its EMA; ema 0 keeps the last output); None only before a
        # first iteration that was not restored
        est = runner.ema if runner.ema is not None else torch.as_tensor(
            runner.final_estimate()).to(runner.device)
        window.append(est.detach().clone())
        if len(window) == args.wmv_window:
            with torch.no_grad():
                var = float(torch.stack(list(window)).var(dim=0, unbiased=False).mean())
            if s.iteration % 10 == 0:
                wmv_curve[s.iteration] = var
            if wmv_best is None or var < wmv_best[0]:
                wmv_best = (var, s.iteration, window[-1])
        if s.heldout is not None and (s.iteration % MIX_EVERY == 0 or runner.done):
            merr = runner.heldout_error(0.5 * (est + xf_t))
            if merr is not None:
                mix_hcurve[s.iteration] = merr
                if mix_best is None or merr < mix_best[0]:
                    mix_best = (merr, s.iteration, est.detach().clone())
        if s.iteration % 50 == 0 or runner.done:
            curve[s.iteration] = psnr_only(truth, est.detach().cpu().numpy())
            mix_curve[s.iteration] = psnr_only(
                truth, 0.5 * (est.detach().cpu().numpy() + x_auto))
            curve_wall[s.iteration] = runner.elapsed_s
            if s.heldout is not None:
                hcurve[s.iteration] = s.heldout
    window.clear()
    peak = peak_mb_since(base)
    final = runner.final_estimate()
    sel = runner.best_estimate()
    with torch.no_grad():
        raw = runner.G.raw().float()[0, :, :h, :w]
        clipped = float((raw >= 0.99).float().mean())
    row["udn"] = dict(scores(truth, sel), iterations=runner.best_iteration,
                      wall_s=runner.elapsed_s, peak_mb=peak, rule="held-out pixels")
    row["udn_final"] = dict(scores(truth, final), iterations=runner.iteration,
                            wall_s=runner.elapsed_s)
    if wmv_best is not None:
        row["udn_wmv"] = dict(scores(truth, wmv_best[2].cpu().numpy()), iterations=wmv_best[1])
    # blend with FISTA (auto tau), the weight chosen on the held-out pixels: the UDN's choice
    # never saw them, and FISTA's fitted-pixel run at the same tau did not either
    herr = {a: _heldout_err(model, a * sel + (1 - a) * x_fit, b, heldout)
            for a in BLEND_WEIGHTS}
    a_best = min(BLEND_WEIGHTS, key=lambda a: herr[a])
    blend = a_best * sel + (1 - a_best) * x_auto
    row["udn_blend"] = dict(scores(truth, blend), weight=a_best)
    if mix_best is not None:
        x_mix = mix_best[2].cpu().numpy()
        row["udn_mix_stop"] = dict(scores(truth, 0.5 * (x_mix + x_auto)),
                                   iterations=mix_best[1], rule="held-out pixels of the mix")
        row["udn_mix_heldout_curve"] = mix_hcurve
        keep["udn_mix_stop"] = x_mix
    if runner.mean_count:  # the runner's iterate average, as a job's mean.tif
        snap_mean = runner.mean_estimate()
        row["udn_snapshots"] = dict(scores(truth, snap_mean), count=runner.mean_count,
                                    every=SNAPSHOT_EVERY)
        keep["udn_snapshots"] = snap_mean
    row["udn_mix_curve"] = mix_curve
    row["udn_mix_oracle_stop"] = _oracle_stop(mix_curve)
    row["udn_curve"] = curve
    row["udn_curve_wall"] = curve_wall
    row["udn_oracle_stop"] = _oracle_stop(curve)
    row["udn_heldout_curve"] = hcurve
    row["udn_wmv_curve"] = wmv_curve
    row["udn_gain"] = {"initial": runner.initial_gain, "final": runner.G.gain}
    row["udn_clipped"] = clipped
    row["udn_still_improving"] = runner.still_improving()
    row["udn_notes"] = list(runner.notes)
    if hasattr(runner.model, "gain_range"):  # --lever sensor-gain: the field it learned
        row["udn_sensor_gain_range"] = runner.model.gain_range()
    keep["udn"], keep["udn_blend"] = sel, blend
    if args.seeds > 1:
        members, walls = [sel], [runner.elapsed_s]
        for seed in range(1, args.seeds):
            r = make_runner(model, b, net, replace(cfg, seed=seed), args.lever)
            if args.warm_start or args.lever == "fista-input":  # its own fitted pixels
                own = r.fit.cpu().numpy().astype(np.float32)
                x_own = _fitted_pixels_fista(pair, b, own, args, min(cps))
                if args.lever == "fista-input":
                    fista_input(r, x_own)
                if args.warm_start:
                    r.warm_start(x_own, args.warm_start)
            for _ in r.steps():
                pass
            members.append(r.best_estimate())
            walls.append(r.elapsed_s)
        avg = np.mean(np.stack(members), axis=0)
        row["udn_ensemble"] = dict(scores(truth, avg), seeds=args.seeds, wall_s=sum(walls),
                                   members=[psnr_only(truth, m) for m in members])
        keep["udn_ensemble"] = avg
    return row


def fista_input(r: Any, x: Any) -> Any:
    """``--lever fista-input``: the first C channels of the network's input z become the
    FISTA-TV estimate ``x`` (C, K, H, W) of the same measurement's fitted pixels, divided by its
    99.9th percentile (so about [0, 1]) and padded to the network's grid by reflection; the
    other channels stay the seeded noise. The network then maps an image of the scene, not
    noise, to the estimate (a guided deep image prior); the held-out pixels stay unseen, since
    ``x`` used only the fitted ones. Returns the runner, restarted (fresh Adam, new restore
    point; the gain fitted again to the new first output)."""
    import numpy as np
    import torch
    import torch.nn.functional as F

    g = r.G
    c, k, h, w = g.scene_shape
    img = np.asarray(x, dtype=np.float32).reshape(c * k, h, w)
    img = np.clip(img / max(float(np.percentile(img, 99.9)), 1e-12), 0.0, None)
    t = torch.as_tensor(img)[None]
    ph, pw = g.padded[-2:]
    mode = "reflect" if (ph - h < h and pw - w < w) else "replicate"
    t = F.pad(t, (0, pw - w, 0, ph - h), mode=mode)
    n = min(c * k, int(g.z.shape[1]))
    with torch.no_grad():
        g.z[:, :n] = t[:, :n].to(g.z.device, g.z.dtype)
        g.set_gain(r._fit_gain() * r.config.headroom)  # the fit of the new first output
    r.initial_gain = g.gain
    return _restart(r)


def _restart(r: Any) -> Any:
    """A runner whose generator a lever changed: a fresh optimizer over its weights now, and
    the restore point taken again (so a divergence restores the changed generator)."""
    import torch

    r.opt = torch.optim.Adam(r.G.parameters(), lr=r.config.lr)
    r._snapshot = r._take_snapshot()
    return r


def make_runner(model: Any, b: Any, net: Any, cfg: Any, lever: str = "none") -> Any:
    """A UDN runner, plain or with one of the ``--lever`` variants (measured, not defaults).

    - ``precondition``: the gradient that reaches the network from its output is multiplied by
      FISTA's Fourier preconditioner P (``recon.fista.fourier_preconditioner`` at
      ``AUTO_KAPPA``: the frequencies the PSF passes best damped to that level), so the
      frequencies the measurement attenuates are fitted sooner; the loss is unchanged.
    - ``channel-gain``: one learnable output gain per colour channel, each initialised by the
      least-squares fit of that channel (the runner's scalar fit, per channel), instead of one.
    - ``block-holdout``: the held-out pixels (the stopping rule's) in whole blocks of the sensor
      with all their channels (``recon.holdout``, as the automatic tau holds them out) instead
      of single values.
    - ``deep-decoder``: another prior, the deep decoder (:func:`_deep_decoder_class`) in place
      of the encoder-decoder; the rest of the runner (loss, gain, stop) unchanged.
    - ``sensor-gain``: the forward model gets a smooth multiplicative field on the sensor, one
      per colour channel, learned with the network (log-gains at ``SENSOR_GAIN_POINTS`` control
      points along the measured extent's shorter side, bilinear between them, starting at 1,
      bounded to [1 / ``SENSOR_GAIN_MAX``, ``SENSOR_GAIN_MAX``]):
      a camera whose response departs smoothly from the model (the sensor side of the mismatch
      the held-out pixels cannot tell from detail) is fitted by the field, not by the image.
    """
    import numpy as np
    import torch

    from recon.udn.network import Generator
    from recon.udn.runner import UDNRunner

    if lever in ("none", "fista-input"):  # fista-input: the input is set by fista_input()
        return UDNRunner(model, b, network=net, config=cfg)
    if lever == "precondition":
        from recon.fista import AUTO_KAPPA, fourier_preconditioner

        found = fourier_preconditioner(model.op, AUTO_KAPPA)
        assert found is not None  # required=True raises instead of returning None
        prec = found[0]

        class _Precondition(torch.autograd.Function):
            @staticmethod
            def forward(ctx: Any, x: Any) -> Any:
                return x.view_as(x)

            @staticmethod
            def backward(ctx: Any, g: Any) -> Any:
                return prec.apply(g)

        class _PreconditionedRunner(UDNRunner):
            def _forward(self, noise: bool) -> Any:
                x = super()._forward(noise)
                return _Precondition.apply(x) if torch.is_grad_enabled() else x  # type: ignore[no-untyped-call]

        return _PreconditionedRunner(model, b, network=net, config=cfg)
    if lever == "channel-gain":
        class _ChannelGain(Generator):
            @property
            def gain(self) -> float:  # the largest, for the runner's notes and cap check
                return float(self.log_gain.detach().exp().max())

        r = UDNRunner(model, b, network=net, config=cfg)
        with torch.no_grad():
            r.G.log_gain.fill_(0.0)
            ax = model.apply(r._forward(noise=False))
            w = r.fit.to(ax.dtype)
            dims = tuple(range(1, ax.dim()))
            g = (ax * r.b * w).sum(dim=dims) / (ax * ax * w).sum(dim=dims).clamp_min(1e-30)
        if not bool(torch.isfinite(g).all() and (g > 0).all()):
            raise ValueError(f"channel-gain: a least-squares gain is not positive ({g.tolist()})")
        head = (-1,) + (1,) * (len(model.scene_shape) - 1)  # (C, 1, 1, 1): per channel
        r.G.__class__ = _ChannelGain
        r.G.log_gain = torch.nn.Parameter(
            (g * cfg.headroom).log().reshape(head).to(torch.float32))
        r.initial_gain = r.G.gain
        return _restart(r)
    if lever == "deep-decoder":
        r = UDNRunner(model, b, network=net, config=cfg)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(cfg.seed)
            dd = _deep_decoder_class()(r.G.net.head.out_channels, r.G.padded, seed=cfg.seed)
        r.G.net = dd
        r._net = dd
        r.G.set_gain(r._fit_gain() * cfg.headroom)
        r.initial_gain = r.G.gain
        return _restart(r)
    if lever == "sensor-gain":
        import torch.nn.functional as F

        r = UDNRunner(model, b, network=net, config=cfg)
        measured = (r.fit | r.heldout).reshape(-1, *r.fit.shape[-2:]).any(dim=0)
        rows = torch.nonzero(measured.any(dim=1)).flatten()
        cols = torch.nonzero(measured.any(dim=0)).flatten()
        r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
        hh, ww = r1 - r0, c1 - c0
        ph, pw = measured.shape
        n = SENSOR_GAIN_POINTS - 1  # intervals along the shorter side, as many per length
        gh, gw = (n + 1, round(n * ww / hh) + 1) if hh <= ww else (round(n * hh / ww) + 1, n + 1)
        nc = int(r.b.shape[0])
        r.G.register_parameter("sensor_log_gain", torch.nn.Parameter(
            torch.zeros(nc, 1, gh, gw, device=r.b.device)))

        class _SensorGainModel:
            """The model with the learned smooth sensor gain applied to its prediction."""

            def __init__(self, base: Any, log_gain: Any) -> None:
                self._base, self._log_gain = base, log_gain

            def __getattr__(self, name: str) -> Any:
                return getattr(self._base, name)

            def field(self) -> Any:
                bound = math.log(SENSOR_GAIN_MAX)
                f = F.interpolate(bound * torch.tanh(self._log_gain), size=(hh, ww),
                                  mode="bilinear", align_corners=True)
                return F.pad(f, (c0, pw - c1, r0, ph - r1)).exp()  # 1 outside the extent

            def apply(self, x: Any) -> Any:
                ax = self._base.apply(x)
                f = self.field()
                return ax * f.reshape(nc, *([1] * (ax.dim() - 3)), ph, pw)

            def gain_range(self) -> list[float]:
                with torch.no_grad():
                    f = self.field()[..., r0:r1, c0:c1]
                return [float(f.min()), float(f.max())]

        r.model = _SensorGainModel(model, r.G.sensor_log_gain)
        return _restart(r)
    if lever == "block-holdout":
        from recon.holdout import heldout_blocks

        class _BlockHoldout(UDNRunner):
            def _choose_heldout(self, measured: Any, n_hold: int) -> Any:
                # whole blocks of the sensor, every channel of a held-out pixel (recon.holdout)
                m = measured.reshape(-1, *measured.shape[-2:]).all(dim=0).numpy()
                n = max(1, round(n_hold * m.sum() / int(measured.sum())))
                hold, _ = heldout_blocks(m, n, np.random.default_rng(self.config.seed + 7919))
                return torch.as_tensor(hold).expand(measured.shape) & measured

        return _BlockHoldout(model, b, network=net, config=cfg)
    raise ValueError(f"lever must be one of {LEVERS}, got {lever!r}")


def _deep_decoder_class() -> Any:
    """The deep decoder (Heckel & Hand 2019, "Deep Decoder: concise image representations from
    untrained non-convolutional networks"): a fixed random input at 1/2^depth of the padded
    grid, then per level a 1x1 convolution, bilinear upsampling x2, ReLU and batch norm, and a
    1x1 convolution with a sigmoid; no encoder, no 3x3 convolutions, fewer weights than the
    image has values (64 channels, 4 levels: 17 k against 24 k at 1/4 resolution in colour).
    It ignores the runner's input (and with it the regularisation noise): its own input is
    fixed. ``head`` is the last 1x1 convolution, as the runner's clipping correction expects."""
    import math as _math

    import torch
    from torch import nn
    from torch.nn import functional as F

    class DeepDecoder(nn.Module):
        def __init__(self, out_channels: int, padded: tuple[int, ...], channels: int = 64,
                     depth: int = 4, seed: int = 0) -> None:
            super().__init__()
            hp, wp = (int(v) for v in padded)
            self.sizes = [(_math.ceil(hp / 2 ** (depth - i)), _math.ceil(wp / 2 ** (depth - i)))
                          for i in range(1, depth)] + [(hp, wp)]
            gen = torch.Generator().manual_seed(int(seed))
            h0, w0 = _math.ceil(hp / 2 ** depth), _math.ceil(wp / 2 ** depth)
            self.register_buffer("z0", torch.rand((1, channels, h0, w0), generator=gen))
            self.convs = nn.ModuleList(nn.Conv2d(channels, channels, 1) for _ in self.sizes)
            self.norms = nn.ModuleList(nn.BatchNorm2d(channels) for _ in self.sizes)
            self.head = nn.Conv2d(channels, out_channels, 1)

        def forward(self, z: Any) -> Any:
            h = self.z0
            for conv, norm, size in zip(self.convs, self.norms, self.sizes, strict=True):
                h = norm(F.relu(F.interpolate(conv(h), size=size, mode="bilinear",
                                              align_corners=False)))
            return torch.sigmoid(self.head(h))

    return DeepDecoder


def _oracle_stop(curve: dict[Any, float]) -> dict[str, Any] | None:
    """The UDN's best PSNR along its curve (seen with the truth: a bound, not a method)."""
    if not curve:
        return None
    it, best = max(((int(k), v) for k, v in curve.items()), key=lambda kv: kv[1])
    return {"psnr": best, "iterations": it}


# ---------------------------------------------------------------------------------------------
# table and figure
# ---------------------------------------------------------------------------------------------

METHODS = (("fista_auto", "FISTA-TV auto tau"), ("fista_oracle", "FISTA-TV oracle tau"),
           ("admm", "ADMM-TV (oracle tau)"), ("udn", "UDN (held-out stop)"),
           ("udn_wmv", "UDN (ES-WMV stop)"), ("udn_final", "UDN (final)"),
           ("udn_blend", "UDN+FISTA blend (held-out weight)"),
           ("udn_ensemble", "UDN seed ensemble (held-out stops)"),
           ("udn_oracle_stop", "UDN, best iteration seen with the truth (bound)"),
           ("udn_snapshots", "UDN, mean of its estimates every 500 iterations"),
           ("udn_mix_stop", "UDN and FISTA-TV auto averaged, stopped by the mix's held-out "
                            "error"),
           ("udn_mix_oracle_stop", "UDN and FISTA-TV auto averaged, best iteration seen with "
                                   "the truth (bound)"))


#: the keys every case has (and, in each method's record, ``psnr``; in FISTA's, ``tau``)
REQUIRED = ("pair", "erasure", "fista_auto", "fista_oracle")


def read_results(path: str) -> list[dict[str, Any]]:
    """The rows of a results file; a later row of the same case replaces an earlier one.

    A file of another benchmark, or a record without what the tables read, is a ValueError in
    one line naming the file and what is missing (:func:`benchmarks._cli.read_records`).
    """
    rows: dict[tuple[str, float], dict[str, Any]] = {}
    for r in read_records(path, "--results", "real-pairs", RESULTS_VERSION, REQUIRED):
        case = f"{r['pair']} at {r['erasure']}"
        for k, _label in METHODS:
            need = ("psnr", "tau") if k.startswith("fista") else ("psnr",)
            if k in r and not (isinstance(r[k], dict) and all(n in r[k] for n in need)):
                raise ValueError(f"--results {path}: the case {case} has no "
                                 f"{' and '.join(need)} for {k}: choose another file")
        if "udn_oracle_stop" not in r and r.get("udn_curve"):  # rows of older runs
            r["udn_oracle_stop"] = _oracle_stop(r["udn_curve"])
        rows[(r["pair"], r["erasure"])] = r
    return list(rows.values())


def _fmt(v: Any, nd: int = 2) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{nd}f}"


def make_tables(rows: list[dict[str, Any]]) -> str:
    """Mean over the pairs per erasure level and method, then per case."""
    erasures = sorted({r["erasure"] for r in rows})
    methods = [(k, label) for k, label in METHODS if any(k in r for r in rows)]
    out = ["| erasure | method | pairs | PSNR (dB) | SSIM | MS-SSIM | wall (s) | peak memory "
           "(MiB) |", "|---|---|---|---|---|---|---|---|"]
    for e in erasures:
        rs = [r for r in rows if r["erasure"] == e]
        for k, label in methods:
            have = [r[k] for r in rs if k in r]
            if not have:
                continue

            def mean(key: str, have: list[dict[str, Any]] = have) -> float | None:
                vals = [h[key] for h in have if h.get(key) is not None]
                return sum(vals) / len(vals) if vals else None

            # peak resident memory of the run above the process's baseline: the FISTA grid's
            # for both FISTA rows (one figure for the whole grid), the method's own otherwise
            peaks = [r.get("fista_peak_mb") if k.startswith("fista") else r[k].get("peak_mb")
                     for r in rs if k in r]
            peak_vals = [v for v in peaks if v is not None]
            peak = sum(peak_vals) / len(peak_vals) if peak_vals else None
            out.append(f"| {e:.0%} | {label} | {len(have)} | {_fmt(mean('psnr'))} | "
                       f"{_fmt(mean('ssim'), 3)} | {_fmt(mean('ms_ssim'), 3)} | "
                       f"{_fmt(mean('wall_s'), 1)} | {_fmt(peak, 0)} |")
    return "\n".join(out)


def case_table(rows: list[dict[str, Any]]) -> str:
    """PSNR of every case and method, with the taus and the UDN's iterations."""
    methods = [(k, label) for k, label in METHODS if any(k in r for r in rows)]
    head = "| pair | erasure | " + " | ".join(label for _, label in methods) + \
        " | auto / oracle tau | UDN it. (held-out / ES-WMV) | UDN at cap |"
    out = [head, "|" + "---|" * (len(methods) + 5)]
    for r in sorted(rows, key=lambda r: (r["erasure"], r["pair"])):
        cells = [_fmt(r[k]["psnr"]) if k in r else "-" for k, _ in methods]
        its = (f"{r['udn']['iterations']} / {r.get('udn_wmv', {}).get('iterations', '-')}"
               if "udn" in r else "-")
        clip = f"{r['udn_clipped']:.2%}" if "udn_clipped" in r else "-"
        out.append(f"| {r['pair']} | {r['erasure']:.0%} | " + " | ".join(cells) +
                   f" | {r['fista_auto']['tau']:g} / {r['fista_oracle']['tau']:g} | {its} | "
                   f"{clip} |")
    return "\n".join(out)


#: the scale of the shading in the error analysis: a Gaussian of this fraction of the frame's
#: shorter side (8 px at 67x120)
SHADING_FRACTION = 1 / 8
#: the finest band of the error analysis: below a Gaussian of this fraction of the shorter side
#: (about 1 px at 67x120, 4 px at the dataset's 270x480)
FINE_FRACTION = 1 / 64
#: the methods of the error analysis, from the images a run keeps
ERROR_METHODS = (("fista_auto", "FISTA-TV auto tau"), ("fista_oracle", "FISTA-TV oracle tau"),
                 ("udn", "UDN (held-out stop)"), ("udn_blend", "UDN+FISTA blend"),
                 ("udn_ensemble", "UDN seed ensemble"),
                 ("ensemble_fista_mean", "UDN seed ensemble and FISTA-TV auto, averaged"),
                 ("udn_fista_mean", "UDN (seed 0) and FISTA-TV auto, averaged "
                                    "(jobs combine --with-fista --estimate best)"),
                 ("udn_mix_fista_mean", "UDN (seed 0, stopped by the mix's held-out error) "
                                        "and FISTA-TV auto, averaged"),
                 ("udn_snapshots", "UDN, mean of its estimates every 500 iterations"),
                 ("udn_snapshots_fista_mean", "UDN's mean of estimates every 500 iterations and "
                                              "FISTA-TV auto, averaged (jobs combine "
                                              "--with-fista)"))

#: The derived estimate of ``ensemble_fista_mean``: the plain mean of the seed ensemble and the
#: automatic-tau FISTA-TV result, neither weighted by the truth (both fit the same measurement,
#: so their scales agree; the seed ensemble's own rule, one weight per member, extended to one
#: more member whose errors are of another kind).
#: ``udn_fista_mean``: the same with the first seed's held-out choice alone, what
#: ``lenslesscam jobs combine RUN --with-fista --estimate best`` writes for one run (FISTA-TV
#: with the automatic tau on all measured pixels, weight 0.5); ``udn_snapshots_fista_mean``:
#: with the run's iterate mean instead, what ``jobs combine RUN --with-fista`` writes.
#: ``udn_mix_fista_mean``: the same with the first seed stopped where the mix (its estimate and
#: FISTA-TV of its fitted pixels, half and half) predicts its held-out pixels best.
def _derived(imgs: dict[str, Any]) -> dict[str, Any]:
    if "udn_ensemble" in imgs and "fista_auto" in imgs and "ensemble_fista_mean" not in imgs:
        imgs = {**imgs, "ensemble_fista_mean": 0.5 * (imgs["udn_ensemble"] + imgs["fista_auto"])}
    if "udn" in imgs and "fista_auto" in imgs and "udn_fista_mean" not in imgs:
        imgs = {**imgs, "udn_fista_mean": 0.5 * (imgs["udn"] + imgs["fista_auto"])}
    if "udn_mix_stop" in imgs and "fista_auto" in imgs and "udn_mix_fista_mean" not in imgs:
        imgs = {**imgs, "udn_mix_fista_mean": 0.5 * (imgs["udn_mix_stop"] + imgs["fista_auto"])}
    if "udn_snapshots" in imgs and "fista_auto" in imgs and "udn_snapshots_fista_mean" not in imgs:
        imgs = {**imgs,
                "udn_snapshots_fista_mean": 0.5 * (imgs["udn_snapshots"] + imgs["fista_auto"])}
    return imgs


ERROR_TEXT = (
    "Where the error is (`--error-analysis`, from the kept images). The error against the "
    "truth (after the gain fit) split by scale with Gaussian blurs: *fine*, what a blur of "
    "1/{fine} of the frame's shorter side removes; *smooth*, what is left after a blur of "
    "1/{den} of it (the shading); *mid*, between the two; each as the mean squared value x "
    "1000 (Gaussian blurs are not sharp filters: the bands overlap, and their mean squares do not "
    "add up to the total). The row "
    "*the truth's own content* gives the same bands of the truth less its mean per channel: "
    "the error of an estimate without any of that content. Then the PSNR once a shading is "
    "removed that was learned from the *other* pairs at that level (per colour channel, "
    "blurred truth over blurred estimate; leave one pair out, so no case is corrected with "
    "its own truth). The last column, on oracle FISTA-TV's row: the factor its mid-band error "
    "would have to shrink by, its fine and smooth errors kept, for its mean PSNR to rise by "
    "1 dB (the issue's margin).\n\n")


def _smooth(a: Any, sigma: float) -> Any:
    """Each channel of (C, h, w) blurred by a Gaussian of ``sigma`` pixels (edges reflected)."""
    import numpy as np
    from scipy.ndimage import gaussian_filter

    return np.stack([gaussian_filter(np.asarray(c, np.float64), sigma) for c in a])


def _split(err: Any, fine_sigma: float, sigma: float) -> tuple[Any, Any, Any]:
    """``err`` as fine + mid + smooth: below a blur of ``fine_sigma``, between, above ``sigma``."""
    e1, es = _smooth(err, fine_sigma), _smooth(err, sigma)
    return err - e1, e1 - es, es


def _bands(err: Any, fine_sigma: float, sigma: float) -> list[float]:
    """Mean squares of the three parts of ``err`` (:func:`_split`)."""
    import numpy as np

    return [float(np.mean(b ** 2)) for b in _split(err, fine_sigma, sigma)]


def _mid_factor(cases: list[tuple[Any, Any, float, float]], gain_db: float) -> float | None:
    """The factor on the mid band of each error that raises the mean PSNR by ``gain_db``, the
    other bands kept (bisection; None if removing the mid band entirely is not enough).

    ``cases``: (truth, error, fine_sigma, sigma) per pair, the error = truth - estimate.
    """
    import numpy as np

    from recon.metrics import psnr

    parts = []
    for t, err, fs, sigma in cases:
        fine, mid, smooth = _split(err, fs, sigma)
        parts.append((t, fine + smooth, mid))

    def mean_psnr(a: float) -> float:
        return float(np.mean([psnr(t, (t - rest - a * mid).astype(np.float32))
                              for t, rest, mid in parts]))

    target = mean_psnr(1.0) + gain_db
    if mean_psnr(0.0) < target:
        return None
    lo, hi = 0.0, 1.0  # mean_psnr(lo) >= target > mean_psnr(hi)
    for _ in range(30):
        mid_a = (lo + hi) / 2
        lo, hi = (mid_a, hi) if mean_psnr(mid_a) >= target else (lo, mid_a)
    return lo


def error_analysis(images: dict[tuple[str, float], dict[str, Any]]) -> list[dict[str, Any]]:
    """Where the error against the truth is, per erasure level and method (mean over pairs).

    ``psnr``: after the gain fit, as in the tables. ``fine`` / ``mid`` / ``smooth``: the mean
    squared error in three bands of scale, split by Gaussian blurs of the error at
    ``FINE_FRACTION`` and at ``SHADING_FRACTION`` of the frame's shorter side (fine = e -
    blur_f e, mid = blur_f e - blur_s e, smooth = blur_s e). The row of method ``truth`` has
    the same bands of the truth less its mean per channel (the error of an estimate without
    any of that content), so a method's band reads as the part of it not recovered.
    ``psnr_shaded``: after a shading correction learned from the *other* pairs at the same
    level and applied to this one: s = sum_other blur_s(truth) / sum_other blur_s(gain-fitted
    estimate), per colour channel, then the gain fit again (leave one pair out, so no case is
    corrected with its own truth). A smooth error that the other scenes share is the camera's
    (vignetting, the reference camera's shading), not the scene's: no prior can remove it
    from one measurement, and if removing it lifts the methods alike it is not what separates
    them. ``ensemble_fista_mean``: the mean of the seed ensemble and automatic-tau FISTA-TV
    (:func:`_derived`), where a case kept both. ``mid_factor_1db`` (oracle FISTA-TV's row
    only): the factor on its mid-band error, its fine and smooth errors kept, that would raise
    its mean PSNR by 1 dB, the issue's margin (what a method that shares the other two bands
    would have to do in the mid band). ``ssim`` / ``ms_ssim``: the means of :func:`scores`,
    as in the tables, so that the averaged rows, which exist only here, have all three scores
    (None where a case has no MS-SSIM). Levels with fewer than two pairs are left out.
    """
    import numpy as np

    from recon.metrics import gain_fit, psnr

    out: list[dict[str, Any]] = []
    for e in sorted({e for _, e in images}):
        cases = {p: _derived(imgs) for (p, ee), imgs in images.items()
                 if ee == e and "truth" in imgs}
        if len(cases) < 2:
            continue
        short = min(next(iter(cases.values()))["truth"].shape[-2:])
        fs, sigma = FINE_FRACTION * short, SHADING_FRACTION * short
        fine, mid, smooth = (float(v) for v in np.mean(
            [_bands(c["truth"] - c["truth"].mean(axis=(-2, -1), keepdims=True), fs, sigma)
             for c in cases.values()], axis=0))
        out.append({"erasure": e, "method": "truth", "label": "the truth's own content",
                    "pairs": len(cases), "sigma": sigma, "psnr": None, "psnr_shaded": None,
                    "fine": fine, "mid": mid, "smooth": smooth})
        for key, label in ERROR_METHODS:
            have = {p: c for p, c in cases.items() if key in c}
            if len(have) < 2:
                continue
            fitted = {p: gain_fit(c["truth"], np.asarray(c[key]).reshape(c["truth"].shape))[0]
                      for p, c in have.items()}
            blur_t = {p: _smooth(c["truth"], sigma) for p, c in have.items()}
            blur_f = {p: _smooth(f, sigma) for p, f in fitted.items()}
            p0, p1, bands, sc = [], [], [], []
            for p, c in have.items():
                t, f = c["truth"], fitted[p]
                num = sum(blur_t[q] for q in have if q != p)
                den = sum(blur_f[q] for q in have if q != p)
                shade = num / np.maximum(den, 1e-6 * float(np.max(den)))
                bands.append(_bands(t - f, fs, sigma))
                p0.append(psnr(t, f))
                p1.append(psnr(t, gain_fit(t, (shade * f).astype(np.float32))[0]))
                sc.append(scores(t, c[key]))
            fine, mid, smooth = (float(v) for v in np.mean(bands, axis=0))
            row = {"erasure": e, "method": key, "label": label, "pairs": len(have),
                   "sigma": sigma, "psnr": float(np.mean(p0)), "psnr_shaded": float(np.mean(p1)),
                   "fine": fine, "mid": mid, "smooth": smooth}
            for k in ("ssim", "ms_ssim"):  # the tables' scores, so an averaged row has all three
                vals = [s[k] for s in sc]
                row[k] = None if any(v is None for v in vals) else float(np.mean(vals))
            if key == "fista_oracle":
                row["mid_factor_1db"] = _mid_factor(
                    [(c["truth"], c["truth"] - fitted[p], fs, sigma) for p, c in have.items()],
                    1.0)
            out.append(row)
    return out


def error_table(rows: list[dict[str, Any]]) -> str:
    """The error analysis as Markdown, with each method's distance to oracle FISTA-TV."""
    ref = {r["erasure"]: r for r in rows if r["method"] == "fista_oracle"}
    out = ["| erasure | method | pairs | PSNR (dB) | SSIM / MS-SSIM | error x 1000: fine / mid / "
           "smooth | PSNR, shading of the other pairs removed (dB) | gain (dB) | - oracle "
           "FISTA-TV, before / after (dB) | mid-band factor for +1 dB |", "|---" * 10 + "|"]
    for r in rows:
        bands = f"{1e3 * r['fine']:.2f} / {1e3 * r['mid']:.2f} / {1e3 * r['smooth']:.2f}"
        if r["psnr"] is None:  # the truth's own content
            out.append(f"| {r['erasure']:.0%} | {r['label']} | {r['pairs']} | - | - | {bands} "
                       "| - | - | - | - |")
            continue
        o = ref.get(r["erasure"])
        d = (f"{r['psnr'] - o['psnr']:+.2f} / {r['psnr_shaded'] - o['psnr_shaded']:+.2f}"
             if o is not None else "-")
        structure = f"{_fmt(r.get('ssim'), 3)} / {_fmt(r.get('ms_ssim'), 3)}"
        out.append(f"| {r['erasure']:.0%} | {r['label']} | {r['pairs']} | {r['psnr']:.2f} | "
                   f"{structure} | {bands} | {r['psnr_shaded']:.2f} | "
                   f"{r['psnr_shaded'] - r['psnr']:+.2f} | {d} | "
                   f"{_fmt(r.get('mid_factor_1db'))} |")
    return "\n".join(out)


def _view(x: Any) -> Any:
    """(3, h, w) RGB (upright, as loaded) -> (h, w, 3) uint8, the 99.5th percentile white."""
    import numpy as np

    a = np.asarray(x, dtype=np.float64).reshape(3, *x.shape[-2:])
    hi = float(np.percentile(a, 99.5)) or 1.0
    return (np.clip(a / hi, 0, 1) * 255).round().astype(np.uint8).transpose(1, 2, 0)


def write_figure(images: dict[tuple[str, float], dict[str, Any]], path: str) -> None:
    """Rows: erasure levels; per pair: truth / FISTA (auto tau) / UDN columns."""
    import numpy as np
    from PIL import Image

    from recon.atomic import atomic_write

    pairs = sorted({p for p, _ in images}, key=lambda p: PAIRS.index(p) if p in PAIRS else 99)
    erasures = sorted({e for _, e in images})
    cols = ("truth", "fista_auto", "udn")
    any_img = next(iter(images.values()))["truth"]
    h, w = any_img.shape[-2:]
    gap = 2
    canvas = np.full((len(erasures) * (h + gap), len(pairs) * (len(cols) * w + 3 * gap), 3),
                     255, np.uint8)
    for i, e in enumerate(erasures):
        for j, p in enumerate(pairs):
            imgs = images.get((p, e), {})
            for k, c in enumerate(cols):
                if c not in imgs:
                    continue
                y, x = i * (h + gap), j * (len(cols) * w + 3 * gap) + k * w
                canvas[y:y + h, x:x + w] = _view(imgs[c])
    img = Image.fromarray(canvas).quantize(colors=256)  # a palette PNG: about 3x smaller
    atomic_write(Path(path), lambda tmp: img.save(tmp, format="PNG", optimize=True))


def images_folder(results: str) -> Path:
    """Where the cases of ``results`` keep their images (beside it)."""
    return Path(results).parent / f"{Path(results).stem}-images"


def _save_images(results: str, pair: str, erasure: float, keep: dict[str, Any]) -> None:
    import numpy as np

    from recon.atomic import atomic_write

    path = images_folder(results) / f"{pair}-{round(erasure * 100)}.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda tmp: np.savez_compressed(
        tmp, **{k: np.asarray(v, np.float32).reshape(3, *v.shape[-2:]) for k, v in keep.items()}))


def _load_images(results: str) -> dict[tuple[str, float], dict[str, Any]]:
    import numpy as np

    folder = images_folder(results)
    out: dict[tuple[str, float], dict[str, Any]] = {}
    for f in sorted(folder.glob("*.npz")) if folder.is_dir() else []:
        pair, pct = f.stem.rsplit("-", 1)
        with np.load(f) as z:
            out[(pair, int(pct) / 100)] = {k: z[k] for k in z.files}
    return out


def time_threads(args: argparse.Namespace) -> dict[str, Any]:
    """Seconds per UDN iteration (the configured network) on the first pair, interleaved
    settings, 3 rounds: 1 and 2 torch threads on a CPU; float32 and bf16 on a GPU, and FISTA-TV
    (the oracle grid's middle tau) beside them."""
    import torch

    from recon.fista import Fista
    from recon.models import build_model
    from recon.udn.network import NetworkConfig
    from recon.udn.runner import UDNConfig, UDNRunner, describe_device

    name = args.pairs[0]
    pair = load_pair(name, pair_files(name, data_dir(args.data)), args.downsample)
    mask = sensor_mask(pair, 0.0)
    model = build_model("2d", pair.psf, mask=mask, field=pair.truth.shape[1:],
                        device=args.device)
    net = NetworkConfig(channels=args.channels, scales=args.scales, skip_channels=args.skip)
    gpu = torch.device(args.device).type == "cuda"

    def sync() -> None:
        if gpu:
            torch.cuda.synchronize(args.device)

    settings: tuple[Any, ...] = ("float32", "bf16") if gpu else (1, 2)
    out: dict[Any, list[float]] = {k: [] for k in settings}
    fista: list[float] = []
    b = pair.meas * mask
    for _ in range(3):
        for setting in settings:
            if not gpu:
                torch.set_num_threads(setting)
            r = UDNRunner(model, b, network=net,
                          config=UDNConfig(max_iter=args.time_threads + 1, lr=args.lr,
                                           ema=args.ema, headroom=args.headroom,
                                           precision=setting if gpu else "float32"))
            r.step()  # warm-up
            sync()
            t0 = time.perf_counter()
            for _ in range(args.time_threads):
                r.step()
            sync()
            out[setting].append((time.perf_counter() - t0) / args.time_threads)
        if gpu:
            solver = Fista(model.op, torch.as_tensor(b), tau=TAUS[len(TAUS) // 2],
                           max_iter=args.time_threads + 1, tol=0.0)
            it = solver.steps()
            next(it)
            sync()
            t0 = time.perf_counter()
            for _ in it:
                pass
            sync()
            fista.append((time.perf_counter() - t0) / args.time_threads)
    res: dict[str, Any] = {
        "pair": name, "shape": list(pair.truth.shape), "device": describe_device(args.device),
        "s_per_iteration": {str(k): sorted(v) for k, v in out.items()},
        "load": os.getloadavg(), "cpus": os.cpu_count()}
    if fista:
        res["fista_s_per_iteration"] = sorted(fista)
    return res


SETTING_KEYS = ("downsample", "udn_iters", "channels", "scales", "skip", "headroom", "lr",
                "ema", "tv_weight", "holdout", "wmv_window", "fista_iters", "warm_start",
                "seeds", "lever", "reg_noise")
"""The settings a results file's cases must share (the device may differ: it changes the time,
and the scores only by rounding; the thread count is checked apart: one per file)."""


def _settings(args: argparse.Namespace) -> dict[str, Any]:
    """The settings stored with each case."""
    return {k: getattr(args, k) for k in (*SETTING_KEYS, "threads", "device")}


#: ``--results`` settings key -> option, for the one command that runs a file's cases
SETTING_OPTIONS = {k: "--" + k.replace("_", "-") for k in (*SETTING_KEYS, "threads", "device")}
SETTING_OPTIONS["skip"] = "--skip"


def one_go(rows: list[dict[str, Any]], out: str | None, figure: str | None) -> str:
    """The one command that runs every case of ``rows`` (from their stored settings), or a
    sentence saying why there is none (cases of several runs that one command cannot make)."""
    s = rows[0].get("settings", {})
    threads = {r.get("settings", {}).get("threads") for r in rows}
    udn = {"udn" in r for r in rows}
    if len(udn) > 1:
        return ("There is no one command for all of these cases: some ran with the UDN and "
                "some with `--no-udn`.")
    values: dict[str, Any] = {k: s[k] for k in (*SETTING_KEYS, "device") if k in s}
    values["threads"] = next(iter(threads)) if len(threads) == 1 else None
    values.update(pairs=[p for p in PAIRS if any(r["pair"] == p for r in rows)],
                  erasures=sorted({r["erasure"] for r in rows}), no_udn=udn == {False},
                  out=out, figure=figure or "FIGURE.png", overwrite=True)
    cmd = command_line("real-pairs", values, add_arguments)
    return f"In one go: `{cmd}`."


#: options that ``--table-only`` cannot apply (the cases ran as their records say)
RUN_ONLY = (*SETTING_KEYS, "threads", "no_udn", "time_threads")


def _table_only_refusals(args: argparse.Namespace) -> None:
    """``--table-only`` with an option it cannot honour (a run setting) is refused."""
    from benchmarks._cli import option_defaults

    given = [a.option_strings[-1] for a in option_defaults(add_arguments)
             if a.dest in RUN_ONLY and getattr(args, a.dest, a.default) not in (a.default, None)]
    if given:
        raise ValueError(f"--table-only makes the table of the cases in --results as they ran: "
                         f"{', '.join(given)} cannot apply to them (--pairs and --erasures "
                         "choose the cases)")


def fill_defaults(args: argparse.Namespace) -> None:
    """Replace the UDN settings left at None by recon.udn's defaults."""
    from recon.udn.network import NetworkConfig
    from recon.udn.runner import UDNConfig

    net, cfg = NetworkConfig(), UDNConfig()
    for name, value in (("channels", net.channels), ("scales", net.scales),
                        ("skip", net.skip_channels), ("headroom", cfg.headroom),
                        ("lr", cfg.lr), ("ema", cfg.ema), ("tv_weight", cfg.tv_weight),
                        ("reg_noise", cfg.reg_noise)):
        if getattr(args, name) is None:
            setattr(args, name, value)


#: what the wall column of each row of the summary includes (item 9 of the bench review)
WALL_TEXT = (
    "The wall (s) column is each method's own time per case, not alike across rows: *FISTA-TV "
    "oracle tau* is one run at the chosen tau up to its checkpoint (the 7-tau grid that makes "
    "it the oracle excluded); *FISTA-TV auto tau* is the automatic search plus the final run; "
    "*ADMM-TV* one run at the oracle tau; the UDN rows the UDN's whole run (every seed). Both "
    "FISTA rows give the peak memory of the whole tau grid.")


def _software_of(rows: list[dict[str, Any]]) -> str:
    """The machines and software the cases were run with (their records' provenance)."""
    def said(get: Any) -> str:
        return ", ".join(sorted({str(get(r.get("provenance") or {}) or "not recorded")
                                 for r in rows}))

    return (f"The cases ran on {said(lambda p: p.get('cpu', {}).get('model'))} with "
            f"lenslesscam {said(lambda p: p.get('versions', {}).get('lenslesscam'))} (commit "
            f"{said(lambda p: p.get('commit'))}, torch "
            f"{said(lambda p: p.get('versions', {}).get('torch'))}).")


def run(args: argparse.Namespace) -> int:
    """Run the cases not yet in ``--results`` (unless --table-only), then write the table."""

    from app.commands._options import check_output_folders

    runs = not (args.table_only or args.time_threads)
    if args.table_only:
        _table_only_refusals(args)
    check_outputs(args, {"--out": args.out, "--figure": args.figure},
                  appended={"--results": args.results} if runs else None,
                  inputs={"--data": args.data, **({} if runs else {"--results": args.results})})
    if not args.time_threads:
        read_results(args.results)  # a JSON-lines file of another benchmark stops here
    if runs:
        check_output_folders([images_folder(args.results) / "x.npz"])
    # the cases: each once (a repeat would run the same case twice), in the order given
    chosen_pairs = list(dict.fromkeys(args.pairs or PAIRS))
    chosen_erasures = list(dict.fromkeys(ERASURES if args.erasures is None else args.erasures))
    if not args.table_only:
        args.pairs, args.erasures = chosen_pairs, chosen_erasures

    choice = bench_threads(args)
    fill_defaults(args)
    if not 0 < args.holdout < 0.5:
        raise ValueError(f"--holdout must be in (0, 0.5), got {args.holdout}")
    for e in chosen_erasures:
        if not 0 <= e < 1:
            raise ValueError(f"--erasures must be in [0, 1), got {e}")
    from recon.udn.runner import resolve_device

    try:
        args.device = str(resolve_device(args.device))
    except (ValueError, RuntimeError) as exc:
        raise ValueError(f"--device: {exc}") from None
    t_all = time.perf_counter()
    if args.time_threads:
        print(json.dumps(time_threads(args)))
        return 0
    if not args.table_only:
        folder = data_dir(args.data)
        previous = read_results(args.results)
        settings = _settings(args)
        for r in previous:
            # one thread count per file: the wall column compares the cases
            diff = sorted(k for k in (*SETTING_KEYS, "threads")
                          if k in r.get("settings", {}) and r["settings"][k] != settings[k])
            if diff:
                raise ValueError(
                    f"{args.results} holds a case run with other settings ({r['pair']} at "
                    f"{r['erasure']:.0%}: " + ", ".join(
                        f"{k} {r['settings'][k]} not {settings[k]}" for k in diff)
                    + "): give another --results file (or those settings)")
        done = {(r["pair"], r["erasure"]) for r in previous if args.no_udn or "udn" in r}
        for e in args.erasures:
            for name in args.pairs:
                if (name, e) in done:
                    continue
                pair = load_pair(name, pair_files(name, folder), args.downsample)
                keep: dict[str, Any] = {}
                row = run_case(pair, e, args, keep)
                row["load"] = os.getloadavg()
                row["settings"] = _settings(args)
                # the images first: a case in the file always has them (figure, error analysis)
                _save_images(args.results, name, e, keep)
                append_jsonl(args.results, tagged("real-pairs", RESULTS_VERSION, row))
                done.add((name, e))
                print(f"{name} {e:.0%}: " + ", ".join(
                    f"{k} {row[k]['psnr']:.2f}" for k, _ in METHODS if k in row),
                    file=sys.stderr, flush=True)
    rows = read_results(args.results)
    if args.table_only:  # --pairs and --erasures choose the cases of the table
        rows = [r for r in rows if r["pair"] in chosen_pairs and r["erasure"] in chosen_erasures]
    if not rows:
        print(f"lenslesscam bench: error: no results in {args.results}"
              + (" for these --pairs and --erasures" if args.table_only else ""),
              file=sys.stderr)
        return 1
    counts = sorted({r["settings"]["threads"] for r in rows if "threads" in r.get("settings", {})})
    if len(counts) > 1:
        raise ValueError(f"--results {args.results} holds cases run on {counts} torch threads: "
                         "their walls do not compare in one table; choose the cases with "
                         "--pairs / --erasures, or rerun them on one count")
    summary, cases = make_tables(rows), case_table(rows)
    print(summary)
    print(cases)
    errors = ""
    if args.error_analysis:
        erows = error_analysis(_load_images(args.results))
        if not erows:
            raise ValueError(f"--error-analysis: {args.results} has no level with the images "
                             "of two pairs or more")
        errors = error_table(erows)
        print(errors)
    if args.figure:
        write_figure(_load_images(args.results), args.figure)
    if args.out:
        from recon.atomic import atomic_write_bytes

        old = next((r for r in rows if "settings" not in r or "shape" not in r), None)
        if old is not None:
            raise ValueError(f"--out: the case {old['pair']} at {old['erasure']:.0%} in "
                             f"{args.results} has no stored settings or shape (a case of an "
                             "older run), which the Markdown states: make the table without "
                             "--out, or rerun the case")
        s = rows[0]["settings"]
        h, w = rows[0]["shape"][1:]
        loads = [r["load"][0] for r in rows if "load" in r]
        fig = ""
        if args.figure:
            rel = os.path.relpath(args.figure, Path(args.out).resolve().parent)
            fig = (f"![truth / FISTA-TV (auto tau) / UDN per pair, one row per erasure level]"
                   f"({rel})\n\nColumns: for each pair (im65, im408, im740, im1000) the truth, "
                   "FISTA-TV with the automatic tau and the UDN (held-out stop); rows: the "
                   "erasure levels run, top to bottom in increasing order (an empty cell: "
                   "not run). Each image scaled to its own 99.5th percentile.\n\n")
        cmd = command_line("real-pairs", args, add_arguments,
                           leave_out=RUN_ONLY if args.table_only else ())
        devices = sorted({r.get("device", "cpu") for r in rows})
        load = (f"load average {min(loads, default=0):.1f}-{max(loads, default=0):.1f} during "
                "the runs")
        threads = f"{counts[0]} torch thread(s)" if counts else "torch threads not recorded"
        where = (f"{threads}; {load}." if devices == ["cpu"] else
                 f"FISTA-TV, ADMM-TV and the UDN on {', '.join(devices)}; host {load} (the "
                 "walls are of processes that may have shared the device: see the command).")
        where += " " + _software_of(rows) + " The table: " + machine_text(
            None if args.table_only else choice)
        n_udn = sum("udn" in r for r in rows)
        others = " (the others: FISTA and ADMM only, `--no-udn`)" if n_udn < len(rows) else ""
        text = (
            "# Real pairs: UDN against FISTA-TV and ADMM-TV on real DiffuserCam data\n\n"
            "The four measurement / lensed-truth pairs of the DiffuserCam Lensless MirFlickr "
            "dataset in `../shared/data/dlmd` (im65, im408, im740, im1000) with the estimated "
            "effective PSF, read through `recon.problem` in the dataset's layout (BGR, "
            "upside-down, PSF on the padded grid), in colour, with synthetic erasures of the "
            "measured pixels (one fixed seed per level). Scores against the lensed truth after "
            "a least-squares gain fit; MS-SSIM with as many scales as the size allows. "
            "FISTA-TV *auto*: `recon.autotau` (held-out pixels choose tau and the iteration "
            "count); *oracle*: the best tau of the grid and iteration checkpoint by PSNR "
            "against the truth. ADMM-TV at the oracle tau. UDN: the defaults of `recon udn` "
            "with the iteration limit below; its iteration chosen by held-out pixels "
            "(`best`), by the running variance of its output (ES-WMV, window "
            f"{rows[0]['settings'].get('wmv_window', 50)}), or its last; *blend*: "
            "w UDN + (1 - w) FISTA-auto, w in {0, 0.25, 0.5, 0.75, 1} chosen on the UDN's "
            "held-out pixels. Walls are single runs on a loaded machine (see the load).\n\n"
            f"Cases with a UDN run: {n_udn} of {len(rows)}{others}.\n\n"
            "How to read it, what was tried and the time to beat FISTA: "
            "[udn.md](udn.md#real-pairs).\n\n"
            "## Results\n\n"
            f"Resolution 1/{s['downsample']} ({h}x{w}, 3 colour channels); FISTA-TV "
            f"{s['fista_iters']} iterations, tau grid {', '.join(f'{t:g}' for t in TAUS)}; "
            f"UDN {s['scales']} scales x {s['channels']} channels, skip {s['skip']}, headroom "
            f"{s['headroom']:g}, lr {s['lr']:g}, EMA {s.get('ema', 0.99):g}, "
            f"TV weight {s['tv_weight']:g}, "
            f"{s['udn_iters']} iterations, {s['holdout']:.0%} of the measured pixels held out"
            + (f", {s['seeds']} seeds (the ensemble row)" if s.get("seeds", 1) > 1 else "")
            + (f", warm start {s['warm_start']} iterations" if s.get("warm_start") else "")
            + ". "
            + where + "\n\n"
            "Mean over the pairs:\n\n" + summary + "\n\n" + WALL_TEXT
            + "\n\nPSNR (dB) per case:\n\n" + cases +
            "\n\n" + (ERROR_TEXT.format(
                fine=round(1 / FINE_FRACTION), den=round(1 / SHADING_FRACTION)) + errors + "\n\n"
                      if errors else "") + fig +
            f"Produced by `{cmd}` (the runs appended to the results file; "
            "this table and figure from all of them). "
            + one_go(rows, args.out, args.figure) + "\n"
        )
        atomic_write_bytes(args.out, text.encode())
    print(f"total {time.perf_counter() - t_all:.0f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    add_arguments(parser)
    sys.exit(run(parser.parse_args()))
