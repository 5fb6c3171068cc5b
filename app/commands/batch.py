"""``lenslesscam batch run|status|cancel``: reconstruct a manifest of items on Ray.

``batch run MANIFEST --out DIR`` runs every item of the manifest (CSV or TOML, see
:mod:`app.batch.manifest`) as one Ray task: embedded Ray on this machine by default, or an
existing cluster with ``--address``. Rerunning the same command skips finished items.
``batch status DIR`` reads a batch folder (also while a driver elsewhere runs it);
``batch cancel DIR`` asks its driver to stop. Ray is imported only by ``batch run``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from app.commands._options import (
    POSITIVE,
    POSITIVE_INT,
    check_output_folders,
    integer,
    refuse_run_folder_outputs,
)

#: the most Ray retries of a lost worker ``--max-retries`` takes (Ray keeps the count in a
#: 32-bit integer: 2**31 was an OverflowError after Ray had started)
MAX_RETRIES = 1000


def register(sub: Any) -> None:
    """Add ``batch`` and its actions."""
    p = sub.add_parser("batch", help="reconstruct a manifest of measurements on Ray (local or "
                                     "a cluster)")
    acts = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    r = acts.add_parser("run", help="run (or continue) a batch",
                        description="Run every item of MANIFEST (CSV with header "
                                    "measurement,psf,method[,...] or TOML) as a Ray task.")
    r.add_argument("manifest", help="manifest file (.csv or .toml)")
    r.add_argument("--out", required=True, help="batch folder (results, records, summary)")
    r.add_argument("--address", help="join a Ray cluster: 'auto' or HOST:PORT (default: start "
                                     "Ray inside this command on this machine)")
    r.add_argument("--connect-timeout", type=POSITIVE, default=10.0, metavar="SECONDS",
                   help="with --address HOST:PORT: give up when the address does not accept a "
                        "connection within this time, or then does not answer as a Ray "
                        "cluster's GCS (gRPC) within it again (default 10)")
    r.add_argument("--num-cpus", type=POSITIVE_INT,
                   help="CPUs of the embedded Ray (default: all cores)")
    r.add_argument("--cpus-per-item", type=POSITIVE_INT, default=1,
                   help="CPUs (= torch threads) of a fista/auto item (default 1)")
    r.add_argument("--udn-cpus", type=POSITIVE_INT, default=1,
                   help="CPUs (= torch threads) of a udn item when the cluster has no GPU "
                        "(default 1; with GPUs a udn item takes one GPU)")
    r.add_argument("--max-retries", type=integer(0, MAX_RETRIES), default=2,
                   help="Ray retries of an item whose worker died (killed, out of memory, a "
                        f"machine lost; default 2, at most {MAX_RETRIES}); an item that "
                        "raises an error is recorded as failed at once")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    r.add_argument("--json", action="store_true", help="print the outcome as JSON")
    r.set_defaults(func=run_batch_cmd)
    s = acts.add_parser("status", help="state of a batch folder (running here or elsewhere)")
    s.add_argument("dir", help="batch folder")
    s.add_argument("--json", action="store_true", help="print JSON")
    s.set_defaults(func=status_cmd, no_torch=True)
    c = acts.add_parser("cancel", help="stop a running batch cleanly (results written stay)")
    c.add_argument("dir", help="batch folder")
    c.set_defaults(func=cancel_cmd, no_torch=True)


def run_batch_cmd(args: argparse.Namespace) -> int:
    """``batch run``: exit 0 when every item is done, 1 when some failed, 130 if cancelled."""
    from app.batch.driver import BatchOptions, run_batch

    opts = BatchOptions(address=args.address, connect_timeout_s=args.connect_timeout,
                        num_cpus=args.num_cpus,
                        cpus_per_item=args.cpus_per_item, udn_cpus=args.udn_cpus,
                        max_retries=args.max_retries, progress=False if args.quiet else None)
    state = Path(args.out) / "state.json"
    try:  # a batch folder inside a UDN run folder: refused, as every writer refuses it
        refuse_run_folder_outputs([state], "--out")
    except ValueError as exc:
        raise ValueError(str(exc).replace(str(state), str(args.out), 1)) from None
    check_output_folders([state])  # a folder it cannot write: one line
    rep = run_batch(args.manifest, args.out, opts)
    c = rep.counts
    if args.json:
        print(json.dumps({"batch": str(rep.root), "status": rep.status, "counts": c,
                          "ran": rep.ran, "wall_s": round(rep.wall_s, 3),
                          "summary": [str(p) for p in rep.summary]}))
    else:
        print(f"batch {rep.status}: {c.get('done', 0)} done, {c.get('skipped', 0)} already "
              f"done (skipped), {c.get('failed', 0)} failed, {c.get('cancelled', 0)} cancelled "
              f"in {rep.wall_s:.1f} s; summary: {rep.summary[1] if rep.summary else '-'}")
    for item_id, rec in rep.records.items():
        if rep.counts and rec.get("status") == "failed":
            print(f"  failed {item_id}: {rec.get('error')}", file=sys.stderr)
    return {"finished": 0, "failed": 1, "cancelled": 130}.get(rep.status, 1)


def status_cmd(args: argparse.Namespace) -> int:
    """``batch status``."""
    from app.batch.state import batch_status, format_status

    st = batch_status(args.dir)
    print(json.dumps(st) if args.json else format_status(st))
    return 0


def cancel_cmd(args: argparse.Namespace) -> int:
    """``batch cancel``."""
    from app.batch.state import request_cancel

    print(request_cancel(args.dir))
    return 0
