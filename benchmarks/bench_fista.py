"""Time per FISTA-TV and ADMM-TV iteration against the FFT floor, interleaved in one process.

The floor is what one iteration cannot avoid: two rfft2/irfft2 pairs per k-slice at the padded
size (one pair for the forward model, one for the adjoint). Solver steps and the floor are timed
in rounds, in one process, in a rotating order, so the machine's load moves them together: each
round gives one ratio (solver / floor of the same round), and the table reports the median
ratio with its spread (25th-75th percentile over rounds) next to the median times. The thread
count (and why it was chosen) and the load average are printed with the table.

``--threads-check`` adds the thread policy's line: FISTA on the demo problem (the tutorial
PSF and measurement at 1/8 scale) with the policy's thread count against 1 thread, interleaved
the same way; the policy must never be slower than 1 thread.

    lenslesscam bench fista [--sizes 256,512,1024,2048] [--rounds 15] [--threads auto]
                            [--admm-baseline OLD_ADMM.py]
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from app.commands._options import POSITIVE_INT, add_overwrite_option, integer
from benchmarks._cli import bench_metadata, bench_threads, check_outputs, int_list

#: Padded FFT sizes of the 2D cases (the sensor and the PSF are half of it).
SIZES = (256, 512, 1024, 2048)
METHODS = ("fista", "admm")


def _even(text: str) -> int:
    """One padded FFT size: even (the sensor and the PSF are half of it), at least 16."""
    n = integer(16)(text)
    if n % 2:
        raise argparse.ArgumentTypeError(f"must be even, got {n}")
    return n


_even.range_text = "an even integer >= 16"  # type: ignore[attr-defined]
#: ``--sizes``: comma-separated padded FFT sizes, each even and at least 16, each once
_sizes = int_list(_even)


def _methods(text: str) -> list[str]:
    """``--methods``: fista, admm or both, comma-separated."""
    methods = [m.strip() for m in text.split(",") if m.strip()]
    bad = sorted(set(methods) - set(METHODS))
    if bad or not methods:
        raise argparse.ArgumentTypeError(f"must be fista, admm or fista,admm, got {text!r}")
    return methods


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of ``lenslesscam bench fista``."""
    p.add_argument("--sizes", type=_sizes, default=list(SIZES),
                   help="padded FFT sizes of the 2D cases (default 256,512,1024,2048)")
    p.add_argument("--video", action="store_true",
                   help="add a video case (128x128 sensor, K=16 time bins; FISTA only)")
    p.add_argument("--methods", type=_methods, default=list(METHODS),
                   help="fista, admm or both (default)")
    p.add_argument("--rounds", type=integer(3), default=15,
                   help="timed rounds per case, at least 3 (15)")
    p.add_argument("--threads", default=None,
                   help="torch threads: a number, or auto (default: the global --threads, else "
                   "the thread policy, recon.threads)")
    p.add_argument("--prox-iters", type=POSITIVE_INT, default=3,
                   help="inner TV prox iterations (3)")
    p.add_argument("--threads-check", action="store_true",
                   help="also time the policy's thread count against 1 thread on the demo")
    p.add_argument("--admm-baseline", default=None, metavar="FILE",
                   help="also step the Admm class of this older admm.py (for example from "
                   "`git show REV:recon/admm.py`) in the same rounds, as the row "
                   "'admm-baseline' (it imports the current recon package otherwise)")
    p.add_argument("--json", default=None, help="also write the results as JSON here")
    add_overwrite_option(p)


def _quantile(xs: list[float], q: float) -> float:
    s = sorted(xs)
    pos = q * (len(s) - 1)
    lo = int(pos)
    hi = min(lo + 1, len(s) - 1)
    return s[lo] + (s[hi] - s[lo]) * (pos - lo)


def interleave(fns: dict[str, Callable[[], None]], rounds: int, warmup: int = 2,
               block_s: float = 0.05, clock: Callable[[], float] = time.perf_counter
               ) -> dict[str, list[float]]:
    """Seconds per call of each function, one value per round; the order rotates per round.

    Each round times a block of calls lasting about ``block_s`` (the count is fixed per
    function after the warm-up), so a scheduler time slice lost to another process (10 ms or
    more on a loaded machine) spreads over many calls instead of landing on one. ``clock``:
    wall time by default; with one torch thread, :func:`work_clock` (this thread's CPU time)
    leaves out the time other processes held the core.
    """
    names = list(fns)
    reps: dict[str, int] = {}
    for name in names:
        t0 = clock()
        for _ in range(warmup):
            fns[name]()
        one = (clock() - t0) / warmup
        reps[name] = max(1, min(1000, int(block_s / max(one, 1e-6))))
    times: dict[str, list[float]] = {n: [] for n in names}
    for r in range(rounds):
        order = names[r % len(names):] + names[: r % len(names)]
        for name in order:
            fn, k = fns[name], reps[name]
            t0 = clock()
            for _ in range(k):
                fn()
            times[name].append((clock() - t0) / k)
    return times


def work_clock() -> Callable[[], float]:
    """This thread's CPU time when torch runs on one thread (all work is on this thread), else
    wall time: on a shared machine the CPU time is the work itself, without the waits."""
    import torch

    return time.thread_time if torch.get_num_threads() == 1 else time.perf_counter


def ratio_stats(num: list[float], den: list[float]) -> dict[str, float]:
    """Median and quartiles of the per-round ratios num / den."""
    ratios = [a / b for a, b in zip(num, den, strict=True)]
    return {"ratio": round(_quantile(ratios, 0.5), 3),
            "ratio_p25": round(_quantile(ratios, 0.25), 3),
            "ratio_p75": round(_quantile(ratios, 0.75), 3)}


def _load_admm(path: str) -> Any:
    """The ``Admm`` class of an admm.py at ``path``, loaded as a separate module.

    A missing file, a file that is not Python or one without an ``Admm`` class is a
    :class:`ValueError` with one line naming ``--admm-baseline``.
    """
    import importlib.util

    where = f"--admm-baseline {path}"
    if not os.path.exists(path):
        raise ValueError(f"{where}: no such file")
    if not os.path.isfile(path):
        raise ValueError(f"{where}: not a file (name an admm.py)")
    spec = importlib.util.spec_from_file_location("_admm_baseline", path)
    if spec is None or spec.loader is None:
        raise ValueError(f"{where}: cannot be loaded as a Python module (name an admm.py)")
    mod = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(mod)
    except Exception as exc:  # any failure of someone else's file: one line, not a traceback
        first = next((ln for ln in str(exc).splitlines() if ln.strip()), "")
        raise ValueError(f"{where}: cannot be loaded ({type(exc).__name__}: {first})") from None
    if not isinstance(getattr(mod, "Admm", None), type):
        raise ValueError(f"{where}: defines no Admm class")
    return mod.Admm


@contextmanager
def _preconditioned_phase_kept() -> Iterator[None]:
    """Keep a preconditioned FISTA in its first phase while its steps are timed (its end rules,
    a stalled or rising objective, would otherwise switch it to plain steps on this random
    measurement)."""
    import recon.fista as fista_mod

    saved = fista_mod.STALL_WINDOW, fista_mod.PREC_RISE
    fista_mod.STALL_WINDOW, fista_mod.PREC_RISE = 10**18, math.inf
    try:
        yield
    finally:
        fista_mod.STALL_WINDOW, fista_mod.PREC_RISE = saved


def _case_2d(size: int, methods: list[str], rounds: int, prox_iters: int,
             admm_baseline: str | None = None) -> list[dict[str, Any]]:
    import numpy as np
    import torch

    from recon.admm import Admm
    from recon.fista import Fista
    from recon.models import build_model
    from recon.simulate import synthetic_psf
    from recon.threads import fit_threads

    n = size // 2
    psf = synthetic_psf((n, n), n_points=200, seed=0)
    model = build_model("2d", psf)
    fit_threads(model.scene_shape)  # as the commands do: small grids run on one thread
    pad = tuple(model.info["pad"])
    b = torch.as_tensor(np.random.default_rng(0).random(model.meas_shape, dtype=np.float32))
    x = torch.rand(model.scene_shape)

    def floor() -> None:
        for _ in range(2):
            torch.fft.irfft2(torch.fft.rfft2(x, s=pad), s=pad)

    fns: dict[str, Callable[[], None]] = {"floor": floor}
    solvers: dict[str, Any] = {}
    if "fista" in methods:
        # the two kinds of step a default run takes: preconditioned (its first phase, until the
        # objective stalls), then plain
        solvers["fista"] = Fista(model.op, b, tau=1e-3, max_iter=10**9, tol=0.0,
                                 prox_iters=prox_iters, precondition="off")
        solvers["fista-precond"] = Fista(model.op, b, tau=1e-3, max_iter=10**9, tol=0.0,
                                         prox_iters=prox_iters, precondition=0.1)
    if "admm" in methods:
        solvers["admm"] = Admm(model, b, tau=1e-3, max_iter=10**9, tol=0.0)
    if admm_baseline is not None:
        solvers["admm-baseline"] = _load_admm(admm_baseline)(model, b, tau=1e-3,
                                                             max_iter=10**9, tol=0.0)
    for name, s in solvers.items():
        fns[name] = s.step
    with _preconditioned_phase_kept():
        times = interleave(fns, rounds, clock=work_clock())
    pre = solvers.get("fista-precond")
    if pre is not None and pre.params["preconditioned_iterations"] < pre.iteration:
        raise AssertionError("the preconditioned solver left its phase during the timing")
    for s in solvers.values():
        if s.x.dtype != torch.float32:
            raise AssertionError(f"{type(s).__name__} left float32: {s.x.dtype}")
    rows = []
    for name in solvers:
        rows.append({"case": f"2d {n}x{n}", "method": name, "pad": f"{pad[0]}x{pad[1]}",
                     "threads": torch.get_num_threads(),
                     "iter_ms": round(1e3 * _quantile(times[name], 0.5), 2),
                     "floor_ms": round(1e3 * _quantile(times["floor"], 0.5), 2),
                     **ratio_stats(times[name], times["floor"])})
    return rows


def _case_video(rounds: int, prox_iters: int) -> list[dict[str, Any]]:
    import numpy as np
    import torch

    from drivers.timing import SensorTiming
    from recon.fista import Fista
    from recon.models import build_model
    from recon.preprocess import bin_time
    from recon.simulate import synthetic_psf
    from recon.threads import fit_threads
    from recon.tv import TV

    n, k = 128, 16
    psf = synthetic_psf((n, n), n_points=200, seed=0)
    timing = SensorTiming(rows=n, line_time_us=10.0, exposure_lines=n // 2, pattern="outside-in")
    full = timing.shutter(bin_lines=1)
    shutter = bin_time(full, -(-full.shape[0] // k))[:k]
    model = build_model("video", psf, shutter=shutter)
    fit_threads(model.scene_shape)
    pad = tuple(model.info["pad"])
    b = torch.as_tensor(np.random.default_rng(0).random(model.meas_shape, dtype=np.float32))
    solver = Fista(model.op, b, tau=1e-3, tv=TV(weight_k=0.5), max_iter=10**9, tol=0.0,
                   prox_iters=prox_iters)
    x = torch.rand(model.scene_shape)

    def floor() -> None:
        for _ in range(2):
            torch.fft.irfft2(torch.fft.rfft2(x, s=pad), s=pad)

    times = interleave({"floor": floor, "fista": solver.step}, rounds, clock=work_clock())
    return [{"case": f"video {n}x{n} K={k}", "method": "fista", "pad": f"{pad[0]}x{pad[1]}",
             "threads": torch.get_num_threads(),
             "iter_ms": round(1e3 * _quantile(times["fista"], 0.5), 2),
             "floor_ms": round(1e3 * _quantile(times["floor"], 0.5), 2),
             **ratio_stats(times["fista"], times["floor"])}]


def threads_check(chosen: int, rounds: int) -> dict[str, Any]:
    """FISTA on the demo problem: the policy's thread count, 1 thread and all cores, interleaved.

    ``chosen`` is the process's count; an automatic one is fitted to the demo's size first
    (:func:`recon.threads.fit_threads`), as the demo command does.

    Wall time (threads are what is compared). Returns per-count medians and the policy's
    ratio to 1 thread (<= 1: never slower than 1 thread).
    """
    import torch

    from recon import samples
    from recon.fista import Fista
    from recon.models import build_model
    from recon.threads import fit_threads, machine_state

    psf, meas = samples.tutorial_psf(), samples.tutorial_measurement()
    model = build_model("2d", psf)
    fitted = fit_threads(model.scene_shape)  # what `lenslesscam demo` runs this problem with
    if fitted is not None:
        chosen = fitted.threads
    counts = sorted({1, chosen, machine_state()[0]})
    solvers = {t: Fista(model.op, torch.as_tensor(meas), tau=1e-3, max_iter=10**9, tol=0.0)
               for t in counts}

    def stepper(t: int) -> Callable[[], None]:
        def go() -> None:
            torch.set_num_threads(t)
            solvers[t].step()
        return go

    try:
        times = interleave({str(t): stepper(t) for t in counts}, rounds, block_s=0.2)
    finally:
        torch.set_num_threads(chosen)
    return {"chosen": chosen, "ms": {t: round(1e3 * _quantile(times[str(t)], 0.5), 2)
                                     for t in counts},
            **ratio_stats(times[str(chosen)], times["1"])}


def check_memory(sizes: list[int], methods: list[str]) -> None:
    """Refuse, before any allocation, a size whose case would not fit in memory (one line,
    :class:`recon.memory.ProblemTooLarge`), as the reconstruction commands do; and say the
    padded FFT grid of a size the solver pads to another (fast) size."""
    import warnings

    from recon.memory import check_fits, estimate_solver_memory

    for size in sizes:
        n = size // 2
        for method in methods:
            est = estimate_solver_memory((n, n), method=method)
            check_fits(est)
        if tuple(est.pad) != (size, size):
            warnings.warn(f"--sizes {size}: a {n}x{n} sensor and PSF are padded to "
                          f"{est.pad[0]}x{est.pad[1]} (the pad column)", stacklevel=2)


def run(args: argparse.Namespace) -> int:
    """Run the cases and print the table."""

    baseline = getattr(args, "admm_baseline", None)
    check_outputs(args, {"--json": args.json}, inputs={"--admm-baseline": baseline})
    if baseline is not None:
        _load_admm(baseline)  # a bad file stops here, before any timing
    methods = args.methods
    sizes = args.sizes
    check_memory(sizes, methods)  # before anything is built: a large size is one line
    choice = bench_threads(args)
    clock_name = ("CPU time of the one torch thread" if work_clock() is time.thread_time
                  else "wall time")
    load0 = os.getloadavg()[0]
    rows: list[dict[str, Any]] = []
    for size in sizes:
        rows += _case_2d(size, methods, args.rounds, args.prox_iters,
                         getattr(args, "admm_baseline", None))
    if args.video and "fista" in methods:
        rows += _case_video(args.rounds, args.prox_iters)
    check = threads_check(choice.threads, args.rounds) if args.threads_check else None
    load1 = os.getloadavg()[0]
    fitted_note = (" (fitted to each case's size, the threads column)"
                   if choice.source == "auto" else "")
    print(f"Time per iteration vs the FFT floor (2 rfft2/irfft2 pairs per k-slice), interleaved "
          f"in one process, {args.rounds} rounds; {choice.reason}"
          f"{fitted_note}; TV prox inner iterations = "
          f"{args.prox_iters}; load average {load0:.2f} -> {load1:.2f} on "
          f"{os.cpu_count()} CPUs; clock: {clock_name}")
    print("| case | method | padded FFT | threads | iteration (ms) | FFT floor (ms) | "
          "ratio (median) | ratio p25-p75 |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['case']} | {r['method']} | {r['pad']} | {r['threads']} | {r['iter_ms']} | "
              f"{r['floor_ms']} | {r['ratio']:.2f} | {r['ratio_p25']:.2f}-{r['ratio_p75']:.2f} |")
    if check is not None:
        verdict = "not slower" if check["ratio"] <= 1.0 + 0.05 else "SLOWER"
        per = ", ".join(f"{t} thread(s) {ms} ms" for t, ms in check["ms"].items())
        print(f"\nThread policy on the demo (FISTA-TV, tutorial PSF and measurement at 1/8 "
              f"scale, wall time per iteration, interleaved): {per}. The policy's "
              f"{check['chosen']} thread(s) / 1 thread = {check['ratio']:.2f} (p25-p75 "
              f"{check['ratio_p25']:.2f}-{check['ratio_p75']:.2f}): {verdict} than 1 thread "
              f"(load average {os.getloadavg()[0]:.2f})")
    if args.json:
        from recon.atomic import atomic_write_json

        atomic_write_json(args.json, {**bench_metadata("fista", 3, choice),
                                      "sizes": sizes, "methods": methods,
                                      "prox_iters": args.prox_iters, "video": args.video,
                                      "load": [load0, load1], "rounds": args.rounds,
                                      "rows": rows, "threads_check": check})
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    add_arguments(parser)
    sys.exit(run(parser.parse_args()))
