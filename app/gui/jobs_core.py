"""UDN jobs launched from the app, without Qt: a jobs folder, a queue, detached processes.

Each job the app creates is a folder under the jobs folder::

    <jobs dir>/<YYYYmmdd-HHMMSS>-<name>/
        app-job.json     the app's entry: name, device, queue state, launches, memory estimate
        app-job.lock     the claim (an OS lock) a window holds while it launches the job
        job.toml         the UDN job spec (recon.udn.spec), paths relative to this folder
        inputs/          measurement.npy (raw codes), measurement.json (frame metadata),
                         psf.npy (unit sum, float32), shutter.npy (video)
        run/             the run folder of ``lenslesscam jobs run`` (run.json, loss.csv,
                         checkpoint.pt, previews/, final.tif, best.tif)
        job.log          stdout and stderr of the job's processes

The job runs in its own process (``python -m app jobs run job.toml --out run``), started in a
new session by :func:`spawn_job_process`, so closing the window (or the app crashing) leaves it
running; its progress is read back from the run folder. :class:`JobQueue` starts queued jobs
one at a time per device (a second job for a busy device waits), and :func:`discover_jobs`
finds every job again after a restart: running (a process holds the run's lock),
interrupted (none does: resume continues from the last checkpoint), finished.
"""

from __future__ import annotations

import datetime as _dt
import enum
import json
import os
import re
import signal
import subprocess
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
import numpy.typing as npt

from recon.formats import whole_version

__all__ = [
    "APP_JOB_FILE",
    "APP_JOB_FORMAT",
    "AppJobState",
    "JobQueue",
    "JobView",
    "cancel_job",
    "combine_jobs",
    "combine_refusal",
    "create_job",
    "default_sections",
    "device_key",
    "discover_jobs",
    "estimate_job_memory",
    "job_view",
    "jobs_dir_problem",
    "read_loss",
    "resolve_device_name",
    "spawn_job_process",
]

APP_JOB_FILE = "app-job.json"
APP_JOB_FORMAT = "lenslesscam.app_job"
APP_JOB_VERSION = 1
RUN_DIR = "run"
SPEC = "job.toml"
LOG = "job.log"
#: the claim a window holds (an OS lock) while it launches the job
CLAIM = "app-job.lock"

#: Processes this app process started (pid -> Popen), reaped by :meth:`JobQueue.poll` so a
#: finished child never lingers as a zombie that looks alive. Process-wide on purpose: a job
#: started by a window that was closed is still this process's child.
_CHILDREN: dict[int, Any] = {}

#: Starts one job process: ``(lenslesscam arguments, working folder, environment, log file)``
#: -> a handle with Popen's ``pid``, ``poll``, ``wait``, ``terminate`` and ``kill``.
Spawner = Callable[[list[str], Path, dict[str, str], IO[bytes]], Any]


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def _slug(name: str) -> str:
    s = re.sub(r"[^A-Za-z0-9._-]+", "-", name.strip()).strip("-.")
    return (s or "job")[:40]


def _read_json(p: Path) -> dict[str, Any] | None:
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return d if isinstance(d, dict) else None


def _write_entry(folder: Path, entry: Mapping[str, Any]) -> None:
    from recon.atomic import atomic_write_json

    atomic_write_json(folder / APP_JOB_FILE, dict(entry))


def resolve_device_name(name: str) -> str:
    """The device a job would use, as :func:`device_key` names it (``auto``: ``cuda:0``...)."""
    from recon.udn.runner import resolve_device

    return device_key(str(resolve_device(name)))


def device_key(name: str) -> str:
    """One name per device, the queue's key (``cuda`` is ``cuda:0``).

    ``cuda`` is where a job's process puts it, ``cuda:0``; ``auto`` the device it resolves
    to; others as given. The queue keyed on the raw text, so an ``auto`` job (stored as
    ``cuda``) and a ``cuda:0`` job ran at once on one GPU.
    """
    if name == "auto":
        return resolve_device_name(name)
    if name == "cuda":
        return "cuda:0"
    return name


def default_sections() -> dict[str, dict[str, Any]]:
    """Spec sections the app fills in by default (a small network, CPU-friendly outputs)."""
    return {
        "network": {"scales": 4, "channels": 32},
        "stopping": {"max_iter": 3000},
        "device": {"device": "auto", "threads": 1},
        "output": {"checkpoint_every": 200, "preview_every": 50, "status_seconds": 2.0},
    }


def _full_spec(sections: Mapping[str, Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """Every schema key with its default, then ``sections`` on top (no file checks)."""
    from recon.udn.spec import SCHEMA

    out = {sec: {k: key.default for k, key in keys.items()} for sec, keys in SCHEMA.items()}
    for sec, keys in sections.items():
        out.setdefault(sec, {}).update(keys)
    return out


def estimate_job_memory(
    sensor: tuple[int, int], downsample: int, sections: Mapping[str, Mapping[str, Any]],
    k: int = 1,
) -> tuple[Any, int | None, str]:
    """Memory estimate of a 2D job: (MemoryEstimate, bytes available or None, their source)."""
    from recon.udn.memory import available_memory, estimate_udn_memory
    from recon.udn.spec import network_config

    spec = _full_spec(sections)
    h, w = sensor[0] // downsample, sensor[1] // downsample
    if h < 1 or w < 1:
        raise ValueError(f"downsampling by {downsample} leaves nothing of {sensor}")
    net = network_config(spec, k)
    device = resolve_device_name(spec["device"]["device"])
    est = estimate_udn_memory(net, (1, k, h, w), (1, h, w),
                              precision=spec["device"]["precision"], device=device)
    avail, source = available_memory(device)
    return est, avail, source


def jobs_dir_problem(jobs_dir: str | Path) -> str | None:
    """Why no job can be queued in ``jobs_dir`` (None: it is, or can be made, a folder).

    Said when the app starts, not only when the first job fails to be written.
    """
    from app.commands._options import check_output_folders, refuse_run_folder_outputs

    p = Path(jobs_dir)
    if p.exists() and not p.is_dir():
        return (f"the jobs folder {p} is a file, not a folder: no job can be queued; choose "
                "another jobs folder (--jobs-dir, or jobs_dir in the settings file)")
    try:  # the one probe of a folder the system lets us write (os.access says yes to root)
        check_output_folders([p / "probe"])
    except PermissionError as exc:
        return (f"the jobs folder {p} cannot hold jobs ({exc}): no job can be queued there; "
                "choose another jobs folder (--jobs-dir, or jobs_dir in the settings file)")
    try:  # a run's folder holds only its run's files (the shared output rule)
        refuse_run_folder_outputs([p / "probe"], "the jobs folder")
    except ValueError:
        from recon.udn.jobs import run_folder_holding

        return (f"the jobs folder {p} lies inside the UDN run folder "
                f"{run_folder_holding(p / 'probe')}, which holds only its run's files: no job "
                "can be queued there; choose another jobs folder (--jobs-dir, or jobs_dir in "
                "the settings file)")
    return None


def create_job(
    jobs_dir: str | Path,
    name: str,
    measurement: npt.ArrayLike,
    psf: npt.ArrayLike,
    *,
    downsample: int = 1,
    dark: float | str = "auto",
    sections: Mapping[str, Mapping[str, Any]] | None = None,
    shutter: npt.ArrayLike | None = None,
    measurement_metadata: Mapping[str, Any] | None = None,
    queue: bool = True,
) -> Path:
    """Write a job folder (inputs, spec, entry) and queue it; returns the folder.

    The spec is validated (:func:`recon.udn.spec.load_spec`) before the job is queued; an
    invalid one raises :class:`~recon.udn.spec.SpecError` and leaves no folder behind.
    """
    import shutil

    from recon.atomic import atomic_write, atomic_write_bytes, atomic_write_json
    from recon.problem import ProblemSpec
    from recon.udn.spec import load_spec, spec_to_toml

    meas = np.asarray(measurement)
    p = np.asarray(psf, dtype=np.float32)
    if meas.ndim != 2:
        raise ValueError(f"the measurement must be one 2D frame, got shape {meas.shape}")
    if int(downsample) < 1 or min(meas.shape) // int(downsample) < 1:
        raise ValueError(f"downsampling by {downsample} leaves nothing of the "
                         f"{meas.shape[0]}x{meas.shape[1]} frame: the job could not run")
    root = Path(jobs_dir)
    problem = jobs_dir_problem(root)  # before anything is written there
    if problem is not None:
        raise ValueError(problem)
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    folder = root / f"{stamp}-{_slug(name)}"
    n = 1
    while folder.exists():
        n += 1
        folder = root / f"{stamp}-{_slug(name)}-{n}"
    inputs = folder / "inputs"
    inputs.mkdir(parents=True)
    try:
        atomic_write(inputs / "measurement.npy", lambda t: np.save(t, meas))
        atomic_write(inputs / "psf.npy", lambda t: np.save(t, p / p.sum(dtype=np.float64)))
        atomic_write_json(inputs / "measurement.json", dict(measurement_metadata or {}))
        secs = {sec: dict(v) for sec, v in (sections or default_sections()).items()}
        if shutter is not None:
            atomic_write(inputs / "shutter.npy",
                         lambda t: np.save(t, np.asarray(shutter, dtype=np.float32)))
        # the job's [data] table is a ProblemSpec (loaded by recon.problem.load_problem)
        data = ProblemSpec(meas="inputs/measurement.npy", psf="inputs/psf.npy",
                           model="2d" if shutter is None else "video",
                           shutter=None if shutter is None else "inputs/shutter.npy",
                           downsample=int(downsample), dark=dark,
                           psf_dark=0.0).to_data_section()
        spec = {"job": {"name": name}, "data": data, **secs}
        atomic_write_bytes(folder / SPEC, spec_to_toml(spec).encode("utf-8"))
        full = load_spec(folder / SPEC)
        device = resolve_device_name(full["device"]["device"])
        k = 1 if shutter is None else int(np.asarray(shutter).shape[0])
        try:
            est, avail, source = estimate_job_memory(meas.shape, int(downsample), secs, k)
            memory = {"total_bytes": est.total_bytes, "peak_bytes": est.peak_bytes,
                      "available_bytes": avail,
                      "source": source}
        except ValueError as exc:
            memory = {"error": str(exc)}
        _write_entry(folder, {
            "format": APP_JOB_FORMAT, "format_version": APP_JOB_VERSION, "name": name,
            "created_utc": _now(), "device": device,
            "state": "queued" if queue else "held", "action": "run", "launches": [],
            "memory": memory,
        })
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    return folder


def _pid_alive(pid: int, launched_utc: object = None) -> bool:
    """Whether the process ``pid`` (launched at ``launched_utc``, when given) still runs.

    A process that started after its launch was recorded is another one with a reused pid
    (after a reboot): not alive. Only for a launch's pid; whether a run is alive is its
    lock's to say (:func:`recon.udn.jobs.job_status`).
    """
    child = _CHILDREN.get(pid)
    if child is not None:  # our own child: poll() also reaps it (kill(pid, 0) sees zombies)
        return child.poll() is None
    from recon.udn.jobs import pid_alive

    if not pid_alive(pid):
        return False
    started = _process_start(pid)
    try:
        when = _dt.datetime.fromisoformat(str(launched_utc)).timestamp()
    except ValueError:
        return True
    # the launch is stamped (to the second) after the process was started
    return started is None or started <= when + 3.0


def _process_start(pid: int) -> float | None:
    """When process ``pid`` started (Unix time), from /proc; None where that cannot be read."""
    try:
        with open("/proc/stat", encoding="ascii") as fh:
            boot = next(float(line.split()[1]) for line in fh if line.startswith("btime "))
        with open(f"/proc/{pid}/stat", encoding="utf-8", errors="replace") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
        return boot + int(fields[19]) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return None


def spawn_job_process(args: list[str], cwd: Path, env: dict[str, str],
                      log: IO[bytes]) -> subprocess.Popen[bytes]:
    """``python -m app ARGS`` in a new session (detached), its output appended to ``log``."""
    return subprocess.Popen(
        [sys.executable, "-m", "app", *args],
        stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT, cwd=str(cwd),
        env=env, start_new_session=True,
    )


def _launch(folder: Path, action: str, max_iter: int | None = None,
            spawn: Spawner = spawn_job_process, time_limit_s: float | None = None) -> Any:
    """Start ``jobs run`` / ``jobs resume`` for ``folder`` through ``spawn``."""
    if action == "run":
        args = ["jobs", "run", str(folder / SPEC), "--out", str(folder / RUN_DIR), "--quiet"]
    else:
        args = ["jobs", "resume", str(folder / RUN_DIR), "--quiet"]
        if max_iter is not None:
            args += ["--max-iter", str(int(max_iter))]
        if time_limit_s is not None:
            args += ["--time-limit", repr(float(time_limit_s))]
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH", "")) if p)
    env.pop("QT_QPA_PLATFORM", None)
    with open(folder / LOG, "ab") as log:
        log.write(f"--- {_now()} {action}\n".encode())
        log.flush()
        proc = spawn(args, folder, env, log)
    _CHILDREN[proc.pid] = proc
    return proc


class AppJobState(enum.StrEnum):
    """Where an app job stands.

    The run record's states (:class:`recon.udn.state.JobState`, the same strings) and the app
    queue's own: held, withdrawn, launched, failed to start.
    """

    QUEUED = "queued"
    HELD = "held"
    WITHDRAWN = "withdrawn"
    LAUNCHED = "launched"
    STARTING = "starting"
    RUNNING = "running"
    INTERRUPTED = "interrupted"
    FINISHED = "finished"
    FAILED_TO_START = "failed to start"

    @classmethod
    def read(cls, text: object) -> AppJobState:
        """The state named ``text`` (an unknown word, from a newer version: ``HELD``).

        Held, not queued: a job whose state this version does not know is never started by
        itself (it was: an 'archived' job of a newer release ran again).
        """
        try:
            return cls(str(text))
        except ValueError:
            return cls.HELD

    @property
    def cancellable(self) -> bool:
        """Whether Cancel applies (withdraw it, or stop its process)."""
        return self in (AppJobState.QUEUED, AppJobState.STARTING, AppJobState.RUNNING,
                        AppJobState.HELD)


@dataclass
class JobView:
    """What the panel shows about one job (read from its folder)."""

    folder: Path
    name: str
    device: str
    state: AppJobState
    finish_reason: str | None = None
    detail: str | None = None
    iteration: int = 0
    max_iter: int | None = None
    loss: float | None = None
    eta_s: float | None = None
    elapsed_s: float | None = None
    last_preview: Path | None = None
    results: dict[str, Path] = field(default_factory=dict)
    pid: int | None = None
    memory: dict[str, Any] = field(default_factory=dict)
    created_utc: str = ""
    still_improving: bool = False
    #: the run's wall-time limit (seconds of iterations), if it has one
    time_limit_s: float | None = None
    #: the limit a completed run reached: ``max_iter`` or ``time_limit`` (None: neither)
    limit_reached: str | None = None
    #: a resume would begin again from iteration 0: the run stopped before its first
    #: checkpoint (``jobs resume`` does that, with a note)
    from_start: bool = False

    @property
    def fraction(self) -> float:
        """Fraction of the run done: the larger of the iteration and time fractions.

        1 for a run that completed or stopped early (a time-limited run read 1 % throughout
        and after it ended, its iteration limit far away).
        """
        if self.state is AppJobState.FINISHED and self.finish_reason in (
                "completed", "stopped_early"):
            return 1.0
        done = self.iteration / self.max_iter if self.max_iter else 0.0
        if self.time_limit_s and self.elapsed_s is not None:
            done = max(done, self.elapsed_s / self.time_limit_s)
        return min(1.0, max(0.0, done))

    @property
    def active(self) -> bool:
        """Whether a process of this job runs (or is being started)."""
        return self.state in (AppJobState.STARTING, AppJobState.RUNNING)

    @property
    def run_dir(self) -> Path:
        """The job's run folder."""
        return self.folder / RUN_DIR

    @property
    def can_resume(self) -> bool:
        """Whether the run can continue (or the job be queued again).

        What ``jobs resume`` takes: an interrupted or cancelled run, a failed one (from its
        checkpoint, or from iteration 0 when it stopped before its first one, a full disk
        say), one that reached its limit still improving (to twice the iterations,
        :attr:`resume_max_iter`, or the time, :attr:`resume_time_limit_s`); and a job
        withdrawn from the queue (queued again).
        """
        if self.state in (AppJobState.INTERRUPTED, AppJobState.WITHDRAWN):
            return True
        if self.state is not AppJobState.FINISHED:
            return False
        has_checkpoint = (self.run_dir / "checkpoint.pt").is_file()
        if self.finish_reason == "failed":
            return has_checkpoint or self.from_start
        return has_checkpoint and (self.finish_reason == "cancelled" or (
            self.finish_reason == "completed" and self.still_improving))

    @property
    def resume_time_limit_s(self) -> float | None:
        """The time limit a resume passes (``--time-limit``, seconds), or None.

        None unless the run completed at its time limit, then twice what it used (at least
        its limit), as its detail advises. Without it ``jobs resume`` refused ("pass a
        larger --time-limit").
        """
        if (self.finish_reason != "completed" or self.limit_reached != "time_limit"
                or not self.time_limit_s):
            return None
        from recon.udn.jobs import _seconds_arg

        return float(_seconds_arg(2 * max(self.time_limit_s, self.elapsed_s or 0.0)))

    @property
    def resume_max_iter(self) -> int | None:
        """The iteration limit a resume asks for.

        None (the run's own), or twice it for a run that reached it still improving (what its
        detail line suggests).
        """
        if (self.finish_reason == "completed" and self.max_iter
                and self.limit_reached != "time_limit"):
            return 2 * int(self.max_iter)
        return None


def _entry_problem(entry: dict[str, Any]) -> str | None:
    """What makes an app-job.json unusable for starting its job (None: nothing).

    A damaged entry (launches not a list, a max_iter that is not a whole number, an unknown
    action) was started again every second: the launch was made, then recording it failed.
    """
    if entry.get("action", "run") not in ("run", "resume"):
        return f"action {entry.get('action')!r} is not run or resume"
    mi = entry.get("max_iter")
    if mi is not None and (not isinstance(mi, int) or isinstance(mi, bool) or mi < 1):
        return f"max_iter {mi!r} is not a whole number >= 1"
    tl = entry.get("time_limit_s")
    if tl is not None and (not isinstance(tl, int | float) or isinstance(tl, bool)
                           or not 0 < tl < float("inf")):
        return f"time_limit_s {tl!r} is not a number of seconds > 0"
    launches = entry.get("launches", [])
    if not isinstance(launches, list) or not all(isinstance(x, dict) for x in launches):
        return "launches is not a list of launches"
    return None


def job_view(folder: str | Path) -> JobView | None:
    """Read one job folder (None when it is not an app job)."""
    f = Path(folder)
    entry = _read_json(f / APP_JOB_FILE)
    if entry is None or entry.get("format") != APP_JOB_FORMAT:
        return None
    v = JobView(folder=f, name=str(entry.get("name", f.name)),
                device=str(entry.get("device", "?")),
                state=AppJobState.read(entry.get("state", "queued")),
                memory=dict(entry.get("memory") or {}),
                created_utc=str(entry.get("created_utc", "")))
    version = whole_version(entry.get("format_version", APP_JOB_VERSION))
    if version is None or version > APP_JOB_VERSION:
        v.state = AppJobState.HELD  # never started by a version that does not know it
        v.detail = (f"written by a newer lenslesscam (app job format "
                    f"{entry.get('format_version')!r}); this version does not start it")
        return v
    problem = _entry_problem(entry)
    if problem is not None:
        v.state = AppJobState.FAILED_TO_START
        v.detail = f"{APP_JOB_FILE} is damaged: {problem}; it is not started"
        return v
    launches = entry.get("launches") or []
    last = launches[-1] if launches else None
    record = f / RUN_DIR / "run.json"
    if v.state in (AppJobState.QUEUED, AppJobState.HELD, AppJobState.WITHDRAWN):
        if v.state is AppJobState.QUEUED and last is not None and record.is_file():
            pass  # a resume waits in the queue: show the run's numbers
        else:
            return v
    if record.is_file():
        from recon.udn.jobs import job_status

        try:
            st = job_status(f / RUN_DIR)
        except (OSError, ValueError) as exc:
            v.detail = f"run record unreadable: {exc}"
            return v
        v.iteration, v.max_iter, v.loss = st.iteration, st.max_iter, st.loss
        v.eta_s, v.elapsed_s, v.pid = st.eta_s, st.elapsed_s, st.pid
        v.finish_reason, v.detail = st.finish_reason, st.detail
        v.last_preview = Path(st.last_preview) if st.last_preview else None
        rec = _read_json(record) or {}
        res = rec.get("results")
        results: dict[str, Any] = res if isinstance(res, dict) else {}
        _limits_of(v, rec, results)
        if v.state is not AppJobState.QUEUED:
            # running or interrupted: the run's lock said (job_status), not a pid that may be
            # stale or another process's since (a reboot)
            v.state = AppJobState.read(st.state)
            # a resume launched but not yet re-registered in the record
            if (st.state != AppJobState.RUNNING and last is not None
                    and last.get("action") == "resume"
                    and _pid_alive(int(last["pid"]), last.get("utc"))):
                v.state = AppJobState.STARTING
                _resuming(v, last.get("max_iter"), last.get("time_limit_s"))
        elif entry.get("action") == "resume":  # a resume waits its turn in the queue
            _resuming(v, entry.get("max_iter"), entry.get("time_limit_s"))
        sessions = [str(s.get("started_utc", "")) for s in rec.get("sessions") or []
                    if isinstance(s, dict)]
        if (v.state is not AppJobState.QUEUED and last is not None
                and last.get("action") == "resume"
                and not _pid_alive(int(last["pid"]), last.get("utc"))
                and max(sessions, default="") < str(last.get("utc", ""))):
            if _cancelled_while_starting(entry, last):  # the run is as it was
                v.detail = "the resume was cancelled while starting; the run is as it was"
            else:  # a refused resume leaves the run as it was (its state and results stand):
                # only its log says why
                v.detail = f"the resume did not start: {_log_tail(f) or 'see job.log'}"
        v.still_improving = bool(results.get("still_improving"))
        note = results.get("with_fista_note")
        if isinstance(note, str) and note and v.state is AppJobState.FINISHED:
            # a cancel during the FISTA-TV at the end: "completed" without with_fista.tif
            v.detail = f"{v.detail}; {note}" if v.detail else note
        for which in ("final", "best", "mean", "with_fista"):
            r = results.get(which)
            if isinstance(r, str) and (f / RUN_DIR / r).is_file():
                v.results[which] = f / RUN_DIR / r
        return v
    if last is not None and _pid_alive(int(last["pid"]), last.get("utc")):
        v.state = AppJobState.STARTING
    elif last is not None and _cancelled_while_starting(entry, last):
        v.state = AppJobState.WITHDRAWN
        v.detail = "cancelled while starting, before its run began"
    elif last is not None:
        v.state = AppJobState.FAILED_TO_START
        v.detail = _log_tail(f)
    return v


def _limits_of(v: JobView, rec: dict[str, Any], results: dict[str, Any]) -> None:
    """The run's time limit, the limit it reached, and whether a resume starts from 0."""
    stopping = (rec.get("spec") or {}).get("stopping") or {}
    tl = stopping.get("time_limit_s") if isinstance(stopping, dict) else None
    v.time_limit_s = float(tl) if isinstance(tl, int | float) and tl > 0 else None
    reached = results.get("limit_reached")
    if reached is None and v.finish_reason == "completed":  # a record from before the field
        from recon.udn.jobs import _DETAIL

        for key in ("max_iter", "time_limit"):
            if str(v.detail or "").startswith(_DETAIL[key]):
                reached = key
    v.limit_reached = reached if reached in ("max_iter", "time_limit") else None
    rd = v.run_dir
    v.from_start = (rec.get("spec") is not None and not isinstance(rec.get("checkpoint"), dict)
                    and not (rd / "checkpoint.pt").exists()
                    and not (rd / "checkpoint.prev.pt").exists())


def _resuming(v: JobView, max_iter: Any, time_limit_s: Any = None) -> None:
    """Show a resume queued or starting as such.

    The run's last detail (cancelled, reached the limit ...) is no longer news, and its bar
    counts to the new limits.
    """
    from recon.udn.jobs import format_hms

    v.detail = (f"resuming from iteration {v.iteration}"
                + (f" to {int(max_iter)}" if isinstance(max_iter, int) else ""))
    if isinstance(time_limit_s, int | float) and time_limit_s > 0:
        v.detail += f" (time limit {format_hms(float(time_limit_s))})"
        v.time_limit_s = float(time_limit_s)
    v.finish_reason = None
    if isinstance(max_iter, int) and max_iter > 0:
        v.max_iter = max_iter


def _log_tail(folder: Path, n: int = 3) -> str:
    """The last ``n`` lines the job's last launch wrote to its log (after its ``---`` line).

    Not an earlier launch's: a refused resume showed the previous run's JSON summary.
    """
    try:
        lines = (folder / LOG).read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        return ""
    starts = [i for i, line in enumerate(lines) if line.startswith("--- ")]
    if starts:
        lines = lines[starts[-1] + 1:]
    return " | ".join(line for line in lines[-n:] if line.strip())


def discover_jobs(jobs_dir: str | Path) -> list[JobView]:
    """Every app job under ``jobs_dir``, oldest first."""
    root = Path(jobs_dir)
    if not root.is_dir():
        return []
    out = []
    for f in sorted(p for p in root.iterdir() if p.is_dir()):
        try:
            v = job_view(f)
        except (ValueError, KeyError, TypeError, AttributeError, IndexError) as exc:
            # one damaged job file must not hide (or stop) the others: shown, never run
            v = JobView(folder=f, name=f.name, device="?", state=AppJobState.FAILED_TO_START,
                        detail=f"{APP_JOB_FILE} unreadable ({type(exc).__name__}: {exc}); "
                               "the other jobs are not affected")
        if v is not None:
            out.append(v)
    return out


def combine_refusal(views: list[JobView], with_fista: bool = False) -> str | None:
    """Why ``views`` cannot be combined, found without reading a file (None: try it).

    An average needs two finished jobs, one with FISTA-TV (``with_fista``); the rest (same
    measurement, different seeds, inputs unchanged) is :func:`recon.udn.ensemble.combine_runs`'s
    to check. The jobs panel enables its Combine actions with this.
    """
    if not views:
        return "no job selected"
    not_done = [v.name for v in views if "best" not in v.results]
    if not_done:
        return f"not finished (no best estimate yet): {', '.join(not_done)}"
    if len(views) < 2 and not with_fista:
        return ("an ensemble needs at least two runs (or one run averaged with FISTA-TV: "
                "Combine > Average the seeds and FISTA-TV)")
    return None


def combine_jobs(views: list[JobView], jobs_dir: str | Path, with_fista: bool = False,
                 threads: int | None = None) -> Any:
    """Average the estimates of finished jobs of one measurement (an ensemble).

    Their best estimates; with ``with_fista`` their iterate means where every job has one
    (:func:`recon.udn.ensemble.combine_runs`'s ``auto``).

    Writes ``jobs_dir/ensembles/<time>-<name>-xN.tif`` (+ preview; ``-xN+fista.tif`` with
    ``with_fista``) through :func:`recon.udn.ensemble.combine_runs`, which refuses jobs of
    other data or the same seed; returns its :class:`~recon.udn.ensemble.EnsembleResult`.
    ``with_fista``: that average half and half with FISTA-TV (automatic tau) of the jobs' own
    inputs; one job is then enough. It takes seconds to a minute (the tau search): the panel
    runs it off the GUI thread.

    Torch runs it with the thread count of ``lenslesscam jobs combine``
    (:func:`recon.threads.choose_threads` of ``threads``; None: from the machine's cores and
    load), set while it runs and given back after (torch's count is the process's: the live
    preview shares it meanwhile): at torch's default count the app's FISTA-TV took 30-67 s
    where the command took 1.7 s on a loaded machine.
    """
    import torch

    from recon.threads import choose_threads
    from recon.udn.ensemble import combine_runs

    refusal = combine_refusal(views, with_fista)
    if refusal is not None:
        raise ValueError(refusal)
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    out_dir = Path(jobs_dir) / "ensembles"
    out_dir.mkdir(parents=True, exist_ok=True)
    name = views[0].name if views else "ensemble"
    tag = "+fista" if with_fista else ""
    out = out_dir / f"{stamp}-{_slug(name)}-x{len(views)}{tag}.tif"
    n = 1
    while out.exists():
        n += 1
        out = out_dir / f"{stamp}-{_slug(name)}-x{len(views)}{tag}-{n}.tif"
    before = torch.get_num_threads()
    torch.set_num_threads(choose_threads(threads).threads)
    try:
        return combine_runs([v.run_dir for v in views], out, with_fista=with_fista)
    finally:
        torch.set_num_threads(before)


def read_loss(folder: str | Path) -> tuple[Any, ...]:
    """(iterations, loss, held-out error, problem) from the run's ``loss.csv``.

    Empty arrays when there is none yet; ``problem`` is the reader's one-line message when the
    file cannot be read (damaged, or written by a newer lenslesscam), else None.
    """
    from recon.formats import FormatError
    from recon.udn.jobs import read_loss_rows

    its: list[float] = []
    loss: list[float] = []
    held: list[float] = []
    problem = None
    try:
        rows = read_loss_rows(Path(folder) / RUN_DIR)
    except FileNotFoundError:
        rows = []
    except (OSError, FormatError) as exc:
        rows, problem = [], str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    for row in rows:
        try:
            its.append(float(row["iteration"]))
            loss.append(float(row["loss"]))
            held.append(float(row["heldout"]) if row["heldout"] else np.nan)
        except ValueError:
            continue
    return np.array(its), np.array(loss), np.array(held), problem


def cancel_job(folder: str | Path) -> str:
    """Cancel a job: withdraw it from the queue, or ask its running process to stop."""
    f = Path(folder)
    entry = _read_json(f / APP_JOB_FILE) or {}
    if entry.get("state") in (AppJobState.QUEUED, AppJobState.HELD):
        if entry.get("action") == "resume" and (f / RUN_DIR / "run.json").is_file():
            # a resume waiting in the queue: drop it; the run stays as it was (its results,
            # resumable again)
            entry.update(state=AppJobState.LAUNCHED.value, action="run", max_iter=None)
            _write_entry(f, entry)
            return f"{f.name}: the queued resume is withdrawn; the run is as it was"
        entry["state"] = AppJobState.WITHDRAWN.value
        _write_entry(f, entry)
        return f"{f.name}: withdrawn from the queue"
    view = job_view(f)
    if view is not None and view.state is AppJobState.STARTING:
        return _cancel_starting(f, entry)
    from recon.udn.jobs import request_cancel

    return request_cancel(f / RUN_DIR)


def _cancel_starting(folder: Path, entry: dict[str, Any]) -> str:
    """Stop a job whose process started but whose run has not begun.

    The run refused a cancel then ('no UDN run here', or a resume's 'not running') and ran in
    full.

    SIGTERM to the launched process: before its handler is set it dies with nothing written
    (a resume leaves the run as it was); after, the run stops at its first iteration as a
    cancel does. The entry remembers it, so the job shows cancelled, not failed to start.
    """
    last = (entry.get("launches") or [{}])[-1]
    pid = int(last.get("pid", 0))
    if pid <= 0 or not _pid_alive(pid):
        raise ValueError(f"{folder.name}: the job's process is gone; nothing to cancel")
    entry["cancelled_launch"] = {"pid": pid, "utc": last.get("utc"), "at_utc": _now()}
    _write_entry(folder, entry)
    os.kill(pid, signal.SIGTERM)
    what = "resume" if last.get("action") == "resume" else "job"
    return f"{folder.name}: the {what} is cancelled while starting (SIGTERM to pid {pid})"


def _cancelled_while_starting(entry: dict[str, Any], last: dict[str, Any]) -> bool:
    """Whether the app cancelled this launch before its run began."""
    c = entry.get("cancelled_launch")
    return (isinstance(c, dict) and c.get("pid") == last.get("pid")
            and c.get("utc") == last.get("utc"))


def queue_resume(folder: str | Path, max_iter: int | None = None,
                 time_limit_s: float | None = None) -> None:
    """Queue a resume of a run (continues from its checkpoint), or a withdrawn job again.

    ``time_limit_s`` None: the job's :attr:`JobView.resume_time_limit_s` (a run that completed
    at its time limit still improving is continued with twice the time its detail advises;
    ``jobs resume`` refuses it without). A job withdrawn before its run began is queued to run.
    """
    f = Path(folder)
    entry = _read_json(f / APP_JOB_FILE)
    if entry is None:
        raise FileNotFoundError(f"{f}: not an app job")
    if not (f / RUN_DIR / "run.json").is_file():  # withdrawn before it ran: run it
        entry.update(state="queued", action="run", max_iter=None, time_limit_s=None)
        _write_entry(f, entry)
        return
    if time_limit_s is None:
        view = job_view(f)
        time_limit_s = None if view is None else view.resume_time_limit_s
    entry.update(state="queued", action="resume", max_iter=max_iter, time_limit_s=time_limit_s)
    _write_entry(f, entry)


def _key(device: str) -> str:
    """The queue's key of a job's device (:func:`device_key`; the text when it is unknown)."""
    try:
        return device_key(device)
    except (ValueError, RuntimeError):
        return device


class JobQueue:
    """Starts queued jobs, one at a time per device, and reports every job's state.

    ``spawn`` starts a job's process (default :func:`spawn_job_process`).
    """

    def __init__(self, jobs_dir: str | Path, spawn: Spawner = spawn_job_process) -> None:
        self.jobs_dir = Path(jobs_dir)
        self.spawn = spawn

    def poll(self) -> list[JobView]:
        """Reap finished children, start what may start, return every job's view."""
        for pid, proc in list(_CHILDREN.items()):
            if proc.poll() is not None:
                del _CHILDREN[pid]
        views = discover_jobs(self.jobs_dir)
        busy = {_key(v.device) for v in views if v.active}
        for v in views:
            if v.state is not AppJobState.QUEUED or _key(v.device) in busy:
                continue
            launched = self._launch_claimed(v.folder)
            if launched is None:
                continue
            if launched:
                busy.add(_key(v.device))
            nv = job_view(v.folder)
            if nv is not None:
                views[views.index(v)] = nv
        return views

    def _launch_claimed(self, folder: Path) -> bool | None:
        """Launch a queued job holding its claim (an OS lock on ``app-job.lock``).

        Two windows on one jobs folder both read a job queued and both launched it: the one
        that holds the claim reads the entry again and launches only if it is still queued.
        Returns whether a process was started, or None when another window holds the claim or
        launched it meanwhile (the view is then left as read).
        """
        import fcntl

        try:
            fd = os.open(folder / CLAIM, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except FileNotFoundError:  # the folder was deleted meanwhile
            return None
        except OSError as exc:  # not ours to write: it cannot start (as its log could not)
            entry = _read_json(folder / APP_JOB_FILE) or {}
            entry.update(state=AppJobState.FAILED_TO_START.value, error=str(exc))
            _write_entry(folder, entry)
            return False
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                return None  # another window is launching it
            entry = _read_json(folder / APP_JOB_FILE) or {}
            if entry.get("state") != AppJobState.QUEUED or _entry_problem(entry) is not None:
                return None
            action = str(entry.get("action", "run"))
            tl = entry.get("time_limit_s") if action == "resume" else None
            try:
                proc = _launch(folder, action, entry.get("max_iter"), self.spawn, tl)
            except OSError as exc:
                entry["state"] = AppJobState.FAILED_TO_START.value
                entry["error"] = str(exc)
                _write_entry(folder, entry)
                return False
            entry["state"] = AppJobState.LAUNCHED.value
            launch: dict[str, Any] = {"pid": proc.pid, "action": action, "utc": _now()}
            if action == "resume" and entry.get("max_iter") is not None:
                launch["max_iter"] = entry["max_iter"]
            if tl is not None:
                launch["time_limit_s"] = tl
            entry.setdefault("launches", []).append(launch)
            _write_entry(folder, entry)
            return True
        finally:
            os.close(fd)  # releases the claim

    @staticmethod
    def children() -> list[int]:
        """Pids of job processes this app process started and that still run."""
        return [pid for pid, p in _CHILDREN.items() if p.poll() is None]
