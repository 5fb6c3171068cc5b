"""Overnight UDN jobs: a spec file in, a run folder out; checkpoints, resume, status, cancel.

Run folder layout (``RUN_DIR``)::

    job.toml           the spec as given (verbatim copy)
    run.json           run record: status, finish reason, error, spec (normalised, absolute
                       paths), input hashes, versions, device, memory estimate, timings,
                       progress (iteration, loss, held-out error, ETA), checkpoint, results
    loss.csv           iteration, loss, heldout, best_heldout, lr, gain, elapsed_s, restored
    checkpoint.pt      latest checkpoint (weights, Adam state, RNG states, EMA, best, ...)
    previews/iter_NNNNNNN.png   the estimate every ``output.preview_every`` iterations
    final.tif          the final (EMA) estimate, via recon.io.save_reconstruction (+ .png)
    best.tif           the estimate with the lowest held-out error (+ .png)
    CANCEL             present while a cancellation is requested (``jobs cancel``)

Every file is written atomically. A checkpoint is written every ``output.checkpoint_every``
iterations or ``output.checkpoint_minutes`` minutes, whichever comes first, and when the run
stops (completed, stopped early, cancelled). A crash or SIGKILL loses at most one interval;
:func:`resume_job` continues from the checkpoint and, on CPU, ends with the same weights as an
uninterrupted run. SIGTERM or SIGINT (with :func:`cancel_on_signals`) or the ``CANCEL`` file
stop the run cleanly at the next iteration, with a final checkpoint and record.

Finish reasons in the record: ``completed`` (iteration or time limit; ``detail`` says which),
``stopped_early``, ``cancelled``, ``failed`` (with ``error``: type and message).
"""

from __future__ import annotations

import contextlib
import csv
import datetime as _dt
import hashlib
import io
import json
import math
import os
import platform
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
import torch

from recon.formats import (
    FORMAT_VERSION,
    FormatError,
    array_hash,
    atomic_write,
    atomic_write_bytes,
    atomic_write_json,
    file_hash,
    provenance,
)
from recon.udn.memory import check_memory, estimate_memory
from recon.udn.runner import UDNRunner, UDNStep, UDNStopReason, resolve_device
from recon.udn.spec import SpecError, network_config, normalise_spec, udn_config

__all__ = [
    "CHECKPOINT_FORMAT",
    "RUN_RECORD_FORMAT",
    "JobOutcome",
    "JobStatus",
    "cancel_on_signals",
    "format_status",
    "job_status",
    "load_checkpoint",
    "request_cancel",
    "resume_job",
    "run_job",
]

#: ``format`` of run.json and of checkpoint.pt.
RUN_RECORD_FORMAT = "lenslesscam.udn_run"
CHECKPOINT_FORMAT = "lenslesscam.udn_checkpoint"

SPEC_FILE = "job.toml"
RECORD_FILE = "run.json"
LOSS_FILE = "loss.csv"
CHECKPOINT_FILE = "checkpoint.pt"
CANCEL_FILE = "CANCEL"
PREVIEW_DIR = "previews"

#: Fault injection for tests: after the iteration given in this environment variable the job
#: writes its progress and then stalls (sleeps) until it is killed.
STALL_ENV = "LENSLESSCAM_UDN_STALL_AT"

_CSV_FIELDS = ("iteration", "loss", "heldout", "best_heldout", "lr", "gain", "elapsed_s",
               "restored")
_RESULT_KIND: dict[str, Literal["image", "video", "spectral", "depth"]] = {
    "2d": "image", "video": "video", "spectral": "spectral", "depth": "depth"}
F32 = npt.NDArray[np.float32]
Cancel = threading.Event | Callable[[], bool] | None
Progress = Callable[[UDNStep], None] | None


class JobError(RuntimeError):
    """A job could not continue (the message says why and what is intact)."""


@dataclass(frozen=True)
class JobOutcome:
    """How a job ended."""

    run_dir: Path
    finish_reason: str
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
    if rec.get("status") != "running":
        raise ValueError(f"{rd}: the run is not running (finish reason "
                         f"{rec.get('finish_reason')})")
    atomic_write_bytes(rd / CANCEL_FILE, f"cancel requested {_now()} by pid {os.getpid()}\n"
                       .encode())
    msg = f"cancel requested: the job in {rd} stops at its next iteration"
    pid = rec.get("pid")
    if send_signal and isinstance(pid, int) and pid_alive(pid, rec.get("host")):
        os.kill(pid, signal.SIGTERM)
        msg += f" (SIGTERM sent to pid {pid})"
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


@dataclass
class _Problem:
    model: Any
    meas: F32
    truth: F32 | None
    kind: str
    inputs: dict[str, Any]


def load_input(path: str, where: str) -> npt.NDArray[Any]:
    """A job's input file as an array; errors name the spec key (``where``)."""
    from recon.io import load_image

    try:
        return np.asarray(load_image(path))
    except FileNotFoundError:
        raise FileNotFoundError(f"{where}: file not found: {path}") from None
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None


def _describe_input(path: str | list[str] | None, arr: npt.NDArray[Any] | None) -> dict[str, Any]:
    out: dict[str, Any] = {"path": path}
    if isinstance(path, str) and Path(path).is_file():
        out["file_hash"] = file_hash(path)
    elif isinstance(path, list):
        out["file_hash"] = [file_hash(p) for p in path]
    if arr is not None:
        out["array_hash"] = array_hash(arr)
        out["shape"] = list(arr.shape)
    return out


def _load_problem(spec: Mapping[str, Any], device: torch.device) -> _Problem:
    from recon.io import box_downsample, check_pair, load_measurement, load_psf, load_psf_stack
    from recon.models import build_model

    d = spec["data"]
    kind = d["model"]
    ds = d["downsample"]
    color = d["color"]
    dark = d["dark"]
    psf_dark = d["psf_dark"] if d["psf_dark"] is not None else dark
    pn = None if d["psf_normalise"] == "none" else d["psf_normalise"]
    mn = None if d["measurement_normalise"] == "none" else d["measurement_normalise"]
    try:
        meas = load_measurement(d["measurement"], dark=dark, downsample=ds, channels=color,
                                normalise=mn)
    except (ValueError, FileNotFoundError) as exc:
        raise type(exc)(f"data.measurement: {exc}") from None
    try:
        if kind == "depth":
            psf = load_psf_stack(d["psf"], dark=psf_dark, downsample=ds,
                                 normalise=pn)
            check_pair(psf, meas, psf_is_stack=True)
        else:
            psf = load_psf(d["psf"], dark=psf_dark, downsample=ds, channels=color, normalise=pn)
            check_pair(psf, meas)
    except (ValueError, FileNotFoundError) as exc:
        raise type(exc)(f"data.psf: {exc}") from None
    c, h, w = (int(s) for s in meas.shape)
    sensor = (h, w)
    inputs = {"psf": _describe_input(d["psf"], psf),
              "measurement": _describe_input(d["measurement"], meas)}
    mask = None
    if d["mask"] is not None:
        raw = load_input(d["mask"], "data.mask").astype(np.float64)
        if raw.ndim == 3 and raw.shape[0] == 1:
            raw = raw[0]
        if raw.ndim != 2:
            raise ValueError(f"data.mask must be a 2D (H, W) array, got shape {raw.shape}")
        if raw.shape == sensor:
            mask = (raw > 0.5).astype(np.float32)
        elif (raw.shape[0] // ds, raw.shape[1] // ds) == sensor and ds > 1:
            # a downsampled pixel counts as measured only if all its sensor pixels were
            mask = (box_downsample(raw > 0.5, ds) >= 1.0).astype(np.float32)
        else:
            raise ValueError(f"data.mask has shape {raw.shape}; the measurement is {sensor} "
                             f"(or {h * ds}x{w * ds} at full resolution)")
        inputs["mask"] = _describe_input(d["mask"], mask)
    shutter = filters = None
    if kind == "video":
        raw = load_input(d["shutter"], "data.shutter").astype(np.float64)
        if raw.ndim != 2:
            raise ValueError(f"data.shutter must be a (K, rows) array, got shape {raw.shape}")
        if raw.shape[1] == h:
            shutter = raw
        elif ds > 1 and raw.shape[1] // ds == h:
            rows = h * ds
            shutter = raw[:, :rows].reshape(raw.shape[0], h, ds).mean(axis=2)
        else:
            full = f" or (K, {h * ds}) at full resolution" if ds > 1 else ""
            raise ValueError(f"data.shutter has shape {raw.shape}, but the measurement has {h} "
                             f"rows: expected (K, {h}){full}")
        inputs["shutter"] = _describe_input(d["shutter"], shutter)
    if kind == "spectral":
        raw = load_input(d["filters"], "data.filters").astype(np.float64)
        if raw.ndim != 3:
            raise ValueError(f"data.filters must be a (K, H, W) array, got shape {raw.shape}")
        if raw.shape[1:] == sensor:
            filters = raw
        elif ds > 1 and (raw.shape[1] // ds, raw.shape[2] // ds) == sensor:
            filters = box_downsample(raw, ds)
        else:
            raise ValueError(f"data.filters has shape {raw.shape}; expected (K, {h}, {w})")
        inputs["filters"] = _describe_input(d["filters"], filters)
    fld = d["field"]
    field = None if fld == "sensor" else (2 * h, 2 * w) if fld == "full" else tuple(fld)
    psf_arg: Any = psf
    if kind != "depth" and psf.shape[0] == 1:
        psf_arg = psf[0]
    if kind == "depth" and c != 1:
        raise ValueError("data.measurement: the depth model takes a grayscale measurement")
    model = build_model(kind, psf_arg, channels=c if kind != "depth" else None, mask=mask,
                        shutter=shutter, filters=filters, field=field, device=device)
    truth = None
    if d["truth"] is not None:
        truth = load_input(d["truth"], "data.truth").astype(np.float32)
        if truth.shape != tuple(model.scene_shape):
            raise ValueError(f"data.truth has shape {truth.shape}; the scene is "
                             f"{tuple(model.scene_shape)} (C, K, H, W)")
        inputs["truth"] = _describe_input(d["truth"], truth)
    return _Problem(model, meas, truth, kind, inputs)


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
        rec = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise FormatError(f"{p}: cannot read the run record: {exc}") from None
    if not isinstance(rec, dict) or rec.get("format") != RUN_RECORD_FORMAT:
        raise FormatError(f"{p} is not a UDN run record")
    if int(rec.get("format_version", 0)) > FORMAT_VERSION:
        raise FormatError(f"{p}: run record version {rec.get('format_version')} is newer than "
                          f"this release reads ({FORMAT_VERSION})")
    return rec


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


def _spec_hash(spec: Mapping[str, Any]) -> str:
    return hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:16]


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read a checkpoint written by a job (safe loader: tensors and plain data only)."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no checkpoint")
    try:
        ck = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise FormatError(f"{p}: cannot read the checkpoint: {exc}") from None
    if not isinstance(ck, dict) or ck.get("format") != CHECKPOINT_FORMAT:
        raise FormatError(f"{p} is not a UDN checkpoint")
    if int(ck.get("format_version", 0)) > FORMAT_VERSION:
        raise FormatError(f"{p}: checkpoint version {ck.get('format_version')} is newer than "
                          f"this release reads ({FORMAT_VERSION})")
    return ck


def _preview_png(x: F32) -> npt.NDArray[np.uint8]:
    """(C, K, H, W) -> uint8 (C', H', W'): gray/RGB (else the channel mean), frames tiled."""
    from recon.io import contrast_stretch

    arr = np.asarray(x, dtype=np.float32)
    if arr.shape[0] not in (1, 3):
        arr = arr.mean(axis=0, keepdims=True)
    c, k, h, w = arr.shape
    if k > 1:
        cols = math.ceil(math.sqrt(k))
        rows = math.ceil(k / cols)
        pad = 2
        tile = np.full((c, rows * (h + pad) - pad, cols * (w + pad) - pad), np.nan,
                       dtype=np.float32)
        for i in range(k):
            r, q = divmod(i, cols)
            tile[:, r * (h + pad): r * (h + pad) + h, q * (w + pad): q * (w + pad) + w] = \
                arr[:, i]
        img = tile
    else:
        img = arr[:, 0]
    return contrast_stretch(img)


def _write_png(path: Path, chw: npt.NDArray[np.uint8]) -> None:
    from PIL import Image

    im = Image.fromarray(chw[0]) if chw.shape[0] == 1 else Image.fromarray(
        np.ascontiguousarray(np.moveaxis(chw, 0, -1)))
    atomic_write(path, lambda p: im.save(p, format="PNG"))


# --------------------------------------------------------------------------------------------
# The job
# --------------------------------------------------------------------------------------------


class _Job:
    """One session of a job (a fresh run or a resume)."""

    def __init__(self, run_dir: Path, record: dict[str, Any], progress: Progress,
                 cancel: Cancel) -> None:
        self.run_dir = run_dir
        self.record = record
        self.progress = progress
        self.cancel = _CancelCheck(cancel, run_dir)
        self.rows: list[dict[str, Any]] = []
        self.runner: UDNRunner | None = None
        self.problem: _Problem | None = None
        self.spec: dict[str, Any] = record["spec"]
        self._last_status = 0.0
        self._last_ckpt_time = time.monotonic()
        self._last_ckpt_iter = 0
        self._session_start = time.monotonic()
        stall = os.environ.get(STALL_ENV)
        self._stall_at = int(stall) if stall and stall.isdigit() else None

    # -- files ---------------------------------------------------------------------------------
    def write_record(self) -> None:
        atomic_write_json(self.run_dir / RECORD_FILE, self.record)

    def write_csv(self) -> None:
        buf = io.StringIO()
        wr = csv.DictWriter(buf, fieldnames=_CSV_FIELDS, lineterminator="\n")
        wr.writeheader()
        wr.writerows(self.rows)
        atomic_write_bytes(self.run_dir / LOSS_FILE, buf.getvalue().encode())

    def read_csv(self, upto: int) -> None:
        p = self.run_dir / LOSS_FILE
        self.rows = []
        if not p.is_file():
            return
        with open(p, encoding="utf-8", newline="") as fh:
            for row in csv.DictReader(fh):
                if int(row["iteration"]) <= upto:
                    self.rows.append({k: row.get(k, "") for k in _CSV_FIELDS})

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
            "written_utc": _now(),
            "provenance": provenance(),
            "state": runner.state_dict(),
        }
        self.write_csv()
        prev = self.record.get("checkpoint") or {}
        try:
            atomic_write(self.run_dir / CHECKPOINT_FILE, lambda p: torch.save(ck, p))
        except OSError as exc:
            kept = (f"the previous checkpoint (iteration {prev.get('iteration')}) is intact"
                    if prev else "no earlier checkpoint exists")
            raise JobError(f"could not write the checkpoint at iteration {it}: {exc}; {kept}"
                           ) from exc
        self.record["checkpoint"] = {"path": CHECKPOINT_FILE, "iteration": it,
                                     "written_utc": ck["written_utc"]}
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
        threads = spec["device"]["threads"]
        if threads > 0:
            torch.set_num_threads(threads)
        problem = _load_problem(spec, device)
        self.problem = problem
        model = problem.model
        net = network_config(spec, model.k)
        cfg = udn_config(spec)
        limit = max_memory if max_memory is not None else spec["device"]["max_memory"]
        est = estimate_memory(net, model.scene_shape, model.meas_shape, precision=cfg.precision)
        self.record["memory"] = check_memory(est, net, model.scene_shape, device, limit,
                                             model.meas_shape)
        runner = UDNRunner(model, problem.meas, network=net, config=cfg)
        self.runner = runner
        dev_info: dict[str, Any] = {
            "requested": dev_name, "device": str(device), "threads": torch.get_num_threads(),
            "precision": cfg.precision, "channels_last": cfg.channels_last,
            "compile": {"requested": cfg.compile, "active": bool(runner._compiled)},
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
        for name, now in self.problem.inputs.items():
            old = before.get(name, {})
            if old.get("file_hash") != now.get("file_hash") or old.get("array_hash") != now.get(
                    "array_hash"):
                raise ValueError(f"data.{name} ({now.get('path')}) changed since the run "
                                 f"started (hash {old.get('file_hash')} -> "
                                 f"{now.get('file_hash')}); start a new run instead")

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
                _write_png(self.run_dir / name, _preview_png(s.preview))
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
            if self._stall_at is not None and s.iteration == self._stall_at:
                self.write_csv()
                self.write_record()
                while True:  # fault injection for the kill-and-resume test
                    time.sleep(0.05)
        reason = runner.reason or UDNStopReason.CANCELLED
        return reason.value

    def finish(self, reason: str) -> None:
        runner = self.runner
        problem = self.problem
        assert runner is not None and problem is not None
        self.checkpoint()
        kind = _RESULT_KIND[problem.kind]
        final, best = runner.final_estimate(), runner.best_estimate()
        base_meta = {
            "method": "udn", "model": problem.kind, "iterations": runner.iteration,
            "best_iteration": runner.best_iteration, "best_heldout": runner.best_heldout,
            "finish_reason": reason, "network": self.record.get("network"),
            "optimizer": self.spec["optimizer"], "stopping": self.spec["stopping"],
            "inputs": self.record.get("inputs"), "device": self.record.get("device"),
            "run_dir": str(self.run_dir),
        }
        from recon.io import save_reconstruction

        results: dict[str, Any] = {}
        for which, x in (("final", final), ("best", best)):
            paths = save_reconstruction(self.run_dir / f"{which}.tif", x,
                                        {**base_meta, "estimate": which}, kind=kind)
            results[which] = str(paths[0].relative_to(self.run_dir))
        results["best_iteration"] = runner.best_iteration
        results["best_heldout"] = runner.best_heldout
        if problem.truth is not None:
            from recon.metrics import metrics_report

            results["scores"] = {
                which: {k: v for k, v in metrics_report(problem.truth, x, gain_fit=True).items()
                        if k in ("psnr", "ssim", "gain", "mse")}
                for which, x in (("final", final), ("best", best))}
        self.record["results"] = results


_DETAIL = {
    "max_iter": "reached the iteration limit",
    "time_limit": "reached the wall-time limit",
    "stopped_early": "the held-out error stopped improving",
    "cancelled": "cancelled",
}


def _finish_reason(reason: str) -> str:
    return "completed" if reason in ("max_iter", "time_limit") else reason


def _session(job: _Job, max_memory: int | None, resume_state: dict[str, Any] | None) -> JobOutcome:
    rec = job.record
    sessions = rec.setdefault("sessions", [])
    session = {"started_utc": _now(), "pid": os.getpid(), "host": platform.node(),
               "start_iteration": 0}
    sessions.append(session)
    rec.update(status="running", finish_reason=None, detail=None, error=None, pid=os.getpid(),
               host=platform.node(), finished_utc=None)
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
        rec.update(status="finished", finish_reason=finish, detail=detail)
    except BaseException as exc:
        rec.update(status="finished", finish_reason="failed",
                   error={"type": type(exc).__name__, "message": str(exc)},
                   detail=f"{type(exc).__name__}: {exc}")
        if isinstance(exc, KeyboardInterrupt):
            rec["detail"] = "interrupted (KeyboardInterrupt)"
        if job.runner is not None:
            rec["notes"] = list(job.runner.notes)
            if isinstance(exc, ArithmeticError) and job.runner.best is not None:
                _save_best_after_failure(job)
        _finalise(job, session, t0)
        raise
    _finalise(job, session, t0)
    it = job.runner.iteration if job.runner is not None else 0
    return JobOutcome(job.run_dir, rec["finish_reason"], rec["detail"], it, rec)


def _save_best_after_failure(job: _Job) -> None:
    """Keep the best estimate of a run that diverged (it is often still worth having)."""
    from recon.io import save_reconstruction

    runner, problem = job.runner, job.problem
    if runner is None or problem is None:
        return
    try:
        paths = save_reconstruction(
            job.run_dir / "best.tif", runner.best_estimate(),
            {"method": "udn", "model": problem.kind, "estimate": "best",
             "best_iteration": runner.best_iteration, "best_heldout": runner.best_heldout,
             "finish_reason": "failed", "run_dir": str(job.run_dir)},
            kind=_RESULT_KIND[problem.kind])
    except (OSError, ValueError):
        return
    job.record["results"] = {"best": str(paths[0].relative_to(job.run_dir)),
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
    rec["timings"]["wall_s"] = round(sum(s.get("wall_s", 0.0) for s in rec["sessions"]), 3)
    with contextlib.suppress(OSError):  # a full disk may refuse even this; the error is raised
        job.write_csv()
    with contextlib.suppress(OSError):
        job.write_record()
    with contextlib.suppress(OSError):
        (job.run_dir / CANCEL_FILE).unlink(missing_ok=True)


def run_job(spec_path: str | Path, run_dir: str | Path, *, progress: Progress = None,
            cancel: Cancel = None, max_memory: int | None = None,
            spec_text: str | None = None, seed: int | None = None) -> JobOutcome:
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

    Returns the outcome; on failure the run record says ``failed`` with the error, and the
    exception is raised again.

    """
    rd = Path(run_dir)
    sp = Path(spec_path)
    if (rd / RECORD_FILE).exists():
        raise ValueError(f"{rd} already holds a run: use 'jobs resume {rd}' or another folder")
    if spec_text is None:
        if not sp.is_file():
            raise FileNotFoundError(f"job spec not found: {sp}")
        spec_text = sp.read_text(encoding="utf-8")
    rd.mkdir(parents=True, exist_ok=True)
    copy = spec_text if seed is None else (
        f"# run with 'jobs run --seed {seed}': optimizer.seed = {seed} overrides this file "
        "(run.json: overrides)\n" + spec_text)
    atomic_write_bytes(rd / SPEC_FILE, copy.encode("utf-8"))
    record: dict[str, Any] = {
        "format": RUN_RECORD_FORMAT,
        "format_version": FORMAT_VERSION,
        "status": "starting",
        "finish_reason": None,
        "detail": None,
        "error": None,
        "spec_file": SPEC_FILE,
        "spec_source": str(sp.resolve()) if sp.exists() else str(sp),
        "spec": None,
        "started_utc": _now(),
        "pid": os.getpid(),
        "host": platform.node(),
        "provenance": provenance(),
        "timings": {},
        "sessions": [],
    }
    job = _Job(rd, record, progress, cancel)
    try:
        import tomllib

        try:
            raw = tomllib.loads(spec_text)
        except tomllib.TOMLDecodeError as exc:
            raise SpecError(f"{sp}: not valid TOML: {exc}") from None
        if seed is not None:
            opt = raw.setdefault("optimizer", {})
            if isinstance(opt, dict):
                opt["seed"] = seed
            record["overrides"] = {"optimizer.seed": seed}
        record["spec"] = normalise_spec(raw, sp.parent, source=str(sp))
        job.spec = record["spec"]
        record["spec_hash"] = _spec_hash(record["spec"])
    except BaseException as exc:
        record.update(status="finished", finish_reason="failed", finished_utc=_now(),
                      error={"type": type(exc).__name__, "message": str(exc)},
                      detail=f"{type(exc).__name__}: {exc}")
        with contextlib.suppress(OSError):
            job.write_record()
        raise
    return _session(job, max_memory, None)


def resume_job(run_dir: str | Path, *, max_iter: int | None = None,
               time_limit_s: float | None = None, progress: Progress = None,
               cancel: Cancel = None, max_memory: int | None = None) -> JobOutcome:
    """Continue a run from its last checkpoint (from the start if it never wrote one).

    ``max_iter`` / ``time_limit_s`` raise the limits (to continue a completed run). Refuses a
    run whose process is still alive, and inputs whose files changed since the run started.
    """
    rd = Path(run_dir)
    rec = read_record(rd)
    if rec.get("spec") is None:
        raise ValueError(f"{rd}: the run never started (its spec was invalid: "
                         f"{rec.get('detail')}); fix the spec and start a new run")
    pid = rec.get("pid")
    if (rec.get("status") in ("running", "starting") and isinstance(pid, int)
            and pid != os.getpid() and pid_alive(pid, rec.get("host"))):
        raise ValueError(f"{rd}: the run is still running (pid {pid}); cancel it first")
    spec = {sec: {k: v for k, v in keys.items() if v is not None}
            for sec, keys in json.loads(json.dumps(rec["spec"])).items()}
    if max_iter is not None:
        spec["stopping"]["max_iter"] = int(max_iter)
    if time_limit_s is not None:
        spec["stopping"]["time_limit_s"] = float(time_limit_s)
    spec = normalise_spec(spec, rd, source=f"{rd / RECORD_FILE} spec")
    rec["spec"] = spec
    with contextlib.suppress(FileNotFoundError):
        (rd / CANCEL_FILE).unlink()
    ck_path = rd / CHECKPOINT_FILE
    state = load_checkpoint(ck_path) if ck_path.is_file() else None
    # refusals that leave the run's record as it is
    done = int(state["iteration"]) if state is not None else 0
    limit = spec["stopping"]["max_iter"]
    if done >= limit:
        raise ValueError(f"{rd}: the run is at iteration {done} and its limit is {limit}: pass a "
                         "larger --max-iter to continue it")
    for name, info in (rec.get("inputs") or {}).items():
        path, old = info.get("path"), info.get("file_hash")
        if isinstance(path, str) and old is not None and file_hash(path) != old:
            raise ValueError(f"data.{name} ({path}) changed since the run started (hash {old} "
                             f"-> {file_hash(path)}); start a new run instead")
    if state is None:
        rec.setdefault("notes", []).append("resumed without a checkpoint: started again")
    rec["resumes"] = int(rec.get("resumes", 0)) + 1
    job = _Job(rd, rec, progress, cancel)
    return _session(job, max_memory, state)


# --------------------------------------------------------------------------------------------
# Status
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class JobStatus:
    """What ``jobs status`` shows."""

    run_dir: Path
    name: str
    state: str
    finish_reason: str | None
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
    if status in ("running", "starting"):
        alive = isinstance(pid, int) and pid_alive(pid, rec.get("host"))
        state = "running" if alive else "interrupted"
    else:
        state = "finished"
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
        finish_reason=rec.get("finish_reason"), detail=rec.get("detail"),
        iteration=int(prog.get("iteration", 0)),
        max_iter=prog.get("max_iter", (spec.get("stopping") or {}).get("max_iter")),
        loss=prog.get("loss"), heldout=prog.get("heldout"),
        best_iteration=prog.get("best_iteration"), elapsed_s=prog.get("elapsed_s"),
        eta_s=prog.get("eta_s") if state == "running" else None, device=device,
        checkpoint_iteration=ck.get("iteration"),
        last_preview=str(rd / lp) if lp else None, pid=pid if isinstance(pid, int) else None,
        updated_utc=prog.get("updated_utc"),
    )


def _hms(s: float | None) -> str:
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
        state = (f"interrupted: process {st.pid} is gone; continue with "
                 f"'lenslesscam jobs resume {st.run_dir}'")
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
        f"elapsed:    {_hms(st.elapsed_s)}   ETA: {_hms(st.eta_s)}",
        f"device:     {st.device or '-'}",
        f"checkpoint: {'-' if st.checkpoint_iteration is None else st.checkpoint_iteration}",
        f"preview:    {st.last_preview or '-'}",
    ]
    return "\n".join(lines)
