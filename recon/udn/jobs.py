"""Overnight UDN jobs: a spec file in, a run folder out; checkpoints, resume, status, cancel.

Run folder layout (``RUN_DIR``)::

    job.toml           the spec as given (verbatim copy; its relative paths are relative to
                       the record's spec_base, where a run of this copy takes them from too)
    run.json           run record: status, finish reason, error, spec (normalised, absolute
                       paths), input hashes, versions, device, memory estimate, timings,
                       progress (iteration, loss, held-out error, ETA), checkpoint, results,
                       warnings (the MeasurementWarnings the inputs raised, as text)
    loss.csv           iteration, loss, heldout, best_heldout, lr, gain, elapsed_s, restored
                       (after '# format: lenslesscam.udn_loss', '# format_version', ... lines)
    checkpoint.pt      latest checkpoint (weights, Adam state, RNG states, EMA, best, ...)
    checkpoint.prev.pt the checkpoint before it (used when the latest is damaged or missing)
    checkpoints.json   SHA-256 and iteration of the checkpoints written (checked on resume)
    run.lock           the OS lock of the process writing the folder (see recon.udn.rundir)
    previews/iter_NNNNNNN.png   the estimate every ``output.preview_every`` iterations
    final.tif          the final (EMA) estimate, via recon.io.save_reconstruction (+ .png)
    best.tif           the estimate with the lowest held-out error (+ .png)
    mean.tif           the mean of the estimates every ``output.average_every`` iterations
                       (iterate averaging; written once there is one; + .png)
    with_fista.tif     ``output.with_fista`` (default): the mean (best while the mean holds
                       fewer than two estimates) and FISTA-TV at ``recon fista``'s defaults,
                       half and half, written when the run completes or stops early (+ .png)
    CANCEL             present while a cancellation is requested (``jobs cancel``)

Every file is written atomically, by one process at a time (:class:`RunLock`: a second
``jobs run`` / ``jobs resume`` on the folder is refused with :class:`RunFolderBusy`). A
checkpoint is written every ``output.checkpoint_every`` iterations or
``output.checkpoint_minutes`` minutes, whichever comes first, and when the run stops
(completed, stopped early, cancelled); it is read back and checked against its hash before it
replaces the previous one. A crash or SIGKILL loses at most one interval; :func:`resume_job`
continues from the newest verified checkpoint (from the previous one, with a note in the
record, when the newest is damaged) and, on CPU, ends with the same weights as an
uninterrupted run. Without any usable checkpoint it refuses unless ``restart=True``.
SIGTERM or SIGINT (with :func:`cancel_on_signals`) or the ``CANCEL`` file stop the run cleanly
at the next iteration, with a final checkpoint and record. A full disk fails the run with
:class:`DiskFull` (one line naming the folder); the record says ``failed`` and keeps the last
good checkpoint.

States (``status``) and finish reasons in the record are :class:`recon.udn.state.JobState`
and :class:`recon.udn.state.FinishReason`: ``completed`` (iteration or time limit; ``detail``
says which), ``stopped_early``, ``cancelled``, ``failed`` (with ``error``: type and message).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import math
import os
import platform
import shlex
import signal
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
import torch

from recon.atomic import atomic_write_bytes, atomic_write_json
from recon.calibfile import DARK_CORRECTED_KINDS, calibration_kind
from recon.formats import FORMAT_VERSION, FormatError, file_hash, provenance, read_utf8
from recon.previews import preview_image
from recon.previews import write_png as _write_png  # the shared writer (tests patch it)
from recon.problem import DARK_INPUTS, Problem
from recon.stepwise import StopReason
from recon.udn.memory import check_memory, estimate_udn_memory
from recon.udn.rundir import (
    CHECKPOINT_FILE,
    CHECKPOINT_FORMAT,
    LOCK_FILE,
    PREVIOUS_CHECKPOINT_FILE,
    CheckpointError,
    DiskFull,
    JobError,
    RunFolderBusy,
    RunFolderGone,
    RunLock,
    clean_temp_files,
    is_disk_full,
    load_checkpoint,
    load_latest_checkpoint,
    lock_holder,
    write_checkpoint,
)
from recon.udn.runner import UDNRunner, UDNStep, resolve_device
from recon.udn.spec import (
    network_config,
    normalise_spec,
    parse_spec_text,
    read_spec_text,
    udn_config,
)
from recon.udn.state import FinishReason, JobState

__all__ = [
    "CHECKPOINT_FORMAT",
    "RUN_RECORD_FORMAT",
    "CheckpointError",
    "DiskFull",
    "FinishReason",
    "JobError",
    "JobOutcome",
    "JobState",
    "JobStatus",
    "RunFolderBusy",
    "RunFolderGone",
    "cancel_on_signals",
    "format_status",
    "is_run_folder",
    "job_status",
    "load_checkpoint",
    "refuse_outputs_in_run_folders",
    "request_cancel",
    "resume_job",
    "run_job",
]

#: ``format`` of run.json (checkpoint.pt: ``CHECKPOINT_FORMAT`` from recon.udn.rundir).
RUN_RECORD_FORMAT = "lenslesscam.udn_run"

SPEC_FILE = "job.toml"
RECORD_FILE = "run.json"
LOSS_FILE = "loss.csv"
#: ``loss.csv``'s format name (its leading ``# key: value`` lines, :mod:`recon.csvmeta`)
LOSS_FORMAT = "lenslesscam.udn_loss"
CANCEL_FILE = "CANCEL"
PREVIEW_DIR = "previews"

_CSV_FIELDS = ("iteration", "loss", "heldout", "best_heldout", "lr", "gain", "elapsed_s",
               "restored")
_RESULT_KIND: dict[str, Literal["image", "video", "spectral", "depth"]] = {
    "2d": "image", "video": "video", "spectral": "spectral", "depth": "depth"}
F32 = npt.NDArray[np.float32]
Cancel = threading.Event | Callable[[], bool] | None
OnStep = Callable[[UDNStep], None] | None


def _preprocessing(problem: Any) -> dict[str, Any]:
    """How the inputs were read, as ``recon fista`` records it.

    ``metrics`` puts a truth in the result's frame with it.
    """
    return {**problem.metadata, "rgb": problem.spec.color == "rgb"}


@dataclass(frozen=True)
class JobOutcome:
    """How a job ended."""

    run_dir: Path
    finish_reason: FinishReason
    detail: str
    iterations: int
    record: dict[str, Any]


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


# --------------------------------------------------------------------------------------------
# Signals and cancellation
# --------------------------------------------------------------------------------------------


@contextlib.contextmanager
def cancel_on_signals(event: threading.Event,
                      signals: tuple[int, ...] = (signal.SIGTERM, signal.SIGINT)) -> Iterator[None]:
    """Set ``event`` on SIGTERM / SIGINT while inside (main thread only; else a no-op).

    A second SIGINT falls through to the previous handler (so Ctrl-C twice still interrupts).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old: dict[int, Any] = {}

    def handler(signum: int, frame: FrameType | None) -> None:
        already = event.is_set()
        event.set()
        if already and signum == signal.SIGINT:
            prev = old.get(signum)
            if callable(prev):
                prev(signum, frame)
            else:
                raise KeyboardInterrupt

    for s in signals:
        old[s] = signal.signal(s, handler)
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def request_cancel(run_dir: str | Path, *, send_signal: bool = False) -> str:
    """Ask a running job to stop: writes ``RUN_DIR/CANCEL`` (and SIGTERMs its process).

    Returns a one-line message. Raises FileNotFoundError if there is no run there, ValueError
    if the run is not running.
    """
    rd = Path(run_dir)
    rec = read_record(rd)
    here = rec.get("host") in (None, platform.node())
    # on this host the run's lock says whether a process works on the run (a run, or a
    # resume still in its setup, holds it for as long as it lives); the record's pid may be
    # stale or reused
    holder = lock_holder(rd) if here else None
    if here and holder is None:
        if rec.get("status") == "running":
            raise ValueError(f"{rd}: the run is not running (its process {rec.get('pid')} is "
                             f"gone: it was interrupted); continue it with 'lenslesscam jobs "
                             f"resume {rd}'")
        raise ValueError(f"{rd}: the run is not running (finish reason "
                         f"{rec.get('finish_reason')})")
    if not here and rec.get("status") != "running":
        raise ValueError(f"{rd}: the run is not running (finish reason "
                         f"{rec.get('finish_reason')})")
    atomic_write_bytes(rd / CANCEL_FILE, f"cancel requested {_now()} by pid {os.getpid()}\n"
                       .encode())
    msg = f"cancel requested: the job in {rd} stops at its next iteration"
    if send_signal:
        pid = holder[0] if holder else None
        if isinstance(pid, int) and pid > 0:
            os.kill(pid, signal.SIGTERM)  # the process that holds the lock, by its own line
            msg += f" (SIGTERM sent to pid {pid})"
        else:
            msg += " (no SIGTERM: the process holding the run is not known on this host)"
    return msg


class _CancelCheck:
    """Cancellation from an event, a callable or the ``CANCEL`` file in the run folder."""

    def __init__(self, cancel: Cancel, run_dir: Path) -> None:
        self.cancel = cancel
        self.path = run_dir / CANCEL_FILE
        self.why = ""

    def __call__(self) -> bool:
        if isinstance(self.cancel, threading.Event):
            if self.cancel.is_set():
                self.why = "cancel requested (signal or caller)"
                return True
        elif self.cancel is not None and self.cancel():
            self.why = "cancel requested by the caller"
            return True
        if self.path.exists():  # a stat per iteration: microseconds against milliseconds
            self.why = f"cancel requested ({CANCEL_FILE} file)"
            return True
        return False


# --------------------------------------------------------------------------------------------
# Loading the data of a spec
# --------------------------------------------------------------------------------------------


#: the keys of a spec's [data] whose values can be files
_DATA_FILE_KEYS = frozenset({"measurement", "psf", "mask", "shutter", "filters", "truth", "dark",
                             "psf_dark"})


def _load_problem(spec: Mapping[str, Any], device: torch.device) -> Problem:
    """The problem of a normalised spec's ``[data]`` table (:func:`recon.problem.load_problem`).

    Errors name the spec key: ``data.measurement: ...``.
    """
    from recon.problem import ProblemSpec, load_problem

    d = spec["data"]
    try:
        return load_problem(ProblemSpec.from_data_section(d), device=device)
    except (ValueError, FileNotFoundError) as exc:
        msg = str(exc)
        for key, path in d.items():  # the file the message names (not a word such as 'sensor')
            if key in _DATA_FILE_KEYS and isinstance(path, str) and path and path in msg:
                raise type(exc)(f"data.{key}: {msg}") from None
        raise type(exc)(f"[data]: {msg}") from None


# --------------------------------------------------------------------------------------------
# Records and files
# --------------------------------------------------------------------------------------------


def read_record(run_dir: str | Path) -> dict[str, Any]:
    """The run record (``run.json``) of a run folder, checked for format and version."""
    run_dir = Path(run_dir)
    p = run_dir / RECORD_FILE
    if not p.is_file():
        raise FileNotFoundError(f"{run_dir}: no UDN run here ({RECORD_FILE} not found)")
    try:
        rec = json.loads(read_utf8(p, error=FormatError, what="cannot read the run record: "))
    except FormatError:  # not UTF-8: its one-line message as it is
        raise
    except (OSError, ValueError) as exc:
        raise FormatError(f"{p}: cannot read the run record: {exc}") from None
    if not isinstance(rec, dict) or rec.get("format") != RUN_RECORD_FORMAT:
        raise FormatError(f"{p} is not a UDN run record")
    _check_record_fields(rec, p)
    if rec.get("format_version", 0) > FORMAT_VERSION:
        raise FormatError(f"{p}: run record version {rec.get('format_version')} is newer than "
                          f"this release reads ({FORMAT_VERSION})")
    return rec


def is_run_folder(folder: str | Path) -> bool:
    """Whether ``folder`` holds a UDN run: a ``run.json`` that is a run record.

    A ``run.json`` that cannot be read counts too when the folder also holds the run's
    ``job.toml`` (a damaged record is still a run's). The one test of the commands that must
    never write into a run (every writer command's outputs, through
    ``app.commands._options.check_command_outputs``; a new run's folder in ``jobs run`` and
    ``recon udn``, and :func:`run_job` itself).
    """
    p = Path(folder) / RECORD_FILE
    if not p.is_file():
        return False
    try:
        with open(p, "rb") as fh:
            rec = json.loads(fh.read(1 << 24))
    except (OSError, ValueError):
        return (Path(folder) / SPEC_FILE).is_file()
    return isinstance(rec, dict) and rec.get("format") == RUN_RECORD_FORMAT


def run_folder_holding(path: str | os.PathLike[str]) -> Path | None:
    """The UDN run folder that ``path`` (a file to write) lies in, at any depth; or None."""
    p = Path(os.path.abspath(path))
    with contextlib.suppress(OSError, RuntimeError):
        # through symbolic links, before '..' (a/link/../x is where the link points, then up)
        p = Path(path).resolve()
    for folder in p.parents:
        if is_run_folder(folder):
            return folder
    return None


def refuse_outputs_in_run_folders(outputs: Iterable[str | os.PathLike[str]], option: str,
                                  shown: str | os.PathLike[str] | None = None) -> None:
    """Raise ValueError (one line) when an output lies inside a UDN run folder.

    A run's files are what ``jobs status``, ``resume``, ``cancel`` and ``combine`` read: a
    file written over them (``--write-spec RUN/run.json --overwrite`` made the run unreadable)
    or beside them is refused whatever ``--overwrite`` says. ``option`` and ``shown`` (what
    the user gave, when the outputs are files in it, as ``trade --out``'s) name it.
    """
    for o in outputs:
        folder = run_folder_holding(o)
        if folder is not None:
            raise ValueError(f"{option} {o if shown is None else shown} writes into the UDN run "
                             f"folder {folder} (it holds {RECORD_FILE}): a run's folder holds "
                             "only the run's own files; choose another place")


_NUM = (int, float)
_NONE = type(None)
#: Fields of run.json that the code reads, with the types they must have (absent is fine).
_RECORD_FIELDS: dict[str, tuple[type, ...]] = {
    "format_version": (int,),
    "status": (str,),
    "finish_reason": (str, _NONE),
    "detail": (str, _NONE),
    "pid": (int, _NONE),
    "host": (str, _NONE),
    "resumes": (int,),
    "spec": (dict, _NONE),
    "inputs": (dict, _NONE),
    "notes": (list,),
    "warnings": (list,),
    "sessions": (list,),
    "timings": (dict,),
    "device": (dict, _NONE),
    "results": (dict, _NONE),
    "progress": (dict, _NONE),
    "progress.iteration": (int,),
    "progress.max_iter": (int, _NONE),
    "progress.loss": (*_NUM, _NONE),
    "progress.heldout": (*_NUM, _NONE),
    "progress.best_iteration": (int, _NONE),
    "progress.elapsed_s": (*_NUM, _NONE),
    "progress.eta_s": (*_NUM, _NONE),
    "progress.last_preview": (str, _NONE),
    "progress.updated_utc": (str, _NONE),
    "checkpoint": (dict, _NONE),
    "checkpoint.iteration": (int,),
}
_TYPE_WORDS = {int: "an integer", float: "a number", str: "a string", dict: "a table",
               list: "a list", _NONE: "null"}


def _check_record_fields(rec: dict[str, Any], path: Path) -> None:
    """One-line error naming the file and the field when a field of run.json is damaged."""
    for key, types in _RECORD_FIELDS.items():
        head, _, tail = key.partition(".")
        holder: Any = rec if not tail else rec.get(head)
        name = tail or head
        if not isinstance(holder, dict) or name not in holder:
            continue
        v = holder[name]
        ok = isinstance(v, types) and not (isinstance(v, bool) and bool not in types)
        if not ok:
            want = " or ".join(dict.fromkeys(_TYPE_WORDS[t] for t in types))
            raise FormatError(f"{path}: field '{key}' should be {want}, got {v!r:.60} (the run "
                              "record is damaged; repair that field or start a new run)")
    for key, enum_type in (("status", JobState), ("finish_reason", FinishReason)):
        v = rec.get(key)
        if isinstance(v, str) and v not in enum_type._value2member_map_:
            allowed = ", ".join(m.value for m in enum_type)
            raise FormatError(f"{path}: field '{key}' is {v!r:.60}; expected one of {allowed}")


def pid_alive(pid: int, host: Any = None) -> bool:
    """Whether process ``pid`` runs (False for a process recorded on another host)."""
    if host not in (None, platform.node()):
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def read_loss_rows(run_dir: str | os.PathLike[str]) -> list[dict[str, str]]:
    """The rows of a run's ``loss.csv`` (its one reader).

    Each row has every column of the file (an absent one as ""); the iteration is checked to
    be an integer. Reads the file with its header (format version 1) and without (written
    before the header existed); a newer format or a damaged file is a
    :class:`~recon.formats.FormatError` naming the file and line.
    """
    from recon.csvmeta import read_table

    p = Path(run_dir) / LOSS_FILE
    table = read_table(p, LOSS_FORMAT, FORMAT_VERSION, "UDN loss.csv")
    rows = []
    for line, row in table.rows:
        if None in row or None in row.values():  # more or fewer fields than the header
            what = "more" if None in row else "fewer"
            raise FormatError(f"{p}: line {line}: {what} fields than the header's "
                              f"{len(table.fieldnames)} (a damaged row): repair or delete "
                              "that line")
        try:
            int(row["iteration"])
        except (KeyError, TypeError, ValueError):
            raise FormatError(f"{p}: line {line}: field 'iteration' should be an integer, got "
                              f"{row.get('iteration')!r:.40}") from None
        rows.append({k: row.get(k) or "" for k in _CSV_FIELDS})
    return rows


def _spec_hash(spec: Mapping[str, Any]) -> str:
    return hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:16]


# --------------------------------------------------------------------------------------------
# The job
# --------------------------------------------------------------------------------------------


class _Job:
    """One session of a job (a fresh run or a resume)."""

    def __init__(self, run_dir: Path, record: dict[str, Any], progress: OnStep,
                 cancel: Cancel, lock: RunLock | None = None) -> None:
        self.run_dir = run_dir
        self.record = record
        self.lock = lock
        #: what this session has to say about how it started (kept in the record's notes)
        self.notes: list[str] = []
        #: told each note that arises once the session has begun (a resume's ``notice``)
        self.notice: Callable[[str], None] | None = None
        self.progress = progress
        self.cancel = _CancelCheck(cancel, run_dir)
        self.rows: list[dict[str, Any]] = []
        self.runner: UDNRunner | None = None
        #: torch threads for this session given by the caller (overrides device.threads)
        self.threads: int | None = None
        self.problem: Problem | None = None
        self.spec: dict[str, Any] = record["spec"]
        self._last_status = 0.0
        self._last_ckpt_time = time.monotonic()
        self._last_ckpt_iter = 0
        self._session_start = time.monotonic()

    # -- files ---------------------------------------------------------------------------------
    def folder_intact(self) -> bool:
        """Whether the run folder is still there, with this session's lock file in it."""
        if self.lock is not None and self.lock.held:
            return self.lock.intact()
        return self.run_dir.is_dir()

    def check_folder(self) -> None:
        """Raise :class:`RunFolderGone` when the run folder was deleted or moved.

        Called before every write: an atomic write makes missing parent folders, so a run
        whose folder was deleted went on writing a new one that no one saw (the app's queue
        then started the next job beside it).
        """
        if not self.folder_intact():
            raise RunFolderGone(f"the run folder {self.run_dir} (or its {LOCK_FILE}) was deleted "
                                "or moved while the run wrote it: the run stops and writes "
                                "nothing more; start it again in a new folder")

    def write_record(self) -> None:
        self.check_folder()
        atomic_write_json(self.run_dir / RECORD_FILE, self.record)

    def write_csv(self) -> None:
        from recon.csvmeta import format_table

        self.check_folder()
        meta = [("spec_hash", _spec_hash(self.spec)), ("written_utc", _now())]
        text = format_table(LOSS_FORMAT, FORMAT_VERSION, meta, _CSV_FIELDS, self.rows)
        atomic_write_bytes(self.run_dir / LOSS_FILE, text.encode())

    def read_csv(self, upto: int) -> None:
        """The loss history up to ``upto`` (a resume's checkpoint); a lost one is noted."""
        p = self.run_dir / LOSS_FILE
        self.rows = []
        if p.is_file():
            self.rows = [r for r in read_loss_rows(self.run_dir) if int(r["iteration"]) <= upto]
        note = None
        if upto > 0 and not self.rows:
            note = (f"{LOSS_FILE} was {'empty' if p.is_file() else 'missing'} at the resume: "
                    f"the loss history restarts at iteration {upto + 1}")
        elif upto > 0:
            # a repaired file (a damaged row deleted, a cut-off end): one row per iteration
            from recon.checks import index_ranges

            # (rows missing before the first one: a history that restarted, noted then)
            have = {int(r["iteration"]) for r in self.rows}
            missing = sorted(set(range(min(have), upto + 1)) - have)
            if missing:
                note = (f"{LOSS_FILE} lacks the rows of iterations {index_ranges(missing)[1:-1]} "
                        f"({len(missing)} rows): the loss history has a gap there")
                if note in (self.record.get("notes") or []):
                    note = None  # said at an earlier resume
        if note is not None:
            self.notes.append(note)
            if self.notice is not None:
                self.notice(note)

    def checkpoint(self) -> None:
        runner = self.runner
        if runner is None:
            return
        it = runner.iteration
        ck = {
            "format": CHECKPOINT_FORMAT,
            "format_version": FORMAT_VERSION,
            "iteration": it,
            "spec_hash": _spec_hash(self.spec),
            "run_id": self.record.get("run_id"),
            "written_utc": _now(),
            "provenance": provenance(),
            "state": runner.state_dict(),
        }
        self.write_csv()
        self.record["checkpoint"] = write_checkpoint(self.run_dir, ck)
        self._last_ckpt_time = time.monotonic()
        self._last_ckpt_iter = it
        self.write_record()

    def _progress_record(self, s: UDNStep) -> None:
        self.record["progress"] = {
            "iteration": s.iteration,
            "max_iter": self.spec["stopping"]["max_iter"],
            "loss": s.loss,
            "heldout": s.heldout,
            "best_heldout": s.best_heldout,
            "best_iteration": s.best_iteration,
            "lr": s.lr,
            "gain": s.gain,
            "elapsed_s": round(s.elapsed_s, 3),
            "eta_s": None if s.eta_s is None else round(s.eta_s, 1),
            "updated_utc": _now(),
            "last_preview": self.record.get("progress", {}).get("last_preview"),
        }

    # -- setup ---------------------------------------------------------------------------------
    def setup(self, max_memory: int | None) -> None:
        spec = self.spec
        t0 = time.perf_counter()
        dev_name = spec["device"]["device"]
        device = resolve_device(dev_name)
        from recon.threads import apply_threads

        # 0: the thread policy chooses; the caller's count (--threads) overrides the spec's
        want = self.threads if self.threads else spec["device"]["threads"]
        threads = apply_threads(want)
        problem = _load_problem(spec, device)
        self.problem = problem
        # what the inputs were warned of (a raw frame without its dark, zeros without a mask):
        # the record keeps it beside the result, not only a terminal's stderr
        self.record["warnings"] = list(problem.metadata.get("warnings", []))
        model = problem.model
        net = network_config(spec, model.k)
        cfg = udn_config(spec)
        limit = max_memory if max_memory is not None else spec["device"]["max_memory"]
        est = estimate_udn_memory(net, model.scene_shape, model.meas_shape, precision=cfg.precision,
                                  device=device)
        self.record["memory"] = check_memory(est, net, model.scene_shape, device, limit,
                                             model.meas_shape)
        runner = UDNRunner(model, problem.meas, network=net, config=cfg)
        self.runner = runner
        dev_info: dict[str, Any] = {
            "requested": dev_name, "device": str(device), "threads": torch.get_num_threads(),
            "threads_reason": threads.reason if not self.threads else (
                f"{threads.reason} (over the spec's {spec['device']['threads']})"),
            "precision": cfg.precision, "channels_last": cfg.channels_last,
            "compile": {"requested": cfg.compile, "active": bool(runner._compiled),
                        "mode": cfg.compile_mode},
            "machine": platform.machine(), "processor": platform.processor(),
        }
        if device.type == "cuda":
            dev_info["name"] = torch.cuda.get_device_name(device)
        self.record["device"] = dev_info
        self.record["network"] = {**net.to_dict(), "parameters": runner.G.parameter_count()}
        self.record["scene_shape"] = list(model.scene_shape)
        self.record["meas_shape"] = list(model.meas_shape)
        self.record["heldout_pixels"] = runner.n_heldout
        self.record["fitted_pixels"] = runner.n_fit
        self.record["initial_gain"] = runner.initial_gain
        self.record.setdefault("timings", {})["setup_s"] = round(time.perf_counter() - t0, 3)

    def check_inputs_unchanged(self) -> None:
        assert self.problem is not None
        before = self.record.get("inputs", {})
        now_inputs = self.problem.inputs.items()
        for name, now in now_inputs:  # every file first: a changed dark file also reads as
            if name in DARK_INPUTS and name not in before:  # other measurement data
                continue  # a record from before dark files were hashed
            old = before.get(name, {})
            if old.get("file_hash") != now.get("file_hash"):
                raise ValueError(f"data.{name} ({now.get('path')}) changed since the run "
                                 f"started (hash {old.get('file_hash')} -> "
                                 f"{now.get('file_hash')}); start a new run instead")
        for name, now in now_inputs:
            old = before.get(name, {})
            if old.get("array_hash") != now.get("array_hash"):
                raise ValueError(f"data.{name} ({now.get('path')}) is the same file but reads "
                                 f"as other data (array hash {old.get('array_hash')} -> "
                                 f"{now.get('array_hash')}): this version prepares it "
                                 "differently; start a new run instead")

    # -- loop ----------------------------------------------------------------------------------
    def loop(self) -> str:
        runner = self.runner
        assert runner is not None
        out = self.spec["output"]
        every, minutes = out["checkpoint_every"], out["checkpoint_minutes"]
        preview_every, status_s = out["preview_every"], out["status_seconds"]
        self.record["status"] = "running"
        self.write_record()
        for s in runner.steps(preview_every):
            self.rows.append({
                "iteration": s.iteration, "loss": f"{s.loss:.9g}",
                "heldout": "" if s.heldout is None else f"{s.heldout:.9g}",
                "best_heldout": "" if s.best_heldout is None else f"{s.best_heldout:.9g}",
                "lr": f"{s.lr:.6g}", "gain": f"{s.gain:.6g}", "elapsed_s": f"{s.elapsed_s:.4f}",
                "restored": int(s.restored)})
            self._progress_record(s)
            if s.preview is not None:
                name = f"{PREVIEW_DIR}/iter_{s.iteration:07d}.png"
                self.check_folder()
                _write_png(self.run_dir / name, preview_image(s.preview))
                self.record["progress"]["last_preview"] = name
            if self.progress is not None:
                self.progress(s)
            if self.cancel():
                runner.cancel()
                break
            now = time.monotonic()
            if (s.iteration - self._last_ckpt_iter >= every
                    or now - self._last_ckpt_time >= 60.0 * minutes) and not runner.done:
                self.checkpoint()
            elif now - self._last_status >= status_s or s.preview is not None:
                self._last_status = now
                self.write_csv()
                self.write_record()
        reason = runner.reason or StopReason.CANCELLED
        return reason.value

    def _with_fista(self, results: dict[str, Any], hashes: dict[str, str],
                    estimates: list[tuple[str, Any]], base_meta: dict[str, Any],
                    kind: str) -> None:
        """Write ``with_fista.tif``: the averaged recipe (docs/udn.md), appended to ``estimates``.

        The run's mean of at least two estimates, else its best, half and half with FISTA-TV
        at ``recon fista``'s defaults of the same problem. A cancel during the FISTA-TV run
        skips it (noted); so does a FISTA-TV that fails (noted, the run's results stand).
        """
        from recon.io import data_hash, save_reconstruction
        from recon.udn.ensemble import MIN_MEAN_COUNT, average_with_fista, fista_tv_member

        runner, problem = self.runner, self.problem
        assert runner is not None and problem is not None
        which = "mean" if runner.mean_count >= MIN_MEAN_COUNT else "best"
        x_udn = dict(estimates)[which]
        try:
            out = fista_tv_member(problem.model, problem.meas, cancel=self.cancel)
        except (ValueError, RuntimeError, ArithmeticError) as exc:  # memory, numerics
            results["with_fista_note"] = (f"with_fista.tif not written: FISTA-TV failed "
                                          f"({type(exc).__name__}: {exc})")
            return
        if out is None:
            results["with_fista_note"] = "with_fista.tif not written: cancelled during FISTA-TV"
            return
        xf, fmeta = out
        if xf.size != x_udn.size:
            results["with_fista_note"] = (f"with_fista.tif not written: FISTA-TV gave shape "
                                          f"{xf.shape}, the run's estimate is {x_udn.shape}")
            return
        x = np.asarray(average_with_fista(x_udn, xf), dtype=np.float32)
        self.check_folder()
        meta = {**base_meta, "method": "udn+fista-tv", "estimate": "with_fista",
                "udn_estimate": which, "fista": fmeta}
        paths = save_reconstruction(self.run_dir / "with_fista.tif", x, meta, kind=kind)
        results["with_fista"] = str(paths[0].relative_to(self.run_dir))
        results["with_fista_estimate"] = which
        results["fista"] = {k: fmeta[k] for k in ("tau", "iterations", "tau_rule",
                                                  "wall_time_s")}
        hashes["with_fista"] = data_hash(x)
        estimates.append(("with_fista", x))

    def finish(self, reason: str) -> None:
        runner = self.runner
        problem = self.problem
        assert runner is not None and problem is not None
        self.checkpoint()
        kind = _RESULT_KIND[problem.kind]
        final, best = runner.final_estimate(), runner.best_estimate()
        estimates = [("final", final), ("best", best)]
        if runner.mean_count:  # none before the first average_every iterations
            estimates.append(("mean", runner.mean_estimate()))
        base_meta = {
            "method": "udn", "model": problem.kind, "iterations": runner.iteration,
            "best_iteration": runner.best_iteration, "best_heldout": runner.best_heldout,
            "finish_reason": reason, "network": self.record.get("network"),
            "optimizer": self.spec["optimizer"], "stopping": self.spec["stopping"],
            "inputs": self.record.get("inputs"), "device": self.record.get("device"),
            "run_dir": str(self.run_dir), "preprocessing": _preprocessing(problem),
        }
        from recon.io import data_hash, save_reconstruction

        results: dict[str, Any] = {}
        hashes: dict[str, str] = {}
        averaged = {"average_every": runner.config.average_every,
                    "mean_count": runner.mean_count,
                    "mean_last_iteration": runner.mean_last_iteration}
        for which, x in estimates:
            self.check_folder()
            paths = save_reconstruction(self.run_dir / f"{which}.tif", x,
                                        {**base_meta, "estimate": which,
                                         **(averaged if which == "mean" else {})}, kind=kind)
            results[which] = str(paths[0].relative_to(self.run_dir))
            hashes[which] = data_hash(x)
        # what the run wrote: a result file replaced later is told apart (jobs combine)
        results["data_hashes"] = hashes
        results["best_iteration"] = runner.best_iteration
        results["best_heldout"] = runner.best_heldout
        if "mean" in results:
            results.update(averaged)
        if self.spec["output"].get("with_fista", True) and reason in (
                "max_iter", "time_limit", "stopped_early"):
            self._with_fista(results, hashes, estimates, base_meta, kind)
        if reason in ("max_iter", "time_limit"):
            results["still_improving"] = runner.still_improving()
            results["limit_reached"] = reason  # which limit (a resume raises that one)
        if problem.truth is not None:
            from recon.metrics import metrics_report

            try:
                results["scores"] = {
                    which: {k: v for k, v in metrics_report(problem.truth, x,
                                                            gain_fit=True).items()
                            if k in ("psnr", "ssim", "gain", "mse")}
                    for which, x in estimates}
            except ValueError as exc:  # a truth nothing can be scored against (constant):
                results["scores_note"] = f"not scored: {exc}"  # the run's results still count
        self.record["results"] = results


_DETAIL = {
    "max_iter": "reached the iteration limit",
    "time_limit": "reached the wall-time limit",
    "stopped_early": "the held-out error stopped improving",
    "cancelled": "cancelled",
}


def _limit_detail(job: _Job, reason: str, detail: str) -> str:
    """The finish detail of a run that reached a limit: whether it was still improving.

    A run whose held-out error was still improving says so, with the command that continues
    it (``results.still_improving``, written by ``finish``, records it either way).
    """
    r = job.runner
    assert r is not None
    if not r.still_improving():
        return detail
    if reason == "max_iter":
        more = f"--max-iter {2 * r.iteration}"
    else:  # past what the run has used (resume refuses a limit it has reached)
        more = f"--time-limit {_seconds_arg(2 * max(r.config.time_limit_s or 0.0, r.elapsed_s))}"
    return (f"{detail}; the held-out error was still improving (best at iteration "
            f"{r.best_iteration} of {r.iteration}): more iterations would likely give a better "
            f"result: lenslesscam jobs resume {shlex.quote(str(job.run_dir))} {more}")


def _seconds_arg(s: float) -> str:
    """A number of seconds > 0 as a command-line value, never rounded down to 0.

    Whole seconds (rounded up) from 10 s; three significant digits below, rounded up (a
    limit of 0.001 s doubled is "0.002", where ``:.0f`` printed "0", which is refused).
    """
    if s >= 10:
        return str(math.ceil(s))
    text = f"{s:.3g}"
    if float(text) < s:  # rounded down: the next step up at that precision
        exp = math.floor(math.log10(s)) - 2
        text = f"{math.ceil(s / 10.0 ** exp) * 10.0 ** exp:.3g}"
    return text


def _finish_reason(reason: str) -> FinishReason:
    """The job's finish reason for the solver's stop reason (limits count as completed)."""
    if reason in (FinishReason.STOPPED_EARLY, FinishReason.CANCELLED):
        return FinishReason(reason)
    return FinishReason.COMPLETED


def _kept(rec: Mapping[str, Any]) -> str:
    """What a failed run keeps (for its one-line error)."""
    ck = rec.get("checkpoint")
    if isinstance(ck, dict) and isinstance(ck.get("iteration"), int):
        return f"the last good checkpoint (iteration {ck['iteration']}) is kept"
    return "no checkpoint had been written yet"


def _as_disk_full(exc: BaseException, job: _Job) -> DiskFull:
    """A full disk anywhere in a session as one line: the folder, what was written, what is kept."""
    if isinstance(exc, DiskFull):
        head = str(exc)
    else:
        what = ""
        fn = getattr(exc, "filename", None)
        if isinstance(fn, str | os.PathLike):
            what = f" while writing {Path(fn).name}"
        head = f"disk full: no space left on the device of {job.run_dir}{what}"
    return DiskFull(f"{head}; {_kept(job.record)}; free some space, then "
                    f"'lenslesscam jobs resume {job.run_dir}'")


def _session(job: _Job, max_memory: int | None, resume_state: dict[str, Any] | None,
             resumed_from: dict[str, Any] | None = None, *, resuming: bool = False) -> JobOutcome:
    """Run one session of a job; the record and loss.csv say how it ended.

    A resume that fails before its first iteration (a memory or device refusal, another run's
    checkpoint, an unreadable loss.csv, Ctrl-C during start-up) leaves the run as it was: its
    record, spec and loss history are not written (they were: a refused resume wiped loss.csv
    and marked a completed run failed).
    """
    rec = job.record
    # a resume that fails before its first iteration puts the record back as it was
    before = (job.run_dir / RECORD_FILE).read_bytes() if resuming else b""
    sessions = rec.setdefault("sessions", [])
    session: dict[str, Any] = {"started_utc": _now(), "pid": os.getpid(),
                               "host": platform.node(), "start_iteration": 0}
    if resumed_from is not None:
        session["resumed_from"] = resumed_from
    if job.notes:
        session["notes"] = list(job.notes)
    sessions.append(session)
    rec.update(status=JobState.RUNNING, finish_reason=None, detail=None, error=None,
               pid=os.getpid(), host=platform.node(), finished_utc=None)
    t0 = time.perf_counter()
    try:
        job.setup(max_memory)
        assert job.runner is not None and job.problem is not None
        if resume_state is not None:
            job.check_inputs_unchanged()
            job.runner.load_state_dict(resume_state["state"])
            session["start_iteration"] = job.runner.iteration
            job._last_ckpt_iter = job.runner.iteration
            job.read_csv(job.runner.iteration)
        else:
            rec["inputs"] = job.problem.inputs
        # the session's notes travel in the runner's state, so later checkpoints keep them
        job.runner.notes.extend(n for n in job.notes if n not in job.runner.notes)
        rec["notes"] = list(job.runner.notes)
        job.write_record()
        reason = job.loop()
        rec["notes"] = list(job.runner.notes)
        rec["device"]["compile"]["active"] = bool(job.runner._compiled)
        job.finish(reason)
        finish = _finish_reason(reason)
        detail = _DETAIL.get(reason, reason)
        if reason == "cancelled" and job.cancel.why:
            detail = job.cancel.why
        if reason == "stopped_early":
            detail = (f"the held-out error has not improved for "
                      f"{job.runner.config.patience} iterations; best at iteration "
                      f"{job.runner.best_iteration}")
        if reason in ("max_iter", "time_limit"):
            detail = _limit_detail(job, reason, detail)
        rec.update(status=JobState.FINISHED, finish_reason=finish, detail=detail)
    except BaseException as exc:
        if not job.folder_intact():  # deleted or moved: write nothing (it would be made again)
            if isinstance(exc, RunFolderGone):
                raise
            job.check_folder()
        err: BaseException = exc
        if is_disk_full(exc):
            err = _as_disk_full(exc, job)
            if job.lock is not None:
                job.lock.release_reserve()  # room for the record that says so
        elif isinstance(exc, CheckpointError):
            err = CheckpointError(f"{exc}; {_kept(rec)}")
        # a resume that has not finished one iteration (a refusal at setup, torch.compile or
        # an out-of-memory at the first step, Ctrl-C meanwhile) leaves the run as it was
        iterating = job.runner is not None and (
            job.runner.iteration > session["start_iteration"])
        if resuming and not iterating:
            with contextlib.suppress(OSError):  # written as RUNNING just before the loop
                if (job.run_dir / RECORD_FILE).read_bytes() != before:
                    atomic_write_bytes(job.run_dir / RECORD_FILE, before)
            if err is exc:
                raise
            raise err from exc
        rec.update(status=JobState.FINISHED, finish_reason=FinishReason.FAILED,
                   error={"type": type(err).__name__, "message": str(err)},
                   detail=f"{type(err).__name__}: {err}")
        if isinstance(exc, KeyboardInterrupt):
            rec["detail"] = "interrupted (KeyboardInterrupt)"
        if job.runner is not None:
            job.runner.notes.extend(n for n in job.notes if n not in job.runner.notes)
            rec["notes"] = list(job.runner.notes)
            if isinstance(exc, ArithmeticError) and job.runner.best is not None:
                _save_best_after_failure(job)
        else:
            notes = rec.setdefault("notes", [])
            notes.extend(n for n in job.notes if n not in notes)
        _finalise(job, session, t0)
        if err is exc:
            raise
        raise err from exc
    _finalise(job, session, t0)
    it = job.runner.iteration if job.runner is not None else 0
    return JobOutcome(job.run_dir, rec["finish_reason"], rec["detail"], it, rec)


def _save_best_after_failure(job: _Job) -> None:
    """Keep the best estimate of a run that diverged (it is often still worth having)."""
    from recon.io import data_hash, save_reconstruction

    runner, problem = job.runner, job.problem
    if runner is None or problem is None:
        return
    best = runner.best_estimate()
    if not np.all(np.isfinite(best)):  # never replace a good result by a broken one
        return
    try:
        paths = save_reconstruction(
            job.run_dir / "best.tif", best,
            {"method": "udn", "model": problem.kind, "estimate": "best",
             "best_iteration": runner.best_iteration, "best_heldout": runner.best_heldout,
             "finish_reason": FinishReason.FAILED, "run_dir": str(job.run_dir),
             "preprocessing": _preprocessing(problem)},
            kind=_RESULT_KIND[problem.kind])
        written = data_hash(best)
    except (OSError, ValueError):
        return
    job.record["results"] = {"best": str(paths[0].relative_to(job.run_dir)),
                             "data_hashes": {"best": written},
                             "best_iteration": runner.best_iteration,
                             "best_heldout": runner.best_heldout}


def _finalise(job: _Job, session: dict[str, Any], t0: float) -> None:
    rec = job.record
    rec["finished_utc"] = _now()
    session["ended_utc"] = rec["finished_utc"]
    session["wall_s"] = round(time.perf_counter() - t0, 3)
    if job.runner is not None:
        session["end_iteration"] = job.runner.iteration
        timings = rec.setdefault("timings", {})
        timings["iterations_s"] = round(job.runner.elapsed_s, 3)
        if job.runner.iteration:
            timings["per_iteration_s"] = job.runner.elapsed_s / job.runner.iteration
    rec.setdefault("timings", {})["wall_s"] = round(
        sum(s.get("wall_s", 0.0) for s in rec["sessions"]), 3)
    with contextlib.suppress(OSError):  # a full disk may refuse even this; the error is raised
        job.write_csv()
    try:
        job.write_record()
    except OSError:
        if job.lock is None:
            raise
        job.lock.release_reserve()  # the record must say how the run ended: free the reserve
        with contextlib.suppress(OSError):
            job.write_record()
    with contextlib.suppress(OSError):
        (job.run_dir / CANCEL_FILE).unlink(missing_ok=True)


def _start_notes(removed: list[str]) -> list[str]:
    if not removed:
        return []
    return [f"removed {len(removed)} temporary file(s) left by a write that was interrupted: "
            f"{', '.join(removed)}"]


def run_job(spec_path: str | Path, run_dir: str | Path, *, progress: OnStep = None,
            cancel: Cancel = None, max_memory: int | None = None,
            spec_text: str | None = None, seed: int | None = None,
            threads: int | None = None) -> JobOutcome:
    """Run the job of ``spec_path`` into a new run folder ``run_dir``.

    Args:
        spec_path: the TOML spec (relative paths in it are relative to its folder).
        run_dir: the run folder; created; must not already hold a run.
        progress: called with every :class:`UDNStep` (from the job's thread).
        cancel: a threading.Event or a callable; when set / True the job stops cleanly.
        max_memory: refuse runs estimated above this many bytes (overrides the spec).
        spec_text: the spec's text if it is not to be read from ``spec_path``.
        seed: overrides ``optimizer.seed`` (runs of one spec for an ensemble, see
            :mod:`recon.udn.ensemble`); recorded under ``overrides``.
        threads: torch CPU threads for this run (overrides ``device.threads``; None or 0: the
            spec's); recorded in the session's ``device``.

    Returns the outcome; on failure the run record says ``failed`` with the error, and the
    exception is raised again. Raises :class:`RunFolderBusy` while another process writes
    ``run_dir``.

    """
    rd = Path(run_dir)
    sp = Path(spec_path)
    if spec_text is None:
        spec_text = read_spec_text(sp)
    parse_spec_text(spec_text, sp)  # not TOML: refused before a run folder is made (as not UTF-8)
    copy = spec_text if seed is None else (
        f"# run with 'jobs run --seed {seed}': optimizer.seed = {seed} overrides this file "
        "(run.json: overrides)\n" + spec_text)
    _check_new_run_folder(rd, copy)
    lock = RunLock(rd).acquire()
    try:
        _check_new_run_folder(rd, copy)  # again: a process that held the lock may have written
        return _run_locked(sp, rd, lock, progress, cancel, max_memory, spec_text, seed,
                           threads, copy)
    finally:
        lock.release()


def _spec_base(sp: Path) -> Path:
    """The folder a spec's relative paths are relative to.

    Its own folder, or for a run folder's copy (``RUN/job.toml``, verbatim) the folder of the
    spec it was copied from (the record's ``spec_base``), so that ``jobs run RUN/job.toml
    --seed 1`` runs the same problem.
    """
    folder = sp.parent
    if sp.name == SPEC_FILE and (folder / RECORD_FILE).is_file():
        try:
            base = read_record(folder).get("spec_base")
        except (OSError, ValueError):
            base = None
        if isinstance(base, str) and Path(base).is_absolute():
            return Path(base)
    return folder


def _check_new_run_folder(rd: Path, spec_copy: str) -> None:
    """Refuse a folder that holds a run, or files that are not a run's.

    A run would overwrite them, inputs among them. A folder left by a start that failed before
    its first iteration (a refused spec, a device or memory refusal) holds only that attempt's
    record and spec: it may be used again; so may one left by a start killed before its record
    (the lock, temporary files, and a ``job.toml`` that is this very spec). A folder inside
    another run's folder (at any depth, through links) is refused: that folder holds only its
    own run's files (:func:`refuse_outputs_in_run_folders`).
    """
    holder = run_folder_holding(rd)
    if holder is not None:
        raise ValueError(f"{rd} lies inside the UDN run folder {holder} (it holds "
                         f"{RECORD_FILE}): a run's folder holds only the run's own files; "
                         "choose a run folder outside it")
    if (rd / RECORD_FILE).exists():
        try:
            rec = read_record(rd)
        except (OSError, ValueError):
            rec = {}
        never_ran = rec.get("finish_reason") == FinishReason.FAILED and (
            rec.get("spec") is None
            or (not (rec.get("progress") or {}).get("iteration") and not rec.get("checkpoint")
                and not (rd / CHECKPOINT_FILE).exists()))
        if not never_ran:
            raise ValueError(f"{rd} already holds a run: use 'jobs resume {rd}' or another "
                             "folder")
        return  # a start that failed before its first iteration: its files are rewritten
    if rd.is_dir():
        from recon.atomic import is_temp_name

        spec = rd / SPEC_FILE
        ours = spec.is_file() and spec.read_bytes() == spec_copy.encode("utf-8")
        others = sorted(p.name for p in rd.iterdir()
                        if p.name != LOCK_FILE and not is_temp_name(p.name)
                        and not (ours and p.name == SPEC_FILE))
        if others:
            raise ValueError(f"{rd} is not empty and holds no run ({len(others)} entries, e.g. "
                             f"{others[0]}): a run writes its files there; choose a new or "
                             "empty folder")
    elif rd.exists():
        raise ValueError(f"{rd} exists and is not a folder")


def _run_locked(sp: Path, rd: Path, lock: RunLock, progress: OnStep, cancel: Cancel,
                max_memory: int | None, spec_text: str, seed: int | None,
                threads: int | None, copy: str) -> JobOutcome:
    removed = clean_temp_files(rd)
    record: dict[str, Any] = {
        "format": RUN_RECORD_FORMAT,
        "format_version": FORMAT_VERSION,
        "status": JobState.STARTING,
        "finish_reason": None,
        "detail": None,
        "error": None,
        "run_id": uuid.uuid4().hex,  # in every checkpoint: another run's is refused
        "spec_file": SPEC_FILE,
        "spec_source": str(sp.resolve()) if sp.exists() else str(sp),
        "spec_base": str(_spec_base(sp).absolute()),
        "spec": None,
        "started_utc": _now(),
        "pid": os.getpid(),
        "host": platform.node(),
        "provenance": provenance(),
        "timings": {},
        "sessions": [],
    }
    job = _Job(rd, record, progress, cancel, lock)
    job.threads = threads
    job.notes = _start_notes(removed)
    try:
        atomic_write_bytes(rd / SPEC_FILE, copy.encode("utf-8"))
        record["spec_file_hash"] = file_hash(rd / SPEC_FILE)  # a later edit is then noticed
        raw = parse_spec_text(spec_text, sp)
        if seed is not None:
            opt = raw.setdefault("optimizer", {})
            if isinstance(opt, dict):
                opt["seed"] = seed
            record["overrides"] = {"optimizer.seed": seed}
        record["spec"] = normalise_spec(raw, Path(record["spec_base"]), source=str(sp))
        job.spec = record["spec"]
        record["spec_hash"] = _spec_hash(record["spec"])
    except BaseException as exc:
        err: BaseException = _as_disk_full(exc, job) if is_disk_full(exc) else exc
        if err is not exc:
            lock.release_reserve()
        record.update(status=JobState.FINISHED, finish_reason=FinishReason.FAILED,
                      finished_utc=_now(),
                      error={"type": type(err).__name__, "message": str(err)},
                      detail=f"{type(err).__name__}: {err}")
        with contextlib.suppress(OSError):
            job.write_record()
        if err is exc:
            raise
        raise err from exc
    return _session(job, max_memory, None)


def resume_job(run_dir: str | Path, *, max_iter: int | None = None,
               time_limit_s: float | None = None, progress: OnStep = None,
               cancel: Cancel = None, max_memory: int | None = None, restart: bool = False,
               notice: Callable[[str], None] | None = None,
               threads: int | None = None) -> JobOutcome:
    """Continue a run from its newest verified checkpoint.

    ``max_iter`` / ``time_limit_s`` raise the limits (to continue a completed run). When the
    newest checkpoint is damaged or missing the previous one is used, and the run record says
    so. When no checkpoint is usable although one was written, the resume is refused unless
    ``restart`` (begin again from iteration 0); a run stopped before its first checkpoint starts
    again from 0 with a note. ``notice`` receives these notes (one line each) as they arise.
    ``threads`` overrides ``device.threads`` for this session (as in :func:`run_job`).

    Refuses (:class:`RunFolderBusy`) while another process writes the folder, and inputs whose
    files changed since the run started.
    """
    rd = Path(run_dir)
    read_record(rd)  # a run is there (never create a lock file in a folder without one)
    lock = RunLock(rd).acquire()
    try:
        return _resume_locked(rd, lock, max_iter, time_limit_s, progress, cancel, max_memory,
                              restart, notice, threads)
    finally:
        lock.release()


def _resume_locked(rd: Path, lock: RunLock, max_iter: int | None, time_limit_s: float | None,
                   progress: OnStep, cancel: Cancel, max_memory: int | None, restart: bool,
                   notice: Callable[[str], None] | None,
                   threads: int | None = None) -> JobOutcome:
    rec = read_record(rd)  # again, now that no other process writes it
    if rec.get("spec") is None:
        raise ValueError(f"{rd}: the run never started (its spec was invalid: "
                         f"{rec.get('detail')}); fix the spec and start a new run")
    spec = {sec: {k: v for k, v in keys.items() if v is not None}
            for sec, keys in json.loads(json.dumps(rec["spec"])).items()}
    if max_iter is not None:
        spec["stopping"]["max_iter"] = int(max_iter)
    if time_limit_s is not None:
        spec["stopping"]["time_limit_s"] = float(time_limit_s)
    spec = normalise_spec(spec, rd, source=f"{rd / RECORD_FILE} spec")
    notes = _start_notes(clean_temp_files(rd))
    data = spec["data"]
    if ("run_id" not in rec and data.get("psf_dark") is None and data.get("dark") is not None
            and isinstance(data.get("psf"), str)
            and calibration_kind(data["psf"]) in DARK_CORRECTED_KINDS):
        # begun before a calibrated PSF was exempt from data.dark: it goes on as it began
        data["psf_dark"] = data["dark"]
        notes.append("this run began when data.dark was taken off a calibrated PSF too; it "
                     "goes on that way (psf_dark = dark), a new run would not")
    state, info, problems = load_latest_checkpoint(rd)
    recorded = rec.get("checkpoint")
    at = int((rec.get("progress") or {}).get("iteration", 0))
    had_checkpoint = (isinstance(recorded, dict) or (rd / CHECKPOINT_FILE).exists()
                      or (rd / PREVIOUS_CHECKPOINT_FILE).exists())
    why = "; ".join(problems)
    if state is None and had_checkpoint and not restart:
        raise CheckpointError(
            f"{rd}: no usable checkpoint ({why}); the run had reached iteration {at}: pass "
            "--restart to begin again from iteration 0")
    # refusals that leave the run's record as it is
    ours, theirs = rec.get("run_id"), (state or {}).get("run_id")
    if state is not None and ours and theirs and ours != theirs and not restart:
        raise CheckpointError(
            f"{rd}: {info['path']} (iteration {state['iteration']}) is a checkpoint of another "
            f"run (run id {theirs}, this run's is {ours}): put this run's checkpoint back, or "
            "pass --restart to begin again from iteration 0")
    done = int(state["iteration"]) if state is not None and not restart else 0
    limit = spec["stopping"]["max_iter"]
    if done >= limit:
        raise ValueError(f"{rd}: the run is at iteration {done} and its limit is {limit}: pass a "
                         "larger --max-iter to continue it")
    used = float(state["state"].get("elapsed_s", 0.0)) if done else 0.0
    budget = spec["stopping"].get("time_limit_s")
    if budget is not None and used >= budget:  # it would run one iteration and stop again
        raise ValueError(f"{rd}: the run has used {used:.0f} s of iterations and its time limit "
                         f"is {budget:g} s: pass a larger --time-limit to continue it")
    for name, inp in (rec.get("inputs") or {}).items():
        path, old = inp.get("path"), inp.get("file_hash")
        if isinstance(path, str) and old is not None and file_hash(path) != old:
            raise ValueError(f"data.{name} ({path}) changed since the run started (hash {old} "
                             f"-> {file_hash(path)}); start a new run instead")
    if restart:
        if state is not None:
            notes.append(f"restarted from iteration 0 (--restart) at the user's request; the "
                         f"checkpoint of iteration {info['iteration']} was usable")
        else:
            notes.append(f"restarted from iteration 0 (--restart): no usable checkpoint "
                         f"({why}); the run had reached iteration {at}")
        state, info = None, {}
    elif state is None:
        notes.append(f"resumed without a checkpoint (none was written before the run stopped "
                     f"at iteration {at}): started again from iteration 0")
    elif problems:
        notes.append(f"resumed from {info['path']} (iteration {info['iteration']}) because "
                     f"{why}")
    written = rec.get("spec_file_hash")
    if written is not None and (rd / SPEC_FILE).is_file() and file_hash(rd / SPEC_FILE) != written:
        notes.append(f"{SPEC_FILE} was edited after the run started; a resume keeps the spec "
                     f"the run started with ({RECORD_FILE}): --max-iter and --time-limit change "
                     "its limits, other settings need a new run")
    if notice is not None:
        for n in notes:
            notice(n)
    rec["spec"] = spec
    with contextlib.suppress(FileNotFoundError):
        (rd / CANCEL_FILE).unlink()
    rec["resumes"] = int(rec.get("resumes", 0)) + 1
    job = _Job(rd, rec, progress, cancel, lock)
    job.threads = threads
    job.notes = notes
    job.notice = notice
    return _session(job, max_memory, state, info or None, resuming=True)


# --------------------------------------------------------------------------------------------
# Status
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class JobStatus:
    """What ``jobs status`` shows."""

    run_dir: Path
    name: str
    state: JobState
    finish_reason: FinishReason | None
    detail: str | None
    iteration: int
    max_iter: int | None
    loss: float | None
    heldout: float | None
    best_iteration: int | None
    elapsed_s: float | None
    eta_s: float | None
    device: str | None
    checkpoint_iteration: int | None
    last_preview: str | None
    pid: int | None
    updated_utc: str | None

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (for ``--json``)."""
        d = dict(self.__dict__)
        d["run_dir"] = str(self.run_dir)
        return d


def job_status(run_dir: str | Path) -> JobStatus:
    """Read the state of a run folder (running, interrupted, finished)."""
    rd = Path(run_dir)
    rec = read_record(rd)
    prog = rec.get("progress") or {}
    spec = rec.get("spec") or {}
    status = rec.get("status")
    pid = rec.get("pid")
    state: JobState
    if status in (JobState.RUNNING, JobState.STARTING):
        if rec.get("host") in (None, platform.node()):
            # the run's lock says whether a process works on it (docs/udn.md): the record's
            # pid may be stale (a reboot) or another process's since; the pid shown is the
            # lock holder's own
            holder = lock_holder(rd)
            alive = holder is not None
            if holder is not None and holder[0] is not None:
                pid = holder[0]
        else:  # another host's run: not known here
            alive = False
        state = JobState.RUNNING if alive else JobState.INTERRUPTED
    else:
        state = JobState.FINISHED
    fr = rec.get("finish_reason")
    dev = rec.get("device") or {}
    device = None
    if dev:
        device = f"{dev.get('device')} ({dev.get('threads')} threads, {dev.get('precision')}"
        if dev.get("compile", {}).get("active"):
            device += ", compiled"
        device += ")"
    ck = rec.get("checkpoint") or {}
    lp = prog.get("last_preview")
    return JobStatus(
        run_dir=rd, name=(spec.get("job") or {}).get("name", ""), state=state,
        finish_reason=FinishReason(fr) if fr is not None else None, detail=rec.get("detail"),
        iteration=int(prog.get("iteration", 0)),
        max_iter=prog.get("max_iter", (spec.get("stopping") or {}).get("max_iter")),
        loss=prog.get("loss"), heldout=prog.get("heldout"),
        best_iteration=prog.get("best_iteration"), elapsed_s=prog.get("elapsed_s"),
        eta_s=prog.get("eta_s") if state == "running" else None, device=device,
        checkpoint_iteration=ck.get("iteration"),
        last_preview=str(rd / lp) if lp else None, pid=pid if isinstance(pid, int) else None,
        updated_utc=prog.get("updated_utc"),
    )


def format_hms(s: float | None) -> str:
    """Seconds as ``H:MM:SS`` (``-`` when unknown); job status in the CLI and the GUI."""
    if s is None or not math.isfinite(s):
        return "-"
    n = round(s)
    return f"{n // 3600:d}:{n % 3600 // 60:02d}:{n % 60:02d}"


def _num(v: float | None) -> str:
    return "-" if v is None else f"{v:.4g}"


def format_status(st: JobStatus) -> str:
    """Human-readable multi-line status."""
    if st.state == "running":
        state = f"running (pid {st.pid})"
    elif st.state == "interrupted":
        state = (f"interrupted: no process holds the run folder (its last, pid {st.pid}, "
                 f"ended); continue with 'lenslesscam jobs resume {st.run_dir}'")
    else:
        state = f"finished: {st.finish_reason}"
        if st.detail:
            state += f" ({st.detail})"
    of = f" / {st.max_iter}" if st.max_iter else ""
    lines = [
        f"run:        {st.run_dir}" + (f"  ({st.name})" if st.name else ""),
        f"state:      {state}",
        f"iteration:  {st.iteration}{of}",
        f"loss:       {_num(st.loss)}   held-out: {_num(st.heldout)}   best at iteration "
        f"{st.best_iteration if st.best_iteration is not None else '-'}",
        f"elapsed:    {format_hms(st.elapsed_s)}   ETA: {format_hms(st.eta_s)}",
        f"device:     {st.device or '-'}",
        f"checkpoint: {'-' if st.checkpoint_iteration is None else st.checkpoint_iteration}",
        f"preview:    {st.last_preview or '-'}",
    ]
    return "\n".join(lines)
