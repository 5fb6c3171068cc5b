"""Time per UDN iteration (fp32 / bf16, eager / torch.compile) and peak memory.

The gain is fixed at 1 and the clipping correction is off, so what is timed is the plain
iteration (random data at gain 1 clips, and the correction widened the gain and snapshotted the
state every 20 iterations; the GPU rows of docs/real-pairs-gpu.md, 2026-11-27, include that).
Cases: 2D 150x200 and 256x256 (one image), and 128x128 with 16 frames (video model, frames as
output channels and, with ``--with-3d``, the 3D network); ``rgb-270x480`` is the geometry of
the real DiffuserCam pairs at full resolution (colour, the PSF and measurement on the padded
540x960 grid). ``--profile`` (on a GPU) adds what keeps the device idle: per iteration the
code's reads of device values, the synchronize calls and kernel launches, and its busy time
against the wall time. Each case is timed over ``--iters``
iterations after ``--warmup`` (the first call of a compiled network compiles it; its time is
reported separately). Peak memory: ``torch.cuda.max_memory_allocated`` on a GPU; on the CPU
each case runs in a fresh subprocess and reports its peak resident set (``ru_maxrss``) above
the baseline after imports. The estimate of ``recon.udn.memory`` is printed beside it.

    lenslesscam bench udn [--device auto] [--channels 128] [--scales 5] [--iters 5]
                          [--precision float32 bf16] [--compile off on] [--cases 2d-150x200 ...]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from app.commands._options import NONNEG_INT, POSITIVE_INT, add_overwrite_option
from benchmarks._cli import bench_metadata, bench_threads, check_outputs
from recon.udn import COMPILE_MODES

#: the default run's time (``--help``; the bench review measured it, docs/udn.md: about 105 s
#: to compile each of the 6 compiled rows)
DURATION = ("long: more than 15 minutes on a 2-core CPU (12 processes, 6 of them compiling "
            "for about 105 s each, docs/udn.md)")

CASES: dict[str, dict[str, Any]] = {
    "2d-75x100": {"model": "2d", "shape": (75, 100), "k": 1, "variant": "2d"},
    "2d-150x200": {"model": "2d", "shape": (150, 200), "k": 1, "variant": "2d"},
    "2d-256x256": {"model": "2d", "shape": (256, 256), "k": 1, "variant": "2d"},
    "video-128x128x16": {"model": "video", "shape": (128, 128), "k": 16, "variant": "frames"},
    "video3d-128x128x16": {"model": "video", "shape": (128, 128), "k": 16, "variant": "3d"},
    # the DiffuserCam MirFlickr geometry at full resolution: colour, the scene on the sensor's
    # 270x480 field, the PSF and the measurement on the padded 540x960 grid, the sensor in
    # its centre (the rest masked out), as the real pairs are read
    "rgb-270x480": {"model": "2d", "shape": (270, 480), "k": 1, "variant": "2d", "colour": 3,
                    "grid": (540, 960)},
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of ``lenslesscam bench udn``."""
    p.add_argument("--device", default="auto", help="auto, cpu, cuda, mps")
    p.add_argument("--cases", nargs="+", default=["2d-150x200", "2d-256x256",
                                                  "video-128x128x16"],
                   choices=list(CASES), help="which cases")
    p.add_argument("--with-3d", action="store_true", help="add the 3D-network video case")
    p.add_argument("--channels", type=POSITIVE_INT, default=128, help="network channels (128)")
    p.add_argument("--scales", type=POSITIVE_INT, default=5, help="network scales (5)")
    p.add_argument("--iters", type=POSITIVE_INT, default=5, help="timed iterations per case (5)")
    p.add_argument("--warmup", type=NONNEG_INT, default=2, help="untimed iterations first (2)")
    p.add_argument("--precision", nargs="+", default=["float32", "bf16"],
                   choices=["float32", "bf16"], help="network precision: float32 or bf16")
    p.add_argument("--compile", nargs="+", default=["off", "on"], choices=["off", "on"],
                   help="torch.compile the network")
    p.add_argument("--compile-mode", default="default",
                   choices=COMPILE_MODES,
                   help="torch.compile's mode for the compiled rows (default; reduce-overhead: "
                   "CUDA graphs)")
    p.add_argument("--threads", type=NONNEG_INT, default=None,
                   help="torch threads (default or 0: the global --threads, else the thread "
                   "policy, recon.threads, chosen once and used by every row's process)")
    p.add_argument("--grad-checkpoint", action="store_true", help="gradient checkpointing")
    p.add_argument("--profile", action="store_true",
                   help="on a GPU: run the timed iterations twice more and report per "
                   "iteration the code's reads of device values (torch's sync debug mode), "
                   "the synchronize calls and kernel launches (torch.profiler), and the "
                   "device's busy time against the wall time")
    p.add_argument("--json", help="also write the rows as JSON here (not with --ratio)")
    p.add_argument("--ratio", action="store_true",
                   help="bf16 / float32 step-time ratio instead of the matrix: both runners in "
                   "one process, steps interleaved over --rounds rounds, median and p25-p75, "
                   "and where the time goes (a torch.profiler breakdown by kind of op)")
    p.add_argument("--rounds", type=POSITIVE_INT, default=9, help="rounds of --ratio (9)")
    p.add_argument("--case-json", help=argparse.SUPPRESS)  # internal: run one case, print JSON
    add_overwrite_option(p)


def _peak_rss_bytes() -> int:
    import resource

    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024  # Linux: KiB


def _problem(case: dict[str, Any], device: Any) -> tuple[Any, Any]:
    import numpy as np

    from recon.models import build_model
    from recon.simulate import synthetic_psf

    h, w = case["shape"]
    psf = synthetic_psf((h, w), seed=1)
    rng = np.random.default_rng(0)
    if case["model"] == "video":
        k = case["k"]
        shutter = np.zeros((k, h))
        rows = np.array_split(np.arange(h), k)
        for i, r in enumerate(rows):
            shutter[i, r] = 1.0
        model = build_model("video", psf, shutter=shutter, device=device)
    elif "grid" in case:
        gh, gw = case["grid"]
        psf = np.stack([synthetic_psf((gh, gw), seed=1 + i) for i in range(case["colour"])])
        mask = np.zeros((gh, gw), dtype=np.float32)
        mask[(gh - h) // 2:(gh - h) // 2 + h, (gw - w) // 2:(gw - w) // 2 + w] = 1
        model = build_model("2d", psf, mask=mask, field=(h, w), device=device)
    else:
        model = build_model("2d", psf, device=device)
    b = rng.random(model.meas_shape).astype(np.float32)
    return model, b


def run_one(name: str, precision: str, compiled: bool, args: argparse.Namespace) -> dict[str, Any]:
    """Time one configuration in this process."""
    import torch

    from recon.udn.memory import estimate_udn_memory
    from recon.udn.network import NetworkConfig
    from recon.udn.runner import UDNConfig, UDNRunner, resolve_device

    bench_threads(args)
    device = resolve_device(args.device)
    case = CASES[name]
    _load_kernels(precision, device)  # library code pages count in the baseline, not the run
    base_rss = _peak_rss_bytes()
    model, b = _problem(case, device)
    net = NetworkConfig(variant=case["variant"], scales=args.scales, channels=args.channels,
                        gradient_checkpointing=args.grad_checkpoint)
    cfg = UDNConfig(precision=precision, compile=compiled, max_iter=10**9, holdout=0.05,
                    gain=1.0, compile_mode=args.compile_mode, clip_adapt=False)
    est = estimate_udn_memory(net, model.scene_shape, model.meas_shape, precision=precision)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    t0 = time.perf_counter()
    runner = UDNRunner(model, b, network=net, config=cfg)
    runner.step()  # the first step (compiles when compiled)
    _sync(device)
    first = time.perf_counter() - t0
    for _ in range(max(0, args.warmup - 1)):
        runner.step()
    _sync(device)
    t1 = time.perf_counter()
    for _ in range(args.iters):
        runner.step()
    _sync(device)
    per_iter = (time.perf_counter() - t1) / max(args.iters, 1)
    prof: dict[str, Any] = {}
    if args.profile and device.type == "cuda":
        try:
            prof = device_profile(runner, device, args.iters)
            prof["busy_fraction"] = prof["device_s_per_iter"] / per_iter
        except Exception as exc:  # a profiler that fails costs the columns, not the row
            prof = {"profile_error": f"{type(exc).__name__}: {exc}".splitlines()[0]}
    if device.type == "cuda":
        peak = int(torch.cuda.max_memory_allocated(device))
        peak_src = "cuda max allocated"
    else:
        peak = _peak_rss_bytes() - base_rss
        peak_src = "ru_maxrss above baseline"
    return {
        "case": name, "precision": precision, "compile": compiled,
        "compile_mode": args.compile_mode if compiled else None,
        "compile_active": bool(runner._compiled), "notes": runner.notes,
        "device": str(device), "threads": torch.get_num_threads(),
        "scene": list(model.scene_shape), "variant": net.variant, "channels": net.channels,
        "scales": net.scales, "params": runner.G.parameter_count(),
        "first_step_s": first, "per_iter_s": per_iter, "peak_bytes": peak,
        "peak_source": peak_src, "estimate_bytes": est.total_bytes, **prof,
    }


#: host-side CUDA runtime calls that wait for the device (a read-back ends in one of them)
WAIT_CALLS = ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize")


def profile_counts(events: Any, iters: int) -> dict[str, float]:
    """Per-iteration counts from torch.profiler events (``prof.events()``) of ``iters`` steps:
    the synchronize calls (:data:`WAIT_CALLS`), kernel launches (``cudaLaunch*`` /
    ``cuLaunch*``), and the device's busy seconds (the summed duration of its events: kernels,
    copies, fills; one stream, so they do not overlap)."""
    waits = launches = 0
    device_us = 0.0
    for ev in events:
        name = str(ev.name)
        if str(ev.device_type).endswith("CPU"):
            if name.startswith(WAIT_CALLS):
                waits += 1
            elif name.startswith(("cudaLaunch", "cuLaunch")):
                launches += 1
        else:
            device_us += float(ev.time_range.end - ev.time_range.start)
    n = max(iters, 1)
    return {"waits_per_iter": waits / n, "launches_per_iter": launches / n,
            "device_s_per_iter": device_us / 1e6 / n}


def device_profile(runner: Any, device: Any, iters: int) -> dict[str, float]:
    """Profile ``iters`` more steps of ``runner`` on a CUDA device: :func:`profile_counts`,
    and the synchronising operations torch's sync debug mode flags in ``iters`` steps more
    (``reads_per_iter``: the reads of device values by the code, which the profiler's count of
    synchronize calls does not tell from the library's own)."""
    import warnings

    import torch
    from torch.profiler import ProfilerActivity, profile

    _sync(device)
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        for _ in range(iters):
            runner.step()
        _sync(device)
    out = profile_counts(prof.events(), iters)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode(1)
        try:
            for _ in range(iters):
                runner.step()
        finally:
            torch.cuda.set_sync_debug_mode(0)
    out["reads_per_iter"] = sum("synchronizing" in str(w.message) for w in seen) / max(iters, 1)
    return out


def _load_kernels(precision: str, device: Any) -> None:
    """One step of a tiny run, so lazily loaded kernels are resident before the baseline."""
    import numpy as np

    from recon.models import build_model
    from recon.udn.network import NetworkConfig
    from recon.udn.runner import UDNConfig, UDNRunner

    for model in (build_model("2d", np.ones((16, 16)), device=device),
                  build_model("video", np.ones((16, 16)), shutter=np.ones((2, 16)),
                              device=device)):
        for variant in ("2d", "3d") if model.k == 1 else ("frames", "3d"):
            if variant == "3d" and model.k == 1:
                continue
            net = NetworkConfig(variant=variant, scales=2, channels=4, input_channels=2)
            UDNRunner(model, np.ones(model.meas_shape, dtype=np.float32), network=net,
                      config=UDNConfig(precision=precision,
                                       gain=1.0, holdout=0.0)).step()


def _sync(device: Any) -> None:
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _run_isolated(name: str, precision: str, compiled: bool,
                  args: argparse.Namespace) -> dict[str, Any]:
    """Run one configuration in a fresh process (clean peak-RSS on the CPU)."""
    spec = json.dumps({"case": name, "precision": precision, "compile": compiled})
    argv = [sys.executable, "-m", "benchmarks.bench_udn", "--case-json", spec,
            "--device", args.device, "--channels", str(args.channels), "--scales",
            str(args.scales), "--iters", str(args.iters), "--warmup", str(args.warmup),
            "--threads", str(args.threads), "--compile-mode", args.compile_mode]
    if args.grad_checkpoint:
        argv.append("--grad-checkpoint")
    if args.profile:
        argv.append("--profile")
    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ)
    env["PYTHONPATH"] = str(root) + os.pathsep + env.get("PYTHONPATH", "")
    res = subprocess.run(argv, cwd=root, env=env, capture_output=True, text=True)
    if res.returncode != 0:
        return {"case": name, "precision": precision, "compile": compiled,
                "error": (res.stderr.strip().splitlines() or ["?"])[-1]}
    row: dict[str, Any] = json.loads(res.stdout.strip().splitlines()[-1])
    return row


def _fmt_bytes(n: float | None) -> str:
    if n is None:
        return "-"
    return f"{n / 2**20:.0f} MiB"


#: kinds of op in the profile breakdown of ``--ratio`` (first match of the op name wins)
OP_KINDS = (
    ("convolution (forward and backward)", ("conv",)),
    ("FFT (forward model, float32)", ("fft",)),
    ("normalisation", ("norm",)),
    ("dtype casts and copies (autocast)", ("_to_copy", "copy_", "to", "clone", "contiguous")),
    ("activations", ("relu", "sigmoid", "tanh", "elu")),
    ("resampling", ("upsample", "pool", "interpolate", "pad")),
    ("optimizer", ("adam", "_foreach", "addcdiv", "lerp", "sqrt")),
)


def _kind(name: str) -> str:
    n = name.lower().removeprefix("aten::")
    for kind, keys in OP_KINDS:
        if any(k in n for k in keys):
            return kind
    return "other"


def _profile_step(runner: Any) -> dict[str, float]:
    """Self CPU time (s) of one step by kind of op."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        runner.step()
    out: dict[str, float] = {}
    for ev in prof.key_averages():
        if not ev.key.startswith("aten::"):
            continue
        out[_kind(ev.key)] = out.get(_kind(ev.key), 0.0) + ev.self_cpu_time_total / 1e6
    return out


def profile_table(base: dict[str, float], other: dict[str, float], label: str) -> str:
    """The Markdown table of two profiles (:func:`_profile_step`): float32 against ``label``
    (the variant compared, for example "bf16 channels-last"), headed by what was compared.

    The casts row says "autocast" only when the variant is bf16 (float32 runs no autocast).
    """
    kinds = sorted(set(base) | set(other), key=lambda k: -base.get(k, 0.0))
    tot_a, tot_c = sum(base.values()), sum(other.values())
    autocast = label.startswith("bf16")
    lines = [f"| kind of op | float32 (ms) | share | {label} (ms) | share | "
             f"{label} / float32 |", "|---|---|---|---|---|---|"]
    for kd in kinds:
        a, c = base.get(kd, 0.0), other.get(kd, 0.0)
        name = kd if autocast else kd.replace(" (autocast)", "")
        lines.append(f"| {name} | {1e3 * a:.0f} | {100 * a / tot_a:.0f} % | "
                     f"{1e3 * c:.0f} | {100 * c / tot_c:.0f} % | "
                     f"{(c / a) if a > 0 else float('nan'):.2f} |")
    lines.append(f"| total | {1e3 * tot_a:.0f} | 100 % | {1e3 * tot_c:.0f} | "
                 f"100 % | {tot_c / tot_a:.2f} |")
    return "\n".join(lines)


def run_ratio(args: argparse.Namespace) -> int:
    """bf16 / float32 per-step time, interleaved in one process, and where the time goes."""
    import statistics

    import torch

    from recon.udn.network import NetworkConfig
    from recon.udn.runner import UDNConfig, UDNRunner, resolve_device

    choice = bench_threads(args)
    device = resolve_device(args.device)
    if device.type != "cpu":
        print("--ratio times CPU steps (thread CPU time); use the matrix on a GPU",
              file=sys.stderr)
        return 2
    one_thread = torch.get_num_threads() == 1
    clock = time.thread_time if one_thread else time.perf_counter
    load0 = os.getloadavg()[0]
    for name in args.cases:
        case = CASES[name]
        model, b = _problem(case, device)
        net = NetworkConfig(variant=case["variant"], scales=args.scales, channels=args.channels)
        variants = {"float32": ("float32", False), "float32 channels-last": ("float32", True),
                    "bf16": ("bf16", False), "bf16 channels-last": ("bf16", True)}
        runners = {v: UDNRunner(model, b, network=net,
                                config=UDNConfig(precision=p, channels_last=cl, max_iter=10**9,
                                                 holdout=0.05, gain=1.0, seed=0,
                                                 clip_adapt=False))
                   for v, (p, cl) in variants.items()}
        for r in runners.values():
            for _ in range(max(1, args.warmup)):
                r.step()
        times: dict[str, list[float]] = {v: [] for v in variants}
        names = list(variants)
        for k in range(args.rounds):
            for v in names[k % len(names):] + names[:k % len(names)]:  # rotate the order
                t = clock()
                runners[v].step()
                times[v].append(clock() - t)
        print(f"\n{name}: {args.scales} scales x {args.channels} channels; {choice.reason}; "
              f"clock: {'CPU time of the one torch thread' if one_thread else 'wall'}; "
              f"load {load0:.2f} -> {os.getloadavg()[0]:.2f}; {args.rounds} interleaved rounds")
        print("| network | step (ms, median) | / float32 (median of rounds) | p25-p75 |")
        print("|---|---|---|---|")
        for v in names:
            ratios = sorted(a / f for a, f in zip(times[v], times["float32"], strict=True))
            q = statistics.quantiles(ratios, n=4) if len(ratios) > 1 else [ratios[0]] * 3
            print(f"| {v} | {1e3 * statistics.median(times[v]):.0f} | "
                  f"**{statistics.median(ratios):.2f}** | {q[0]:.2f}-{q[2]:.2f} |")
        best = min(names[1:], key=lambda v: statistics.median(times[v]))
        prof = {"float32": _profile_step(runners["float32"]), best: _profile_step(runners[best])}
        print(f"\n(profile: float32 against {best})")
        print("\nWhere one step's time goes (torch.profiler, self CPU time of aten ops):\n")
        print(profile_table(prof["float32"], prof[best], best))
    return 0


def run_udn_benchmark(args: argparse.Namespace) -> int:
    """Run the benchmark matrix and print the table."""
    if args.ratio and args.json and not args.case_json:
        raise ValueError("--json: --ratio writes no JSON (its tables are printed); leave out "
                         "one of them")
    if not args.case_json:
        check_outputs(args, {"--json": args.json})
    if args.ratio and not args.case_json:
        return run_ratio(args)
    if args.case_json:
        spec = json.loads(args.case_json)
        row = run_one(spec["case"], spec["precision"], spec["compile"], args)
        print(json.dumps(row))
        return 0
    import torch

    from recon.udn.runner import describe_device, resolve_device

    choice = bench_threads(args)  # one count for every row: passed to each row's process
    device = resolve_device(args.device)
    cases = list(args.cases) + (["video3d-128x128x16"] if args.with_3d else [])
    rows = []
    for name in cases:
        for precision in args.precision:
            for comp in args.compile:
                compiled = comp == "on"
                if device.type == "cpu":
                    row = _run_isolated(name, precision, compiled, args)
                else:
                    try:
                        row = run_one(name, precision, compiled, args)
                    except Exception as exc:  # report it in the table, go on
                        row = {"case": name, "precision": precision, "compile": compiled,
                               "error": f"{type(exc).__name__}: {exc}".splitlines()[0]}
                    torch.cuda.empty_cache() if device.type == "cuda" else None
                rows.append(row)
                print(_line(row), file=sys.stderr)
    counts = sorted({r["threads"] for r in rows if "threads" in r}) or [choice.threads]
    threads = counts[0] if len(counts) == 1 else "/".join(map(str, counts))
    dev_name = describe_device(device)
    print(f"\nUDN iteration time on {dev_name}, {threads} torch threads, "
          f"{args.scales} scales x {args.channels} channels, skip 4, "
          f"{args.iters} timed iterations after {args.warmup} warm-up"
          + (", gradient checkpointing" if args.grad_checkpoint else ""))
    profiled = args.profile and device.type == "cuda"
    print("| case | scene (C,K,H,W) | network | precision | compile | first step (s) | "
          "per iteration (s) | peak memory | estimate |"
          + (" reads / it. | sync calls / it. | launches / it. | device busy |"
             if profiled else ""))
    print("|---|---|---|---|---|---|---|---|---|" + ("---|---|---|---|" if profiled else ""))
    for r in rows:
        print(_line(r, table=True, profiled=profiled))
    if args.profile and not profiled:
        print("(--profile: only on a CUDA device; nothing profiled here)")
    if args.json:
        from recon.atomic import atomic_write_json

        atomic_write_json(args.json, {**bench_metadata("udn", 1, choice), "rows": rows,
                                      "device": dev_name,
                                      "settings": {k: getattr(args, k) for k in (
                                          "cases", "precision", "compile", "channels", "scales",
                                          "iters", "warmup", "compile_mode", "grad_checkpoint")}})
    return 0


def _line(r: dict[str, Any], table: bool = False, profiled: bool = False) -> str:
    comp = "on" if r.get("compile") else "off"
    if "error" in r:
        body = [r["case"], "-", "-", r["precision"], comp, "-", f"failed: {r['error']}", "-",
                "-"]
    else:
        if r["compile"] and r.get("compile_mode") not in (None, "default"):
            comp = f"on ({r['compile_mode']})"
        if r["compile"] and not r["compile_active"]:
            comp = "on (fell back to eager)"
        body = [r["case"], "x".join(map(str, r["scene"])), r["variant"], r["precision"], comp,
                f"{r['first_step_s']:.2f}", f"{r['per_iter_s']:.3f}",
                f"{_fmt_bytes(r['peak_bytes'])} ({r['peak_source']})",
                _fmt_bytes(r["estimate_bytes"])]
    if profiled:
        if "waits_per_iter" in r:
            body += [f"{r['reads_per_iter']:.1f}", f"{r['waits_per_iter']:.1f}",
                     f"{r['launches_per_iter']:.0f}",
                     f"{100 * r['busy_fraction']:.0f} % ({1e3 * r['device_s_per_iter']:.1f} "
                     "ms)"]
        else:
            body += [r.get("profile_error", "-"), "-", "-", "-"]
    return ("| " + " | ".join(body) + " |") if table else "  ".join(body)


#: ``lenslesscam bench udn`` calls ``run``.
run = run_udn_benchmark


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    add_arguments(parser)
    sys.exit(run_udn_benchmark(parser.parse_args()))
