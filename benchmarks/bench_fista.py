"""Time per FISTA-TV iteration against the FFT floor, and peak memory.

The floor is what one iteration cannot avoid: two rfft2/irfft2 pairs per k-slice at the padded
size (one pair for the forward model, one for the adjoint). Each case runs in a fresh
subprocess so its peak resident memory (ru_maxrss) is its own.

    lenslesscam bench fista [--threads 2] [--iters 30]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from typing import Any

CASES: list[dict[str, Any]] = [
    {"name": "2d 256x256", "kind": "2d", "size": 256, "k": 1},
    {"name": "2d 512x512", "kind": "2d", "size": 512, "k": 1},
    {"name": "video 128x128 K=16", "kind": "video", "size": 128, "k": 16},
    {"name": "video 128x128 K=64", "kind": "video", "size": 128, "k": 64},
]


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of ``lenslesscam bench fista``."""
    p.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    p.add_argument("--iters", type=int, default=30, help="timed iterations per case")
    p.add_argument("--cases", default="all", help="comma-separated case indices (default all)")
    p.add_argument("--prox-iters", type=int, default=3, help="inner TV prox iterations")
    p.add_argument("--json", default=None, help="also write the results as JSON here")


def _median(xs: list[float]) -> float:
    s = sorted(xs)
    return s[len(s) // 2]


def measure_case(case: dict[str, Any], threads: int, iters: int, prox_iters: int) -> dict[str, Any]:
    """Run one case in this process; return its timings."""
    import resource

    import numpy as np
    import torch

    from drivers.timing import SensorTiming, bin_time
    from recon.fista import Fista
    from recon.models import build_model
    from recon.simulate import synthetic_psf
    from recon.tv import TV

    torch.set_num_threads(threads)
    n, k = case["size"], case["k"]
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    psf = synthetic_psf((n, n), n_points=200, seed=0)
    if case["kind"] == "video":
        timing = SensorTiming(rows=n, line_time_us=10.0, exposure_lines=n // 2,
                              pattern="outside-in")
        full = timing.shutter(bin_lines=1)
        shutter = bin_time(full, -(-full.shape[0] // k))[:k]
        model = build_model("video", psf, shutter=shutter)
        tv = TV(weight_k=0.5)
    else:
        model = build_model("2d", psf)
        tv = TV()
    rng = np.random.default_rng(0)
    b = torch.as_tensor(rng.random(model.meas_shape, dtype=np.float32))
    solver = Fista(model.op, b, tau=1e-3, tv=tv, max_iter=10**9, tol=0.0, prox_iters=prox_iters)
    for _ in range(3):
        solver.step()
    times = []
    for _ in range(iters):
        t0 = time.perf_counter()
        solver.step()
        times.append(time.perf_counter() - t0)
    assert solver.x.dtype == torch.float32
    pad = model.info["pad"]
    x = torch.rand((1, k, n, n))
    floor = []
    for i in range(iters + 3):
        t0 = time.perf_counter()
        for _ in range(2):
            xf = torch.fft.rfft2(x, s=pad)
            torch.fft.irfft2(xf, s=pad)
        if i >= 3:
            floor.append(time.perf_counter() - t0)
    rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    it_ms = 1e3 * _median(times)
    floor_ms = 1e3 * _median(floor)
    return {
        "case": case["name"], "pad": f"{pad[0]}x{pad[1]}", "k": k, "threads": threads,
        "iter_ms": round(it_ms, 2), "floor_ms": round(floor_ms, 2),
        "ratio": round(it_ms / floor_ms, 2), "peak_rss_mb": round((rss1 - rss0) / 1024, 1),
    }


def run(args: argparse.Namespace) -> int:
    """Run every case in a subprocess and print the table."""
    picked = CASES if args.cases == "all" else [CASES[int(i)] for i in args.cases.split(",")]
    rows = []
    for case in picked:
        cmd = [sys.executable, "-m", "benchmarks.bench_fista", "--one", json.dumps(case),
               str(args.threads), str(args.iters), str(args.prox_iters)]
        out = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if out.returncode != 0:
            print(out.stderr, file=sys.stderr)
            return 1
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    print(f"FISTA-TV time per iteration vs the FFT floor (2 rfft2/irfft2 pairs per k-slice), "
          f"torch threads = {args.threads}, TV prox inner iterations = {args.prox_iters}")
    print("| case | padded FFT | iteration (ms) | FFT floor (ms) | ratio | peak RSS (MB) |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['case']} | {r['pad']} | {r['iter_ms']} | {r['floor_ms']} | {r['ratio']} | "
              f"{r['peak_rss_mb']} |")
    if args.json:
        from recon.formats import atomic_write_json

        atomic_write_json(args.json, rows)
    return 0


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--one":
        res = measure_case(json.loads(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]),
                           int(sys.argv[5]))
        print(json.dumps(res))
    else:
        parser = argparse.ArgumentParser(description=__doc__)
        add_arguments(parser)
        sys.exit(run(parser.parse_args()))
