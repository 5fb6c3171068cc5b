"""The batch driver: items to Ray tasks, progress, retries, cancel, state and summary.

:func:`run_batch` reads the manifest, takes the batch folder's lock, skips the items whose
record says ``done`` with the same item hash and an intact result, starts Ray (embedded:
``ray.init(num_cpus=...)`` in this process, no dashboard, no usage statistics, logs kept out of
the terminal) or joins a cluster (``address``), submits one task per remaining item, and
collects them as they finish: a live progress bar, ``state.json`` rewritten about once a second
(for ``lenslesscam batch status``), a ``CANCEL`` file polled (``lenslesscam batch cancel``), and
at the end the summary tables. Ray's own retries handle lost workers (``max_retries``); an
exception an item raises is recorded by its task as failed at once (it would only happen again),
and the batch goes on. Ray's reports of failed tasks and dead workers are kept off the terminal
(the batch says what happened, one line per item), and SIGTERM / SIGHUP cancel the batch as
Ctrl-C does (``ray.init`` installs a handler that aborted the driver). Whether Ray is installed
and the cluster's address answers is checked before the batch folder is made.

Joining a cluster at ``HOST:PORT`` first opens a plain TCP connection to that address, bounded
by ``connect_timeout_s`` (``--connect-timeout``): ``ray.init`` itself retries an address where
nothing listens for many minutes, so a wrong host or port, or a head that is not running, is
reported as a one-line error within seconds instead of a silent hang. On that connection it
then opens HTTP/2 as a gRPC client does (Ray's GCS, and the Ray Client server of a ``ray://``
address, are gRPC servers) and waits, as long again at most, for the server's first frame: a
service that is not one (an HTTP/1 server, an SSH or database port, a socket that never
answers) is a one-line error too, where ``ray.init`` retried it for minutes. With
``RAY_USE_TLS`` the GCS speaks TLS first, and that probe is left out.

Ray is imported here only, inside the functions (``import ray`` takes seconds).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import platform
import socket
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from app.batch.manifest import Item, input_hashes, item_hash, read_manifest
from app.batch.state import (
    STATE_FORMAT,
    BatchLock,
    BatchPaths,
    check_not_newer,
    now_utc,
    read_state,
    write_state,
)
from app.batch.summary import write_summary
from app.batch.task import ITEM_FORMAT, run_item
from app.commands._common import TerminateAsInterrupt

__all__ = ["BatchOptions", "BatchReport", "run_batch", "start_ray"]

#: Seconds the driver waits for running UDN items to stop at their next iteration after a
#: cancel (they write a final checkpoint) before it ends them.
CANCEL_GRACE_S = 60.0
#: Object store of the embedded Ray (tasks exchange only small records).
EMBEDDED_OBJECT_STORE = 128 * 1024 * 1024
#: Seconds ``batch run --address HOST:PORT`` waits for the cluster's address to accept a TCP
#: connection before it gives up (``--connect-timeout``).
CONNECT_TIMEOUT_S = 10.0
#: The port of ``ray start --head`` when none is given (named in the error messages).
RAY_DEFAULT_PORT = 6379


@dataclass(frozen=True)
class BatchOptions:
    """How to run a batch (the options of ``lenslesscam batch run``)."""

    address: str | None = None  # None: embedded Ray; "auto" or HOST:PORT: join a cluster
    connect_timeout_s: float = CONNECT_TIMEOUT_S  # reaching a HOST:PORT address
    num_cpus: int | None = None  # embedded Ray's CPUs (None: all cores)
    cpus_per_item: int = 1  # CPUs (= torch threads) of a fista / auto / ... task
    udn_cpus: int = 1  # CPUs (= torch threads) of a udn task on a cluster without GPUs
    max_retries: int = 2  # Ray retries of a task whose worker died (not of an exception)
    progress: bool | None = None  # None: a progress bar when stderr is a terminal
    poll_s: float = 0.5


@dataclass
class BatchReport:
    """How a batch ended."""

    root: Path
    status: str  # finished | failed | cancelled
    records: dict[str, dict[str, Any]]
    counts: dict[str, int]
    wall_s: float
    ran: int  # items run by this driver (not skipped)
    summary: list[Path] = field(default_factory=list)


def split_address(address: str) -> tuple[str, int] | None:
    """``(host, port)`` of a ``[ray://]HOST:PORT`` address; None where Ray alone decides.

    None for ``auto``, ``local`` and ``scheme://`` addresses other than ``ray://``. Raises
    ValueError (a one-line message) for anything else.
    """
    target = address.strip()
    if target.lower() in ("auto", "local"):
        return None
    scheme, sep, rest = target.partition("://")
    if sep:
        if scheme.lower() != "ray":
            return None  # another kind of address Ray knows: left to it, not probed
        target = rest
    host, sep, port_s = target.rpartition(":")
    host = host.strip("[]")  # [::1]:6379
    if not sep or not host or not port_s.isdigit() or not 0 < int(port_s) < 65536:
        raise ValueError(f"--address must be 'auto' or HOST:PORT (for example "
                         f"head.lab:{RAY_DEFAULT_PORT}), got {address!r}")
    return host, int(port_s)


#: The HTTP/2 client connection preface and an empty SETTINGS frame (RFC 9113, 3.4 and 6.5):
#: what a gRPC client sends first. A gRPC server answers with its own SETTINGS frame.
_H2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])


def _tls() -> bool:
    """Ray's own test of ``RAY_USE_TLS`` (its gRPC then starts with a TLS handshake)."""
    return os.environ.get("RAY_USE_TLS", "0").lower() in ("1", "true")


def _not_grpc(sock: socket.socket, timeout_s: float) -> str | None:
    """None when the peer answers an HTTP/2 preface as a gRPC server (Ray's GCS) does.

    That is with a SETTINGS frame; else what it did instead, in words. At most ``timeout_s``
    seconds.
    """
    deadline = time.monotonic() + timeout_s
    head = b""
    try:
        sock.settimeout(timeout_s)
        sock.sendall(_H2_PREFACE)
        while len(head) < 9:
            sock.settimeout(max(deadline - time.monotonic(), 1e-3))
            chunk = sock.recv(9 - len(head))
            if not chunk:
                return ("closed the connection without answering a gRPC (HTTP/2) client"
                        if not head else f"answered {head!r} and closed the connection")
            head += chunk
    except TimeoutError:
        return (f"did not answer a gRPC (HTTP/2) client within {timeout_s:g} s "
                "(--connect-timeout waits longer)" if not head else
                f"answered only {head!r} within {timeout_s:g} s")
    except OSError as exc:
        return f"then failed ({exc.strerror or exc})"
    length, kind, stream = int.from_bytes(head[:3], "big"), head[3], head[5:9]
    if kind == 4 and stream == bytes(4) and length % 6 == 0:  # SETTINGS on stream 0
        return None
    if head.startswith(b"HTTP/"):
        return "answered as an HTTP/1 server"
    text = head.decode("ascii", "replace")
    if text.isprintable():
        return f"answered {text!r}..., not HTTP/2 (gRPC)"
    return "answered with something that is not an HTTP/2 (gRPC) frame"


def _auto_address(address: str) -> tuple[str, int] | None:
    """The cluster ``auto`` finds on this machine, as Ray reads it, or a one-line CliError.

    None where Ray's (private) reading is not available: Ray then decides when it starts.
    """
    try:
        from ray._private.services import canonicalize_bootstrap_address
    except Exception:
        return None
    try:
        found = canonicalize_bootstrap_address("auto")
    except ConnectionError as exc:
        from app.cli import CliError

        why = _first_line(exc).split(". ")[0].rstrip(".")  # not its advice about flags
        raise CliError(f"cannot join the Ray cluster at {address}: {why}; start one on this "
                       "machine with 'ray start --head', or give HOST:PORT") from None
    except Exception:
        return None
    try:
        return split_address(found) if found else None
    except ValueError:
        return None


def check_reachable(address: str, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
    """Raise a one-line :class:`~app.cli.CliError` unless ``address`` is a gRPC server.

    First it must accept a TCP connection within ``timeout_s``; then (unless ``RAY_USE_TLS``)
    answer an HTTP/2 preface with a SETTINGS frame within ``timeout_s`` again, as Ray's GCS
    does: another service there (``ray.init`` retried it for minutes) is named at once, or at
    the timeout when it never answers. ``auto`` is left to Ray (it finds a local cluster or
    fails at once). The probe goes where Ray would connect: Ray's own reading of the address
    (a loopback host becomes this machine's IP) when it can give one.
    """
    hp = split_address(address)
    if hp is None and address.strip().lower() == "auto":
        hp = _auto_address(address)  # a half-made folder, "interrupted", was left otherwise
    if hp is None:
        return
    host, port = hp
    if not address.strip().startswith("ray://"):
        with contextlib.suppress(Exception):  # Ray's private helper; the address as given else
            from ray._private.services import canonicalize_bootstrap_address

            canon = canonicalize_bootstrap_address(address.strip())
            if canon:
                host, port = split_address(canon) or (host, port)
    try:
        with socket.create_connection((host, port), timeout=timeout_s) as sock:
            not_ray = None if _tls() else _not_grpc(sock, timeout_s)
    except OSError as exc:
        if isinstance(exc, socket.gaierror):
            why = f"cannot resolve the host {host!r}"
        elif isinstance(exc, TimeoutError):
            why = f"no answer from {host}:{port} within {timeout_s:g} s"
        elif isinstance(exc, ConnectionRefusedError):
            why = f"nothing listens on {host}:{port} (connection refused)"
        else:
            why = f"{host}:{port}: {exc.strerror or exc}"
        from app.cli import CliError

        raise CliError(f"cannot reach the Ray cluster at {address}: {why}; check that its head "
                       f"runs there ('ray start --head --port={port}', 'ray status') and that "
                       f"the port is right (the GCS port, default {RAY_DEFAULT_PORT}) and open "
                       f"(firewall); --connect-timeout waits longer") from None
    if not_ray is not None:
        from app.cli import CliError

        if address.strip().lower().startswith("ray://"):  # the Ray Client server (gRPC)
            what, port_hint = "a Ray Client server", "its Ray Client port (default 10001)"
        else:
            what, port_hint = "a Ray cluster (GCS)", (
                f"the Ray head's GCS port (default {RAY_DEFAULT_PORT}; 'ray status' on the "
                "head names it)")
        raise CliError(f"{address} does not answer as {what}: {host}:{port} accepts "
                       f"connections but {not_ray}; give {port_hint}") from None


_NEED_RAY = "lenslesscam batch needs Ray: pip install -c constraints.txt 'lenslesscam[batch]'"


def check_ray_installed() -> None:
    """Raise a one-line :class:`~app.cli.CliError` when Ray is not installed (no import)."""
    import importlib.util

    if importlib.util.find_spec("ray") is None:
        from app.cli import CliError

        raise CliError(_NEED_RAY)


def _quiet_ray_reports() -> None:
    """Keep Ray's own reports of failed and retried tasks off the terminal, for the batch.

    Ray prints them (``(raylet) Task run_item failed. There are 2 retries remaining ...``, a
    dead worker's notice, each with a coloured traceback) on the driver's stdout from a
    thread that ``log_to_driver=False`` does not stop, and it has no setting for that. The
    batch says what happened to an item itself, in one line (its record, the summary, the
    final lines); Ray's reports stay in its session logs, but a line about memory (the OOM
    killer's notice of why a worker died) is logged as a warning, which the CLI prints as one
    line. Its "Unhandled error" reports of results never fetched (cancelled tasks) are off too
    (``RAY_IGNORE_UNHANDLED_ERRORS``). :func:`_loud_ray_reports` undoes both.
    """
    if "RAY_IGNORE_UNHANDLED_ERRORS" not in os.environ:
        os.environ["RAY_IGNORE_UNHANDLED_ERRORS"] = "1"
        _RAY_PATCH["env"] = True
    try:
        from ray._private import worker as ray_worker
    except ImportError:  # another Ray layout: its reports stay
        return
    original = getattr(ray_worker, "print_to_stdstream", None)
    if original is None or getattr(original, "lenslesscam_quiet", False):
        return
    log = logging.getLogger("app.batch.ray")

    def quiet(data: dict[str, Any], ignore_prefix: bool) -> None:
        if data.get("pid") == "raylet":  # the error reports, not a worker's own output
            for line in data.get("lines") or ():
                memory = any(w in str(line).lower() for w in ("memory", "oom"))
                log.log(logging.WARNING if memory else logging.DEBUG, "ray: %s",
                        str(line).strip())
            return
        original(data, ignore_prefix=ignore_prefix)

    quiet.lenslesscam_quiet = True  # type: ignore[attr-defined]
    ray_worker.print_to_stdstream = quiet
    _RAY_PATCH["original"] = original


#: what :func:`_quiet_ray_reports` changed, for :func:`_loud_ray_reports`
_RAY_PATCH: dict[str, Any] = {}


def _loud_ray_reports() -> None:
    """Undo :func:`_quiet_ray_reports` (the batch ended; Ray may be used again otherwise)."""
    original = _RAY_PATCH.pop("original", None)
    if original is not None:
        with contextlib.suppress(ImportError):
            from ray._private import worker as ray_worker

            ray_worker.print_to_stdstream = original
    if _RAY_PATCH.pop("env", False):
        os.environ.pop("RAY_IGNORE_UNHANDLED_ERRORS", None)


def start_ray(address: str | None, num_cpus: int | None,
              connect_timeout_s: float = CONNECT_TIMEOUT_S, probe: bool = True) -> bool:
    """Start embedded Ray or join a cluster; True when this call started it (and owns it).

    A ``HOST:PORT`` address that does not accept a TCP connection within ``connect_timeout_s``,
    or then does not answer as a gRPC server (Ray's GCS) within it again, is a one-line
    :class:`~app.cli.CliError` (see :func:`check_reachable`; ``probe=False``: the caller has
    checked).
    """
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # no usage reports, ever
    try:
        import ray
    except ImportError:
        from app.cli import CliError

        raise CliError(_NEED_RAY) from None

    if ray.is_initialized():
        return False
    if address:
        if probe:
            check_reachable(address, connect_timeout_s)
        try:
            given = address.strip()
            ray.init(address=given.lower() if given.lower() in ("auto", "local") else given,
                     log_to_driver=False, logging_level=logging.WARNING)
        except (ConnectionError, TimeoutError) as exc:  # reachable, but not a Ray it can join
            from app.cli import CliError

            hint = ("start one on this machine with 'ray start --head', or give HOST:PORT"
                    if split_address(address) is None else
                    f"is it a Ray head's GCS port (default {RAY_DEFAULT_PORT}), with the same "
                    "Ray version as here?")
            raise CliError(f"cannot join the Ray cluster at {address}: "
                           f"{_first_line(exc).rstrip('.')}; {hint}") from None
    else:  # Ray's notices about its own defaults (auth token, ...) would only clutter the bar
        ray.init(num_cpus=num_cpus or os.cpu_count() or 1, include_dashboard=False,
                 object_store_memory=EMBEDDED_OBJECT_STORE, log_to_driver=False,
                 logging_level=logging.ERROR)
    return True


def finished_record(paths: BatchPaths, item: Item, h: str) -> dict[str, Any] | None:
    """The item's record if it is done with hash ``h`` and its result is intact, else None."""
    from recon.formats import file_hash

    p = paths.record(item.id)
    if not p.is_file():
        return None
    try:
        rec = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(rec, dict) or rec.get("format") != ITEM_FORMAT:
        return None
    from recon.formats import NewerFormat

    try:
        check_not_newer(rec, p)
    except NewerFormat:  # another release's record: never overwritten
        raise
    except ValueError:  # a damaged version ("1", a hand edit): not finished, run again
        return None
    if rec.get("status") != "done" or rec.get("item_hash") != h:
        return None
    out = paths.root / str(rec.get("output", ""))
    if not out.is_file() or file_hash(out) != rec.get("output_hash"):
        return None
    return rec


def _first_line(exc: BaseException) -> str:
    lines = [ln for ln in str(exc).strip().splitlines() if ln.strip()]
    # Ray's messages start with a traceback; the last line is the error itself
    return (lines[-1] if lines else type(exc).__name__)[:500]


class _Driver:
    def __init__(self, manifest: Path, root: Path, items: list[Item], opts: BatchOptions) -> None:
        self.manifest = manifest
        self.paths = BatchPaths(root)
        self.items = items
        self.opts = opts
        self.records: dict[str, dict[str, Any]] = {}
        self.status: dict[str, str] = {}
        self.hashes: dict[str, str] = {}
        self.t0 = time.monotonic()
        self.started = now_utc()
        self._last_state = 0.0
        self.cancelling = False
        self.cancel_deadline: float | None = None
        self.ran = 0

    # -- state -------------------------------------------------------------------------------
    def write_state(self, status: str, eta_s: float | None = None) -> None:
        from recon.formats import FORMAT_VERSION

        items = {}
        for it in self.items:
            rec = self.records.get(it.id, {})
            items[it.id] = {"status": self.status[it.id], "method": it.method,
                            "item_hash": self.hashes.get(it.id), "attempt": rec.get("attempt"),
                            "output": rec.get("output"), "error": rec.get("error")}
        write_state(self.paths.root, {
            "format": STATE_FORMAT, "format_version": FORMAT_VERSION, "status": status,
            "manifest": str(self.manifest), "address": self.opts.address or "embedded",
            "pid": os.getpid(), "host": platform.node(), "started_utc": self.started,
            "updated_utc": now_utc(), "eta_s": None if eta_s is None else round(eta_s, 1),
            "items": items})
        self._last_state = time.monotonic()

    def running_count(self) -> int:
        try:
            return sum(1 for _ in self.paths.items_dir.glob("*.running"))
        except OSError:
            return 0

    # -- the run -----------------------------------------------------------------------------
    def plan(self, known: dict[str, dict[str, str | None]] | None = None
             ) -> list[tuple[Item, str, dict[str, str | None]]]:
        todo = []
        for it in self.items:
            hashes = (known or {}).get(it.id) or input_hashes(it)
            h = item_hash(it, hashes)
            self.hashes[it.id] = h
            rec = finished_record(self.paths, it, h)
            if rec is not None:
                self.records[it.id] = rec
                self.status[it.id] = "skipped"
            else:
                self.status[it.id] = "pending"
                todo.append((it, h, hashes))
        return todo

    def record_failure(self, item: Item, h: str, error: str, status: str = "failed") -> None:
        from recon.atomic import atomic_write_json
        from recon.formats import FORMAT_VERSION

        marker = self.paths.running(item.id)
        attempt = None
        with contextlib.suppress(OSError, ValueError, AttributeError):
            attempt = int(json.loads(marker.read_text(encoding="utf-8"))["attempt"])
        rec = {"format": ITEM_FORMAT, "format_version": FORMAT_VERSION, "id": item.id,
               "method": item.method, "item_hash": h, "item": item.to_dict(),
               "status": status, "error": error, "attempt": attempt,
               "finished_utc": now_utc(), "recorded_by": "driver"}
        atomic_write_json(self.paths.record(item.id), rec)
        marker.unlink(missing_ok=True)
        self.records[item.id] = rec
        self.status[item.id] = status

    def execute(self, todo: list[tuple[Item, str, dict[str, str | None]]]) -> None:
        import ray
        from ray.exceptions import RayError, TaskCancelledError

        gpus = float(ray.cluster_resources().get("GPU", 0.0))  # type: ignore[no-untyped-call]
        remote = ray.remote(run_item)
        pending: dict[Any, tuple[Item, str]] = {}
        for it, h, hashes in todo:
            if it.method == "udn":
                cpus = 1 if gpus > 0 else self.opts.udn_cpus
                opts: dict[str, Any] = {"num_cpus": cpus, "num_gpus": 1 if gpus > 0 else 0}
            else:
                cpus = self.opts.cpus_per_item
                opts = {"num_cpus": cpus}
            # Ray retries a task whose worker died; an exception is the item's own (the task
            # records it as failed) and would only happen again
            ref = remote.options(**opts, max_retries=self.opts.max_retries,
                                 retry_exceptions=False, name=f"batch:{it.id}").remote(
                it, str(self.paths.root), h, hashes, cpus)
            pending[ref] = (it, h)
        show = sys.stderr.isatty() if self.opts.progress is None else self.opts.progress
        from tqdm import tqdm

        bar = tqdm(total=len(todo), desc="batch", unit="item", disable=not show,
                   file=sys.stderr, dynamic_ncols=True)
        failed = 0
        try:
            while pending:
                try:  # Ctrl-C or SIGTERM anywhere in a round cancels the batch cleanly
                    ready, _ = ray.wait(list(pending), num_returns=len(pending),
                                        timeout=self.opts.poll_s)
                    for ref in ready:
                        it, h = pending.pop(ref)
                        try:
                            rec = ray.get(ref)
                        except RayError as exc:
                            kept = finished_record(self.paths, it, h)
                            if kept is not None:  # interrupted after its result was recorded
                                self.records[it.id] = kept
                                self.status[it.id] = "done"
                            elif isinstance(exc, TaskCancelledError):
                                self.record_failure(it, h, "cancelled by 'batch cancel'",
                                                    "cancelled")
                            else:  # retries exhausted, or the worker died
                                self.record_failure(it, h, f"{type(exc).__name__}: "
                                                    f"{_first_line(exc)}")
                        else:
                            self.records[it.id] = rec
                            self.status[it.id] = rec["status"]
                        self.ran += 1
                        failed += self.status[it.id] == "failed"
                        bar.update(1)
                    if not self.cancelling and self.paths.cancel_file.exists():
                        self.cancel(pending)
                    if (self.cancel_deadline is not None
                            and time.monotonic() > self.cancel_deadline):
                        for ref in pending:
                            ray.cancel(ref, force=True)
                        self.cancel_deadline = None
                    running = self.running_count()
                    bar.set_postfix_str(f"running {running}, failed {failed}", refresh=False)
                    if time.monotonic() - self._last_state > 1.0:
                        eta = None
                        if self.ran and pending:
                            eta = (time.monotonic() - self.t0) / self.ran * len(pending)
                        self.write_state("cancelling" if self.cancelling else "running", eta)
                except KeyboardInterrupt:
                    if self.cancelling:
                        raise
                    self.cancel(pending)
        finally:
            bar.close()

    def cancel(self, pending: dict[Any, tuple[Item, str]]) -> None:
        """Stop the batch.

        Pending tasks are dropped, running fista/auto tasks interrupted, udn jobs stop at their
        next iteration (with a checkpoint).
        """
        import ray

        from recon.atomic import atomic_write_json

        self.cancelling = True
        if not self.paths.cancel_file.exists():
            atomic_write_json(self.paths.cancel_file, {"requested_utc": now_utc(),
                                                       "by": "driver (interrupt)"})
        for ref, (it, _) in pending.items():
            if it.method != "udn":
                ray.cancel(ref, force=False)
        self.cancel_deadline = time.monotonic() + CANCEL_GRACE_S
        self.write_state("cancelling")


def _check_batch_folder(root: Path, manifest: Path) -> None:
    """Refuse a folder that holds another manifest's batch, or files that are not a batch's.

    Another manifest's results would be overwritten and orphaned; an input folder would be
    read again by the manifest's glob.
    """
    if root.exists() and not root.is_dir():
        raise ValueError(f"{root} exists and is not a folder: --out names the batch's folder")
    from recon.formats import NewerFormat

    damage = None
    try:
        st = read_state(root, missing_ok=True)
        lost = "missing"
    except NewerFormat:  # not damaged: another release's batch, never overwritten
        raise
    except ValueError as exc:  # damaged: the item records below still say what was done
        st, lost, damage = {}, "damaged", exc
    if st:
        theirs = st.get("manifest")
        if theirs and Path(theirs).resolve() != manifest:
            raise ValueError(f"{root} is the batch of {theirs}; run that manifest there, or "
                             "choose another --out")
    elif root.is_dir() and _batch_without_state(root, manifest):
        print(f"batch: note: {root / 'state.json'} is {lost}; continuing from the item "
              "records in items/ (finished items are skipped as usual)", file=sys.stderr)
    elif damage is not None:
        raise ValueError(f"{damage}; no item record in {root / 'items'} says what was done: "
                         "delete the folder's state.json to start the batch again there, or "
                         "choose another --out")
    elif root.is_dir():
        # what a driver stopped before its first state.json leaves: its lock, empty folders
        from recon.udn.rundir import LOCK_FILE

        made = {d.name for d in BatchPaths(root).folders()}

        def ours(p: Path) -> bool:
            return p.name == LOCK_FILE or (p.name in made and p.is_dir() and not any(p.iterdir()))

        if not all(ours(p) for p in root.iterdir()):
            raise ValueError(f"{root} is not empty and holds no batch: choose a new or empty "
                             "folder for --out")


#: what a batch folder holds (see :mod:`app.batch.state`)
_BATCH_ENTRIES = frozenset({"state.json", "run.lock", "CANCEL", "summary.csv", "summary.md",
                            "items", "results", "runs"})


def _batch_without_state(root: Path, manifest: Path) -> bool:
    """Whether ``root`` is this manifest's batch whose state.json is missing or damaged.

    It holds only a batch's entries, item records among them, and its summary (when there is
    one) names this manifest; a summary naming another is refused.
    """
    from app.batch.summary import read_summary

    items = BatchPaths(root).items_dir
    if any(p.name not in _BATCH_ENTRIES for p in root.iterdir()) or not items.is_dir():
        return False
    records = sorted(items.glob("*.json"))
    if not records:
        return False
    for rec_path in records:  # each record names the manifest row of its item ("m.csv:2")
        source = None
        with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
            source = str(json.loads(rec_path.read_text(encoding="utf-8"))["item"]["source"])
        if source is not None and source.rsplit(":", 1)[0] != manifest.name:
            raise ValueError(f"{root} holds the items of another manifest ({source} in "
                             f"{rec_path.name}); run that manifest there, or choose another "
                             "--out")
    summary = root / "summary.csv"
    theirs = None
    if summary.is_file():
        with contextlib.suppress(ValueError, OSError):
            theirs = read_summary(summary).meta.get("manifest")
    if theirs and Path(str(theirs)).resolve() != manifest:
        raise ValueError(f"{root} is the batch of {theirs}; run that manifest there, or "
                         "choose another --out")
    return True


def run_batch(manifest: str | Path, out: str | Path,
              options: BatchOptions | None = None) -> BatchReport:
    """Run (or continue) the batch of ``manifest`` in the folder ``out``; see the module doc.

    Raises ValueError / FileNotFoundError for a bad manifest (nothing runs) and
    :class:`~app.batch.state.BatchBusy` when another driver holds the folder.
    """
    opts = options or BatchOptions()
    if opts.address is not None:
        split_address(opts.address)  # a malformed address is refused before anything is written
    manifest = Path(manifest).resolve()
    items = read_manifest(manifest)
    if opts.address is None:  # embedded Ray: a task needing more CPUs than it has never starts
        have = opts.num_cpus or os.cpu_count() or 1
        need = max(opts.udn_cpus if it.method == "udn" else opts.cpus_per_item for it in items)
        if need > have:
            raise ValueError(f"an item needs {need} CPUs (--cpus-per-item / --udn-cpus) but "
                             f"this batch's Ray has {have}: it would wait for ever")
    root = Path(out).resolve()
    _check_batch_folder(root, manifest)
    for it in items:  # the batch writes its folder: nothing in it is an input
        inside = [name for name, path in it.inputs
                  if root == Path(path).resolve() or root in Path(path).resolve().parents]
        if inside:
            raise ValueError(f"{it.source}: item {it.id}'s {inside[0]} lies in the batch "
                             f"folder {root}, which the batch writes: move it out")
    paths = BatchPaths(root)
    # what must run, and whether Ray can run it, before anything is written: a run that could
    # not start (Ray missing, a cluster not there) left a half-made folder, "interrupted"
    known = {it.id: input_hashes(it) for it in items}
    if any(finished_record(paths, it, item_hash(it, known[it.id])) is None for it in items):
        check_ray_installed()
        if opts.address is not None:
            check_reachable(opts.address, opts.connect_timeout_s)
    paths.make()
    lock = BatchLock(root).acquire()
    owns_ray = False
    drv = _Driver(manifest, root, items, opts)
    final = "failed"
    signals = TerminateAsInterrupt()
    try:
        signals.install()  # SIGTERM / SIGHUP stop the batch as Ctrl-C does
        paths.cancel_file.unlink(missing_ok=True)  # a request from an earlier run is spent
        for stale in paths.items_dir.glob("*.running"):
            stale.unlink(missing_ok=True)  # no worker of an earlier driver outlives it
        _clean_temp_files(paths)
        for it in items:
            drv.status[it.id] = "pending"
        drv.write_state("starting")
        todo = drv.plan(known)
        drv.write_state("running")
        if opts.progress is not False:  # one line, also in a log (the bar only on a terminal)
            where = (f"joining the Ray cluster at {opts.address}" if opts.address else
                     f"starting Ray here ({opts.num_cpus or os.cpu_count()} CPUs)")
            print(f"batch: {len(items)} items, {len(items) - len(todo)} already done, "
                  f"{len(todo)} to run; {where if todo else 'nothing to run'}", file=sys.stderr)
        if todo:
            _quiet_ray_reports()  # also for a Ray the caller started (undone at the end)
            owns_ray = start_ray(opts.address, opts.num_cpus, opts.connect_timeout_s,
                                 probe=False)
            signals.install()  # ray.init put its own (fatal) SIGTERM handler in place
            drv.execute(todo)
        counts: dict[str, int] = {}
        for s in drv.status.values():
            counts[s] = counts.get(s, 0) + 1
        if drv.cancelling or counts.get("cancelled"):
            final = "cancelled"
        elif counts.get("failed"):
            final = "failed"
        else:
            final = "finished"
        summary = write_summary(root, items, drv.records, drv.status, str(drv.manifest),
                                drv.started)
        drv.write_state(final)
        return BatchReport(root, final, drv.records, counts, time.monotonic() - drv.t0,
                           drv.ran, summary)
    except BaseException:
        with contextlib.suppress(OSError):
            drv.write_state("interrupted")
        raise
    finally:
        paths.cancel_file.unlink(missing_ok=True)
        if owns_ray:
            import ray

            ray.shutdown()
        _loud_ray_reports()
        signals.restore()
        lock.release()


def _clean_temp_files(paths: BatchPaths) -> list[Path]:
    """Remove the temporary files of atomic writes a kill interrupted (the lock is held).

    In the batch folder, ``items/`` and ``results/`` (``.x.tif.abc.tmp``; the targets are
    intact). A UDN run folder in ``runs/`` cleans its own when its job starts or resumes.
    """
    from recon.atomic import temp_files

    removed = []
    for folder in (paths.root, *paths.folders()):
        for p in temp_files(folder):
            with contextlib.suppress(FileNotFoundError):
                p.unlink()
                removed.append(p)
    return removed
