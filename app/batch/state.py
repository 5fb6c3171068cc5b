"""The batch folder: its layout, the driver's lock, the state file, cancel and status.

Layout of ``DIR`` (``lenslesscam batch run MANIFEST --out DIR``)::

    state.json          the driver's state: status, counts, per item status / attempts / hash
                        (rewritten atomically about once a second while the batch runs)
    run.lock            OS lock (fcntl.flock) held by the driver: one driver per folder
    results/ID.tif      the result of a fista / auto / ... item (+ previews), as `recon` writes it
    runs/ID-HASH8/      the run folder of a udn item (a job: checkpoints, run.json, final.tif)
    items/ID.json       the item's record: status, item hash, input hashes, time, loss, metrics
    items/ID.running    present while a worker runs the item (pid, host, attempt)
    summary.csv, summary.md   per item: method, status, time, final loss/residual, metrics
    CANCEL              present while a cancellation is requested (``batch cancel``)
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import os
import platform
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["STATE_FORMAT", "BatchBusy", "BatchLock", "BatchPaths", "batch_status",
           "check_not_newer", "format_status", "read_state", "request_cancel"]

STATE_FORMAT = "lenslesscam.batch_state"


class BatchBusy(ValueError):
    """Another driver holds the batch folder."""


def now_utc() -> str:
    """ISO time stamp (UTC, seconds)."""
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


@dataclass(frozen=True)
class BatchPaths:
    """Where each file of a batch folder lives."""

    root: Path

    @property
    def state(self) -> Path:
        """state.json."""
        return self.root / "state.json"

    @property
    def cancel_file(self) -> Path:
        """CANCEL."""
        return self.root / "CANCEL"

    @property
    def items_dir(self) -> Path:
        """items/."""
        return self.root / "items"

    def record(self, item_id: str) -> Path:
        """items/ID.json."""
        return self.items_dir / f"{item_id}.json"

    def running(self, item_id: str) -> Path:
        """items/ID.running."""
        return self.items_dir / f"{item_id}.running"

    def result(self, item_id: str) -> Path:
        """results/ID.tif."""
        return self.root / "results" / f"{item_id}.tif"

    def run_dir(self, item_id: str, item_hash: str) -> Path:
        """runs/ID-HASH8/ (a new folder when the item's inputs change)."""
        return self.root / "runs" / f"{item_id}-{item_hash[:8]}"

    def folders(self) -> tuple[Path, ...]:
        """The folders :meth:`make` creates inside the batch folder."""
        return (self.items_dir, self.root / "results", self.root / "runs")

    def make(self) -> None:
        """Create the folders."""
        for d in (self.root, *self.folders()):
            d.mkdir(parents=True, exist_ok=True)


class BatchLock:
    """The driver's exclusive lock on a batch folder (the UDN run folder's :class:`RunLock`)."""

    def __init__(self, root: Path) -> None:
        from recon.udn.rundir import RunLock

        self.root = root
        self._lock = RunLock(root)

    def acquire(self) -> BatchLock:
        """Take the lock or raise :class:`BatchBusy`."""
        from recon.udn.rundir import RunFolderBusy

        try:
            self._lock.acquire()
        except RunFolderBusy:
            who = ""
            st = read_state(self.root, missing_ok=True)
            if st:
                who = f" (driver pid {st.get('pid')} on {st.get('host')})"
            raise BatchBusy(f"batch folder {self.root} is in use by another batch driver{who}: "
                            f"watch it with 'lenslesscam batch status {self.root}' or stop it "
                            f"with 'lenslesscam batch cancel {self.root}'") from None
        return self

    def release(self) -> None:
        """Drop the lock."""
        self._lock.release()

    def __enter__(self) -> BatchLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


def read_state(root: str | Path, missing_ok: bool = False) -> dict[str, Any]:
    """The batch's state.json (checked for format); {} if absent and ``missing_ok``."""
    p = BatchPaths(Path(root)).state
    if not p.is_file():
        if missing_ok:
            return {}
        raise FileNotFoundError(f"{root} is not a batch folder (no state.json)")
    try:
        st = json.loads(p.read_text(encoding="utf-8"))
    except ValueError as exc:
        raise ValueError(f"{p}: not valid JSON: {exc}") from None
    if not isinstance(st, dict) or st.get("format") != STATE_FORMAT:
        raise ValueError(f"{p} is not a batch state file (format {STATE_FORMAT})")
    check_not_newer(st, p)
    return st


def check_not_newer(doc: dict[str, Any], path: Path) -> None:
    """Refuse (:class:`~recon.formats.NewerFormat`, one line) a file a newer release wrote.

    It is neither read as if it were ours nor overwritten: the release that wrote it reads it.
    """
    from recon.formats import FORMAT_VERSION, NewerFormat

    v = doc.get("format_version", 0)
    if isinstance(v, bool) or not isinstance(v, int):
        raise ValueError(f"{path}: format_version {v!r} is not a version number")
    if v > FORMAT_VERSION:
        raise NewerFormat(f"{path}: format_version {v} was written by a newer lenslesscam "
                          f"(this release reads {FORMAT_VERSION}): run the batch with that "
                          "release; nothing was changed")


def write_state(root: Path, state: dict[str, Any]) -> None:
    """Write state.json atomically."""
    from recon.atomic import atomic_write_json

    atomic_write_json(BatchPaths(root).state, state)


def request_cancel(root: str | Path) -> str:
    """Ask the driver of the batch in ``root`` to stop; what was done, in one line.

    A batch that is not running (finished, cancelled, or its driver on this host is gone)
    is not an error: the line says so and ends "nothing to cancel" (``jobs cancel`` says the
    same of a UDN run).
    """
    from recon.atomic import atomic_write_json

    root = Path(root)
    st = read_state(root)
    status = st.get("status")
    if status in ("running", "starting") and _alive(st.get("pid"), st.get("host")) is False:
        return (f"{root}: the batch is not running (its driver, pid {st.get('pid')}, is gone: "
                "it was interrupted; rerun the same 'batch run' command to continue it); "
                "nothing to cancel")
    if status not in ("running", "starting"):
        return f"{root}: the batch is not running (status {status}); nothing to cancel"
    atomic_write_json(BatchPaths(root).cancel_file, {"requested_utc": now_utc(),
                                                     "by_pid": os.getpid(),
                                                     "host": platform.node()})
    return (f"{root}: cancellation requested; the driver stops within a few seconds, results "
            "already written stay (rerun the same command to continue)")


def _alive(pid: Any, host: Any) -> bool | None:
    """Whether the process lives (None when it is on another host: unknown)."""
    from recon.udn.jobs import pid_alive

    if not isinstance(pid, int) or host not in (None, platform.node()):
        return None
    return pid_alive(pid)


def batch_status(root: str | Path) -> dict[str, Any]:
    """The state of a batch (running here or elsewhere): counts, running items, ETA."""
    root = Path(root)
    paths = BatchPaths(root)
    st = read_state(root)
    status = st.get("status")
    if status in ("running", "starting") and _alive(st.get("pid"), st.get("host")) is False:
        status = "interrupted"
    running = []
    if paths.items_dir.is_dir():
        for p in sorted(paths.items_dir.glob("*.running")):
            with contextlib.suppress(OSError, ValueError):
                running.append(json.loads(p.read_text(encoding="utf-8")))
    items = st.get("items", {})
    counts: dict[str, int] = {}
    for it in items.values():
        counts[it["status"]] = counts.get(it["status"], 0) + 1
    return {"batch": str(root), "status": status, "manifest": st.get("manifest"),
            "started_utc": st.get("started_utc"), "updated_utc": st.get("updated_utc"),
            "total": len(items), "counts": counts,
            "running": [r.get("id") for r in running] if status == "running" else [],
            "eta_s": st.get("eta_s") if status == "running" else None,
            "address": st.get("address"), "pid": st.get("pid"), "host": st.get("host")}


def format_status(s: dict[str, Any]) -> str:
    """Human-readable status (``lenslesscam batch status DIR``)."""
    c = s["counts"]
    eta = s.get("eta_s")
    eta_txt = "-" if eta is None else f"{int(eta) // 60}:{int(eta) % 60:02d}"
    state = s["status"]
    if state == "interrupted":
        state += (f" (driver pid {s.get('pid')} is gone; rerun the same 'lenslesscam batch "
                  "run' to continue)")
    lines = [
        f"batch:    {s['batch']}   (manifest {s.get('manifest')})",
        f"state:    {state}",
        f"items:    {s['total']}: {c.get('done', 0)} done, {c.get('skipped', 0)} skipped "
        f"(already done), {c.get('running', 0) + c.get('pending', 0)} to run, "
        f"{c.get('failed', 0)} failed, {c.get('cancelled', 0)} cancelled",
        f"running:  {', '.join(s['running']) or '-'}",
        f"ETA:      {eta_txt}",
        f"updated:  {s.get('updated_utc')}",
    ]
    return "\n".join(lines)
