"""One batch item: the work of one Ray task (also callable in this process, for benchmarks).

:func:`run_item` runs an item exactly as the command line would: ``lenslesscam recon METHOD``
with the item's options (the command's own parser and function: same loader, solver, metadata
and atomic writer), and ``udn`` items as jobs (:func:`recon.udn.jobs.run_job`, or
:func:`~recon.udn.jobs.resume_job` when the item's run folder already holds a run, so a retry
after a lost worker continues from the last checkpoint). It then writes the item's record
(``items/ID.json``, atomically) with the item's hash, and returns that record.

An exception the item raises (an input error, a shape mismatch, a numerical failure, a run
folder another process holds) is recorded as ``failed`` at once, in one line: running the same
item again gives the same error, so it is not retried. Ray retries only a task whose worker
died (killed, out of memory, a machine lost; ``max_retries``).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import platform
import time
import tomllib
from pathlib import Path
from typing import Any

from app.batch.manifest import Item, option_names, parse_recon_args
from app.batch.state import BatchPaths, now_utc

__all__ = ["build_udn_spec", "run_item"]

ITEM_FORMAT = "lenslesscam.batch_item"


def build_udn_spec(item: Item, threads: int | None = None) -> tuple[dict[str, Any], Path]:
    """The job spec of a ``udn`` item and the folder its relative paths are relative to.

    Without a ``spec`` column the spec is what ``lenslesscam recon udn`` builds from the same
    options; with one, the spec file with the item's columns replacing its keys. ``threads``
    sets ``device.threads`` (the task's CPUs). The spec is validated (SpecError, a ValueError).
    """
    from recon.udn.spec import normalise_spec

    if item.spec is None:
        from app.commands.recon_udn import build_spec

        args = parse_recon_args("udn", [*item.argv, "--out", "run"])
        spec = build_spec(args)
        base = Path.cwd()
    else:
        p = Path(item.spec)
        if not p.is_file():
            raise FileNotFoundError(f"job spec not found: {p}")
        try:
            spec = tomllib.loads(p.read_text(encoding="utf-8"))
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"{p}: not valid TOML: {exc}") from None
        for sec, key, value in item.spec_data:
            table = spec.setdefault(sec, {})
            if not isinstance(table, dict):
                raise ValueError(f"{p}: [{sec}] must be a table")
            table[key] = value
        base = p.parent
    if threads is not None:
        spec.setdefault("device", {})["threads"] = int(threads)
    normalise_spec(spec, base, source=item.spec or "udn item")
    return spec, base



def _attempt(marker: Path) -> int:
    """1 + the attempt recorded by a previous (lost) worker's running marker."""
    try:
        return int(json.loads(marker.read_text(encoding="utf-8")).get("attempt", 0)) + 1
    except (OSError, ValueError, AttributeError):
        return 1


def _metrics(item: Item, output: Path) -> dict[str, Any]:
    """PSNR / SSIM / MS-SSIM of a fista/auto/... result against the item's truth.

    After a least-squares gain fit, the truth prepared as ``lenslesscam metrics --gain-fit``
    prepares it (:func:`recon.truth.truth_for_result`: from the result's metadata, so a
    ``recon auto`` result's plan (downsampling, region, merged shutter bins, planes) too);
    a result without that metadata through the problem loader (:func:`recon.problem.load_truth`).
    """
    from recon.io import read_reconstruction
    from recon.metrics import metrics_report
    from recon.truth import truth_for_result

    est, meta = read_reconstruction(output)
    got = truth_for_result(item.truth, est, meta)
    if got is None:
        from app.commands._inputs import problem_spec
        from recon.problem import load_truth

        args = parse_recon_args(item.method, [*item.argv, "--out", str(output)])
        # the ProblemSpec the command builds from these options, with the item's truth
        ref = load_truth(problem_spec(args, truth=item.truth), est.shape)
    else:
        ref, est, _ = got
    return _numbers(metrics_report(ref, est, gain_fit=True))


def _numbers(report: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in report.items() if isinstance(v, (int, float))}


def _run_recon(item: Item, out: Path) -> dict[str, Any]:
    """``lenslesscam recon METHOD ... --out OUT`` in this process; what it reports."""
    from recon.io import read_reconstruction

    # the batch owns its results folder: a rerun (changed input, lost worker) replaces them
    overwrite = ["--overwrite"] if "overwrite" in option_names(item.method) else []
    args = parse_recon_args(item.method, [*item.argv, "--out", str(out), *overwrite])
    so, se = io.StringIO(), io.StringIO()  # the command's JSON line and its (silent) bar
    with contextlib.redirect_stdout(so), contextlib.redirect_stderr(se):
        rc = int(args.func(args) or 0)
    if rc != 0:
        raise RuntimeError(f"lenslesscam recon {item.method} exited with {rc}: "
                           f"{se.getvalue().strip()[-300:]}")
    lines = [ln for ln in so.getvalue().splitlines() if ln.startswith("{")]
    summary = json.loads(lines[-1]) if lines else {}
    _, meta = read_reconstruction(out)
    final = meta.get("final") or {}
    return {
        "iterations": meta.get("iterations", summary.get("iterations")),
        "stop_reason": meta.get("stop_reason", summary.get("stop_reason")),
        "loss": final.get("objective"),
        "residual": final.get("residual", meta.get("residual", summary.get("residual"))),
        "solver_s": meta.get("wall_time_s", summary.get("wall_time_s")),
        # what the loader warned of (its stderr is the command's, kept quiet here)
        "warnings": list((meta.get("preprocessing") or {}).get("warnings") or []),
    }


def _run_udn(item: Item, run_dir: Path, threads: int, cancel_file: Path) -> dict[str, Any]:
    """The item as a UDN job in ``run_dir``: start it, or continue the run already there."""
    from recon.udn.jobs import RECORD_FILE, read_record, resume_job, run_job
    from recon.udn.spec import spec_to_toml

    def cancelled() -> bool:
        return cancel_file.exists()

    if (run_dir / RECORD_FILE).is_file():
        rec = read_record(run_dir)
        final = (rec.get("results") or {}).get("final")
        if rec.get("finish_reason") in ("completed", "stopped_early") and final and (
                run_dir / final).is_file():
            outcome_rec, resumed = rec, False  # finished before its item record was written
        else:
            outcome_rec, resumed = resume_job(run_dir, cancel=cancelled).record, True
    else:
        spec, _ = build_udn_spec(item, threads)
        source = Path(item.spec) if item.spec else run_dir / "job.toml"
        outcome = run_job(source, run_dir, spec_text=spec_to_toml(spec), cancel=cancelled)
        outcome_rec, resumed = outcome.record, False
    prog = outcome_rec.get("progress") or {}
    results = outcome_rec.get("results") or {}
    return {
        "iterations": prog.get("iteration"),
        "stop_reason": outcome_rec.get("finish_reason"),
        "detail": outcome_rec.get("detail"),
        "loss": prog.get("loss"),
        "residual": None,
        "solver_s": (outcome_rec.get("timings") or {}).get("iterations_s"),
        "final": results.get("final"),
        "resumed": resumed or bool(outcome_rec.get("resumes")),
        "resumes": int(outcome_rec.get("resumes", 0)),
        "scores": (results.get("scores") or {}).get("final"),
        "warnings": list(outcome_rec.get("warnings") or []),
    }


def run_item(item: Item, out_dir: str, item_hash: str, hashes: dict[str, str | None],
             cpus: int = 1) -> dict[str, Any]:
    """Run one item into the batch folder ``out_dir``; write and return its record.

    ``cpus`` is the task's CPU count: torch's thread count is set to it explicitly.
    """
    from recon.atomic import atomic_write_json
    from recon.formats import FORMAT_VERSION, file_hash, provenance
    from recon.threads import apply_threads

    paths = BatchPaths(Path(out_dir))
    os.environ["OMP_NUM_THREADS"] = str(cpus)
    threads = apply_threads(cpus)
    marker = paths.running(item.id)
    attempt = _attempt(marker)
    atomic_write_json(marker, {"id": item.id, "pid": os.getpid(), "host": platform.node(),
                               "attempt": attempt, "started_utc": now_utc()})
    rec: dict[str, Any] = {
        "format": ITEM_FORMAT, "format_version": FORMAT_VERSION, "id": item.id,
        "method": item.method, "item_hash": item_hash, "input_hashes": hashes,
        "item": item.to_dict(), "attempt": attempt, "pid": os.getpid(),
        "host": platform.node(), "threads": threads.threads, "started_utc": now_utc(),
    }
    t0 = time.perf_counter()
    try:
        if paths.cancel_file.exists():
            rec.update(status="cancelled", detail="the batch was cancelled before it started")
        elif item.method == "udn":
            run_dir = paths.run_dir(item.id, item_hash)
            info = _run_udn(item, run_dir, cpus, paths.cancel_file)
            final = info.pop("final")
            if info["stop_reason"] == "cancelled":
                rec.update(status="cancelled", detail=info.get("detail"))
            elif final is None:
                rec.update(status="failed", error=f"the job ended without a result "
                           f"({info['stop_reason']}: {info.get('detail')})")
            else:
                rec.update(status="done", output=str((run_dir / final).relative_to(
                    paths.root)), run_dir=str(run_dir.relative_to(paths.root)))
            rec.update(info)
        else:
            out = paths.result(item.id)
            rec.update(_run_recon(item, out), status="done",
                       output=str(out.relative_to(paths.root)))
        if rec["status"] == "done":
            output = paths.root / rec["output"]
            rec["output_hash"] = file_hash(output)
            scores = rec.pop("scores", None)  # a udn job scores its result itself
            if item.truth:
                rec["metrics"] = _numbers(scores) if scores else _metrics(item, output)
    except Exception as exc:  # deterministic (bad input, NumericalError, ...): no retry
        from app.cli import one_line  # the CLI's one-line errors, at most 500 characters

        rec.update(status="failed",
                   error=f"{type(exc).__name__}: {one_line(exc)[:500] or type(exc).__name__}")
    rec["time_s"] = round(time.perf_counter() - t0, 3)
    rec["finished_utc"] = now_utc()
    rec["provenance"] = provenance()
    atomic_write_json(paths.record(item.id), rec)
    marker.unlink(missing_ok=True)
    return rec
