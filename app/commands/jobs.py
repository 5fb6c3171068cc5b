"""``lenslesscam jobs run|resume|status|cancel``: overnight UDN jobs in run folders.

Exit codes of ``run`` and ``resume``: 0 completed or stopped early, 3 cancelled (SIGTERM,
SIGINT, ``jobs cancel``), 2 failed (the run record says why) or refused (the folder is in use
by another process, no usable checkpoint without ``--restart``, ...), with one line on stderr.

``cancel`` exits 0 when it asked the job to stop and also when the run is not running (it
ended, or its process is gone): the line says so and ends "nothing to cancel", as ``batch
cancel`` does; 2 when the folder holds no readable run.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

from app.commands._options import (
    NONNEG_INT,
    POSITIVE,
    POSITIVE_INT,
    add_overwrite_option,
    check_command_outputs,
    check_output_folders,
    refuse_run_folder_outputs,
)

EXIT_CANCELLED = 3


def register(sub: Any) -> None:
    """Add ``jobs`` and its actions."""
    p = sub.add_parser("jobs", help="overnight UDN jobs: run, resume, status, list, cancel, "
                                    "combine")
    act = p.add_subparsers(dest="action", metavar="ACTION", required=True)

    r = act.add_parser("run", help="run a job spec (TOML) into a new run folder")
    r.add_argument("spec", help="job spec file (TOML)")
    r.add_argument("--out", required=True, help="run folder to create")
    r.add_argument("--seed", type=NONNEG_INT, help="override optimizer.seed (runs for an ensemble)")
    _common_run_args(r)
    r.set_defaults(func=cmd_run)

    s = act.add_parser("resume", help="continue a run from its last checkpoint")
    s.add_argument("run_dir", help="run folder")
    s.add_argument("--max-iter", type=POSITIVE_INT, help="raise the iteration limit")
    s.add_argument("--time-limit", type=POSITIVE, help="raise the wall-time limit (seconds)")
    s.add_argument("--restart", action="store_true",
                   help="begin again from iteration 0 (needed when no checkpoint is usable)")
    _common_run_args(s)
    s.set_defaults(func=cmd_resume)

    t = act.add_parser("status", help="show a run's iteration, loss, ETA, device, preview")
    t.add_argument("run_dir", help="run folder")
    t.add_argument("--json", action="store_true", help="print JSON")
    t.set_defaults(func=cmd_status)

    ls = act.add_parser("list", help="list the runs in a folder, one line each (default: the "
                                     "app's jobs folder)")
    ls.add_argument("folder", nargs="?",
                    help="folder holding run folders (FOLDER/RUN or FOLDER/JOB/run, as the app "
                    "writes them); default: the app's jobs folder")
    ls.add_argument("--json", action="store_true", help="print JSON (a list of statuses)")
    ls.set_defaults(func=cmd_list)

    c = act.add_parser("cancel", help="ask a running job to stop cleanly")
    c.add_argument("run_dir", help="run folder")
    c.add_argument("--signal", action="store_true",
                   help="also send SIGTERM to the job's process")
    c.set_defaults(func=cmd_cancel)

    e = act.add_parser("combine", help="average finished runs of one problem with different "
                                       "seeds (an ensemble; failed runs are refused), and "
                                       "FISTA-TV with --with-fista")
    e.add_argument("run_dirs", nargs="+", metavar="RUN_DIR",
                   help="run folders (two or more; one with --with-fista)")
    e.add_argument("--out", required=True,
                   help="reconstruction TIFF to write (never inside a run folder)")
    e.add_argument("--estimate", choices=["auto", "best", "final", "mean"], default="auto",
                   help="which estimate of each run: best (held-out choice), final, mean (the "
                   "run's iterate average, mean.tif) or auto (default: mean with --with-fista "
                   "where every run wrote one, else best)")
    e.add_argument("--with-fista", action="store_true",
                   help="average the runs' average half and half with FISTA-TV (recon fista's "
                   "defaults, automatic tau) of the runs' own inputs; one run is then enough "
                   "(on the real DiffuserCam pairs +0.1 to +0.6 dB over the runs alone, "
                   "docs/udn.md)")
    add_overwrite_option(e)
    e.set_defaults(func=cmd_combine)


def _common_run_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--max-memory", help="refuse runs estimated above this (e.g. 2GB)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _stamp(path: Path) -> tuple[int, int] | None:
    """(modification time in ns, size) of a file, or None when there is none."""
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_mtime_ns, st.st_size


def run_with_progress(start: Any, args: argparse.Namespace, total: int | None,
                      run_dir: str) -> int:
    """Run ``start(progress=..., cancel=...)`` with a progress bar and signal handling."""
    import threading

    from app.cli import CliError
    from app.commands._common import ProgressBar
    from recon.udn.jobs import cancel_on_signals

    bar = ProgressBar(total or 1, "udn", enabled=False if args.quiet else None)

    def progress(s: Any) -> None:
        held = "-" if s.heldout is None else f"{s.heldout:.3g}"
        eta = "-" if s.eta_s is None else f"{s.eta_s:.0f}s"
        bar.update(s.iteration, f"loss {s.loss:.3g} held-out {held} ETA {eta}")

    event = threading.Event()
    where = Path(run_dir) / "run.json"
    before = _stamp(where)
    try:
        with cancel_on_signals(event):
            outcome = start(progress=progress, cancel=event)
    except (ValueError, FileNotFoundError, OSError, ArithmeticError, RuntimeError) as exc:
        bar.close()
        # the record this command wrote, not one of an earlier run in that folder (a spec
        # refused before anything was written pointed at the earlier run's record)
        after = _stamp(where)
        suffix = f" (run record: {where})" if after is not None and after != before else ""
        raise CliError(f"{exc}{suffix}") from exc
    bar.close()
    rec = outcome.record
    summary = {
        "run_dir": str(outcome.run_dir), "finish_reason": outcome.finish_reason,
        "detail": outcome.detail, "iterations": outcome.iterations,
        "results": rec.get("results"),
    }
    print(json.dumps(summary), file=sys.stdout)
    return EXIT_CANCELLED if outcome.finish_reason == "cancelled" else 0


def cmd_run(args: argparse.Namespace) -> int:
    """``jobs run``."""
    from recon.udn.jobs import run_job
    from recon.udn.memory import parse_bytes

    # never a new run inside another run's folder (RUN itself: 'already holds a run', below)
    refuse_run_folder_outputs([args.out], "--out")
    check_output_folders([Path(args.out) / "run.json"])  # a folder it cannot write: one line
    mm = parse_bytes(args.max_memory) if args.max_memory else None
    total = _spec_max_iter(args.spec)
    threads = getattr(args, "global_threads", None)  # lenslesscam --threads N: this session's
    return run_with_progress(
        lambda progress, cancel: run_job(args.spec, args.out, progress=progress, cancel=cancel,
                                         max_memory=mm, seed=args.seed, threads=threads),
        args, total, args.out)


def cmd_resume(args: argparse.Namespace) -> int:
    """``jobs resume``."""
    from recon.udn.jobs import job_status, resume_job
    from recon.udn.memory import parse_bytes

    mm = parse_bytes(args.max_memory) if args.max_memory else None
    total = args.max_iter or job_status(args.run_dir).max_iter
    check_output_folders([Path(args.run_dir) / "run.lock"])  # a read-only run: one line
    threads = getattr(args, "global_threads", None)  # lenslesscam --threads N: this session's

    def notice(line: str) -> None:
        print(f"lenslesscam jobs resume: note: {line}", file=sys.stderr)

    return run_with_progress(
        lambda progress, cancel: resume_job(args.run_dir, max_iter=args.max_iter,
                                            time_limit_s=args.time_limit, progress=progress,
                                            cancel=cancel, max_memory=mm, restart=args.restart,
                                            notice=notice, threads=threads),
        args, total, args.run_dir)


def _spec_max_iter(path: str) -> int | None:
    import tomllib

    try:
        with open(path, "rb") as fh:
            v = tomllib.load(fh).get("stopping", {}).get("max_iter")
    except (OSError, ValueError):
        return None
    return v if isinstance(v, int) else None


def cmd_status(args: argparse.Namespace) -> int:
    """``jobs status``."""
    from recon.udn.jobs import format_status, job_status

    st = job_status(args.run_dir)
    if args.json:
        print(json.dumps(st.to_dict(), default=str))
    else:
        print(format_status(st))
    return 0


def _app_jobs_dir() -> Path:
    """The app's jobs folder: the one its settings name, else its default (read only)."""
    from app.gui.settings import SETTINGS_FORMAT, default_jobs_dir, settings_path

    try:
        raw = json.loads(settings_path().read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        raw = None
    chosen = raw.get("jobs_dir") if isinstance(raw, dict) and raw.get(
        "format") == SETTINGS_FORMAT else None
    return Path(chosen) if isinstance(chosen, str) and chosen else default_jobs_dir()


def cmd_list(args: argparse.Namespace) -> int:
    """``jobs list``: the runs under a folder, by folder name; an unreadable one is named."""
    from recon.udn.jobs import RECORD_FILE, format_hms, job_status

    root = Path(args.folder) if args.folder else _app_jobs_dir()
    if not root.is_dir():
        if args.folder and root.exists():
            raise ValueError(f"{root} is a file, not a folder: jobs list takes the folder that "
                             "holds run folders (or a run folder)")
        if args.folder:
            raise ValueError(f"{root}: no such folder")
        print("[]" if args.json else f"no runs: the app's jobs folder {root} does not exist "
              "yet (give a folder to list another)")
        return 0
    # a run folder given itself is listed as itself (it listed nothing: "no runs")
    runs = sorted({p.parent for pattern in (RECORD_FILE, f"*/{RECORD_FILE}",
                                            f"*/*/{RECORD_FILE}") for p in root.glob(pattern)})
    rows: list[dict[str, Any]] = []
    for rd in runs:
        try:
            rows.append(job_status(rd).to_dict())
        except Exception as exc:  # one damaged run (any field of it) does not hide the others
            text = str(exc) if isinstance(exc, OSError | ValueError) else (
                f"{rd / RECORD_FILE}: {type(exc).__name__}: {exc}")
            rows.append({"run_dir": str(rd), "error": text})
    if args.json:
        print(json.dumps(rows, default=str))
        return 0
    if not rows:
        print(f"no runs in {root}")
        return 0
    print(f"{len(rows)} run(s) in {root}:")
    for r in rows:
        where = os.path.relpath(r["run_dir"], root)
        where = Path(r["run_dir"]).name if where == "." else where  # the run folder given
        if "error" in r:
            print(f"  {where}  unreadable: {r['error']}")
            continue
        state = str(r["state"]) if r["state"] != "finished" else str(r["finish_reason"])
        of = f"/{r['max_iter']}" if r.get("max_iter") else ""
        best = ("" if r.get("best_iteration") is None else
                f"  best at {r['best_iteration']}")
        print(f"  {where}  {state}  iteration {r['iteration']}{of}{best}  "
              f"{format_hms(r.get('elapsed_s'))}" + (f"  ({r['name']})" if r.get("name") else ""))
    return 0


def cmd_cancel(args: argparse.Namespace) -> int:
    """``jobs cancel``."""
    from recon.udn.jobs import read_record, request_cancel

    read_record(args.run_dir)  # no run there, or an unreadable record: an error (exit 2)
    try:
        print(request_cancel(args.run_dir, send_signal=args.signal))
    except ValueError as exc:
        # the run is not running: what the user wanted is already true, as for batch cancel
        print(f"{exc}; nothing to cancel")
    return 0


def cmd_combine(args: argparse.Namespace) -> int:
    """``jobs combine``."""
    from recon.io import reconstruction_paths
    from recon.udn.ensemble import combine_runs
    from recon.udn.jobs import refuse_outputs_in_run_folders

    outputs = reconstruction_paths(args.out, "image")  # TIFF and its PNG
    refuse_outputs_in_run_folders(outputs, "--out")  # a run's folder, --overwrite or not
    check_command_outputs(args, outputs)
    res = combine_runs(args.run_dirs, args.out, estimate=args.estimate,
                       with_fista=args.with_fista)
    for m in res.members:
        what = (f"mean of {m.get('mean_count')} estimates, the last at iteration "
                f"{m.get('mean_last_iteration') or '?'} of {m['iteration']}"
                if res.estimate == "mean" else f"{res.estimate} at iteration {m['iteration']}")
        print(f"  seed {m['seed']:>4}  {what}  ({m['finish_reason']})  {m['run_dir']}")
    if res.note is not None:
        print(f"  note: {res.note}")
    if res.fista is not None:
        f = res.fista
        print(f"  FISTA-TV  tau {f['tau']:.3g} ({f['tau_rule']}), {f['iterations']} iterations, "
              f"{f['wall_time_s']:.1f} s; weight {f['weight']:g}")
    n = len(res.members)
    line = (f"ensemble of {n} run{'s' if n > 1 else ''}"
            + (" and FISTA-TV" if res.fista is not None else "") + f" -> {res.paths[0]}")
    if res.scores is not None:
        line += f"  (PSNR {res.scores['psnr']:.2f} dB, SSIM {res.scores['ssim']:.3f} vs truth)"
    print(line)
    return 0
