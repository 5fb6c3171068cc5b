"""Batch throughput on Ray: items per minute for 1 and 2 workers against one process.

The same N small FISTA items (simulated 2D measurements, tutorial-like synthetic PSF) run
(a) one after another in this process through the batch task function (exactly what a Ray
task calls), (b) with ``lenslesscam batch`` on an embedded Ray with 1 CPU and (c) with 2 CPUs,
each cold (fresh workers, or this process, import torch and plan FFTs first) and warm (the
same Ray or process again, a fresh batch folder).
Ray's own overhead is measured directly: the round trip of an empty task (submit + get, one at
a time) and the start of Ray. Every task uses 1 torch thread; the table states the load.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

from app.commands._options import POSITIVE_INT, add_overwrite_option
from benchmarks._cli import hxw, int_list

#: the smallest side of ``--size`` (the synthetic scenes' rectangles need 5 to h/2 pixels)
MIN_SIDE = 16
#: file in a ``--keep`` folder listing what this benchmark wrote there (all it removes)
KEEP_MARKER = ".lenslesscam-bench-batch.json"
#: names this benchmark writes in a ``--keep`` folder (nothing else is ever removed)
KEEP_NAMES = re.compile(r"data|seq-(cold|warm)|ray\d+-(cold|warm)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of ``lenslesscam bench batch``."""
    p.add_argument("--items", type=POSITIVE_INT, default=16, help="items per batch (16)")
    p.add_argument("--size", type=hxw(MIN_SIDE), default="48x64",
                   help=f"measurement size HxW, both sides >= {MIN_SIDE} (48x64)")
    p.add_argument("--iters", type=POSITIVE_INT, default=100, help="FISTA iterations (100)")
    p.add_argument("--workers", type=int_list(POSITIVE_INT), default="1,2",
                   help="comma-separated Ray CPU counts to try, each >= 1 (1,2)")
    p.add_argument("--noop", type=POSITIVE_INT, default=50,
                   help="empty tasks timed for Ray's overhead (50)")
    p.add_argument("--keep", help="keep the data and batch folders here: a new or empty folder, "
                   "or with --overwrite one an earlier bench batch wrote to (what it wrote "
                   "there is removed first, nothing else)")
    add_overwrite_option(p)


def _keep_entries(workers: list[int]) -> list[str]:
    """The names this benchmark writes in its folder."""
    return ["data", "seq-cold", "seq-warm",
            *(f"ray{k}-{label}" for k in workers for label in ("cold", "warm"))]


def prepare_keep(folder: Path, workers: list[int], overwrite: bool) -> None:
    """Make ``--keep`` ready for a fresh run, before any work.

    A folder that is not empty is refused without ``overwrite`` (the batch folders of an earlier
    run would be resumed against newly written data); with it, the entries an earlier run of
    this benchmark listed in :data:`KEEP_MARKER` are removed, and nothing else: a name this run
    writes that is there but was not written by it is refused. The marker then lists this run's
    entries (written first, so an interrupted run is recognised too).
    """
    from app.commands._options import check_output_folders
    from recon.atomic import atomic_write_bytes

    if folder.exists() and not folder.is_dir():
        raise FileExistsError(f"--keep {folder} is a file: name a folder")
    check_output_folders([folder / KEEP_MARKER])
    planned = _keep_entries(workers)
    owned: set[str] = set()
    marker = folder / KEEP_MARKER
    if folder.is_dir() and any(folder.iterdir()):
        if not overwrite:
            raise FileExistsError(
                f"--keep {folder} is not empty: pass --overwrite to replace what an earlier "
                "bench batch wrote there, or name a new or empty folder")
        try:
            listed = json.loads(marker.read_text(encoding="utf-8")).get("entries", [])
            owned = {e for e in listed if isinstance(e, str) and KEEP_NAMES.fullmatch(e)}
        except (OSError, ValueError, AttributeError):
            owned = set()
        foreign = [e for e in planned if (folder / e).exists() and e not in owned]
        if foreign:
            raise FileExistsError(
                f"--keep {folder} holds {', '.join(foreign)}, which bench batch did not write "
                "there: name another folder")
        for e in sorted(owned):
            path = folder / e
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            elif path.exists() or path.is_symlink():
                path.unlink()
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(marker, json.dumps(
        {"format": "lenslesscam.bench_batch.keep", "entries": planned}).encode())


def _make(folder: Path, n: int, h: int, w: int, iters: int) -> Path:
    import numpy as np

    from recon.models import build_model
    from recon.simulate import simulate, synthetic_psf

    (folder / "meas").mkdir(parents=True, exist_ok=True)
    psf = synthetic_psf((h, w), seed=1)
    np.save(folder / "psf.npy", psf)
    model = build_model("2d", psf)
    rng = np.random.default_rng(0)
    for i in range(n):
        scene = np.zeros((h, w))
        for _ in range(5):
            y, x = rng.integers(0, h - 8), rng.integers(0, w - 8)
            scene[y : y + rng.integers(4, h // 2), x : x + rng.integers(4, w // 2)] += 1.0
        sim = simulate(model, scene[None, None], noise=0.01, seed=i)
        np.save(folder / "meas" / f"m{i:03d}.npy", sim.meas)
    manifest = folder / "manifest.csv"
    manifest.write_text(f"measurement,psf,method,iters,tau\nmeas/m*.npy,psf.npy,fista,{iters},"
                        "1e-3\n")
    return manifest


def _noop() -> int:
    return os.getpid()


def _ray_overhead(n: int) -> tuple[float, float]:
    """(ms per empty task one at a time, ms per empty task submitted together)."""
    import ray

    f = ray.remote(num_cpus=1)(_noop)
    ray.get(f.remote())  # a worker is up
    t = time.perf_counter()
    for _ in range(n):
        ray.get(f.remote())
    serial = (time.perf_counter() - t) / n * 1e3
    t = time.perf_counter()
    ray.get([f.remote() for _ in range(n)])
    together = (time.perf_counter() - t) / n * 1e3
    return serial, together


def run(args: argparse.Namespace) -> int:
    """Print the table (Markdown)."""
    from app.batch.driver import BatchOptions, run_batch, start_ray
    from app.batch.manifest import input_hashes, item_hash, read_manifest
    from app.batch.state import BatchPaths
    from app.batch.task import run_item

    h, w = args.size
    workers = args.workers
    if args.keep is not None and not args.keep.strip():
        raise ValueError("--keep: the path is empty: name a folder")
    if args.keep is not None:
        prepare_keep(Path(args.keep), workers, bool(getattr(args, "overwrite", False)))
    tmp = None if args.keep else tempfile.TemporaryDirectory(prefix="bench-batch-")
    root = Path(args.keep or tmp.name)  # type: ignore[union-attr]
    os.environ["OMP_NUM_THREADS"] = "1"
    manifest = _make(root / "data", args.items, h, w, args.iters)
    items = read_manifest(manifest)
    n = len(items)
    load0 = os.getloadavg()[0]
    rows: list[tuple[str, float, str]] = []

    # (a) one process, one item after another, through the task function; cold (first
    # imports and FFT plans in this process) and warm (a second pass, fresh folder)
    t_seq = 0.0
    for label in ("cold", "warm"):
        seq = BatchPaths(root / f"seq-{label}")
        seq.make()
        t = time.perf_counter()
        for it in items:
            hashes = input_hashes(it)
            rec = run_item(it, str(seq.root), item_hash(it, hashes), hashes, cpus=1)
            if rec["status"] != "done":
                raise RuntimeError(f"{it.id}: {rec.get('error')}")
        t_seq = time.perf_counter() - t
        rows.append((f"one process, sequential, {label}", t_seq, "-"))

    import ray

    notes: list[str] = []
    for k in workers:
        t = time.perf_counter()
        start_ray(None, k)
        init_s = time.perf_counter() - t
        try:
            opts = BatchOptions(progress=False, poll_s=0.05)
            for label in ("cold", "warm"):
                t = time.perf_counter()
                rep = run_batch(manifest, root / f"ray{k}-{label}", opts)
                wall = time.perf_counter() - t
                if rep.counts.get("done") != n:
                    raise RuntimeError(f"batch with {k} CPUs: {rep.counts}")
                rows.append((f"Ray, {k} worker(s), {label}", wall, f"{init_s:.1f} s"
                             if label == "cold" else "(running)"))
            serial, together = _ray_overhead(args.noop)
            notes.append(f"{k} CPU(s): empty task {serial:.2f} ms one at a time, "
                         f"{together:.2f} ms each when {args.noop} are submitted together; "
                         f"Ray start {init_s:.1f} s")
        finally:
            ray.shutdown()
    load1 = os.getloadavg()[0]
    print(f"# bench batch: {n} FISTA items {h}x{w}, {args.iters} iterations, 1 torch thread "
          f"per task; {os.cpu_count()} cores, load {load0:.2f} -> {load1:.2f}\n")
    print("| run | wall s | items / min | per item s | vs one process (warm) | Ray start |")
    print("|---|---|---|---|---|---|")
    for label, wall, init in rows:
        print(f"| {label} | {wall:.2f} | {n / wall * 60:.1f} | {wall / n:.3f} | "
              f"{t_seq / wall:.2f}x | {init} |")
    print()
    for line in notes:
        print(f"- Ray overhead, {line}")
    warm1 = next((wall for label, wall, _ in rows if label == "Ray, 1 worker(s), warm"), None)
    if warm1 is not None:
        print(f"- Ray overhead per item (1 warm worker minus one warm process): "
              f"{(warm1 - t_seq) / n * 1e3:.0f} ms")
    if tmp is not None:
        tmp.cleanup()
    return 0


def main(argv: list[str] | None = None) -> Any:
    """Run as a script."""
    p = argparse.ArgumentParser(description=__doc__)
    add_arguments(p)
    return run(p.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
