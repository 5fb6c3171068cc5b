"""The safety of a UDN run folder: one writer at a time, verified checkpoints, named faults.

- :class:`RunLock`: an OS file lock (``fcntl.flock`` on ``run.lock``) held by the process that
  writes the folder (``jobs run``, ``jobs resume``); the kernel releases it when that process
  ends, however it ends (SIGKILL included). A second writer is refused with
  :class:`RunFolderBusy`. The lock file also holds a small space reserve that is given back
  when the disk is full, so that the run record can still say what happened.
- :func:`write_checkpoint`: the checkpoint is serialised in memory, written to a temporary
  file, read back and checked (bytes against their SHA-256, then loaded), its hash is stored
  in ``checkpoints.json``, the newest checkpoint becomes ``checkpoint.prev.pt`` and the new one
  ``checkpoint.pt``. At every moment of this sequence both files that exist are complete.
- :func:`load_latest_checkpoint`: the newest checkpoint whose bytes match a stored hash and
  load; falls back to the previous one and says why.
- :func:`clean_temp_files`: temporary files of writes interrupted by a kill, removed when the
  next writer starts.
- :class:`DiskFull`: a full disk, named with the folder and what was being written.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import errno
import fcntl
import hashlib
import io
import json
import os
import platform
import re
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from recon.atomic import _umask_mode, atomic_write_json, fsync_dir, temp_files
from recon.formats import FORMAT_VERSION, FormatError, NewerFormat

__all__ = [
    "CHECKPOINT_FILE",
    "CHECKPOINT_FORMAT",
    "HASHES_FILE",
    "LOCK_FILE",
    "PREVIOUS_CHECKPOINT_FILE",
    "CheckpointError",
    "DiskFull",
    "JobError",
    "RunFolderBusy",
    "RunFolderGone",
    "RunLock",
    "clean_temp_files",
    "is_disk_full",
    "load_checkpoint",
    "load_latest_checkpoint",
    "write_checkpoint",
]

#: ``format`` of checkpoint.pt.
CHECKPOINT_FORMAT = "lenslesscam.udn_checkpoint"
#: ``format`` of checkpoints.json (the hashes of the checkpoints written).
HASHES_FORMAT = "lenslesscam.udn_checkpoint_hashes"

CHECKPOINT_FILE = "checkpoint.pt"
PREVIOUS_CHECKPOINT_FILE = "checkpoint.prev.pt"
HASHES_FILE = "checkpoints.json"
LOCK_FILE = "run.lock"
#: Bytes kept allocated in the lock file and released when the disk is full.
RESERVE_BYTES = 256 * 1024
#: Hashes kept in checkpoints.json (the new, the newest and the previous checkpoint).
_KEEP_HASHES = 3


class JobError(RuntimeError):
    """A job could not continue (the message says why and what is intact)."""


class RunFolderBusy(JobError):
    """Another process writes this run folder (it holds the run's lock).

    ``holder``: the holder's line from the lock file (``pid N on HOST since T``), or "" when
    it could not be read.
    """

    holder: str = ""


class RunFolderGone(JobError):
    """The run folder (or its lock file) was deleted or moved while the run wrote it.

    The run stops without writing anything more: its atomic writes would make the folder
    again (they create missing parent folders), a run nobody sees.
    """


class CheckpointError(JobError):
    """A checkpoint could not be written, verified or read."""


class DiskFull(JobError):
    """The disk (or the user's quota) is full; the message names the folder."""


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def is_disk_full(exc: BaseException | None) -> bool:
    """Whether ``exc`` (or an exception it was raised from) is a full disk or quota."""
    seen = 0
    while exc is not None and seen < 8:
        if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        if "No space left on device" in str(exc):
            return True
        exc = exc.__cause__ or exc.__context__
        seen += 1
    return False


# --------------------------------------------------------------------------------------------
# The lock
# --------------------------------------------------------------------------------------------


#: errno values of a lock another process holds
_BUSY = (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES)

HOLDER_WAIT_S = 1.0
"""How long a refused process waits for the holder's line (the holder writes it right after
taking the lock; an empty file means it is starting or releasing just then)."""


PROBE_GRACE_S = 0.25
"""How long a refused process tries the lock again before it reads the holder's line: a
status probe (:func:`lock_is_held`, which ``jobs status`` and the app's jobs panel call at
every poll) holds it for microseconds, and the line then read may be a dead holder's."""


def _retry_lock(fd: int, seconds: float) -> bool:
    """Try the exclusive lock again for up to ``seconds``; whether it was taken."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        time.sleep(0.01)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except OSError as exc:
            if exc.errno not in _BUSY:
                raise
    return False


def _wait_for_holder(fd: int) -> bytes | None:
    """After a refused flock: the holder's first line, or None if the lock came free.

    Polls for up to :data:`HOLDER_WAIT_S` while the file is empty, trying the lock again each
    time (a holder that was releasing leaves it free). Returns b"" if the file stays empty and
    the lock held.
    """
    deadline = time.monotonic() + HOLDER_WAIT_S
    while True:
        holder = b""
        with contextlib.suppress(OSError):
            holder = os.pread(fd, 200, 0).split(b"\n")[0].strip(b"\0 ")
        if holder:
            return holder
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return None  # free now
        except OSError as exc:
            if exc.errno not in _BUSY:
                raise
        if time.monotonic() >= deadline:
            return b""
        time.sleep(0.02)


def lock_holder(run_dir: str | Path) -> tuple[int | None, str] | None:
    """The process holding the run folder's lock: (pid, its line), or None when none does.

    The pid comes from the holder's own line in the lock file (``pid N on HOST since T``,
    written by :meth:`RunLock.acquire`); None in the tuple when the line cannot be read yet.
    A momentary probe, as :func:`lock_is_held`.
    """
    if not lock_is_held(run_dir):
        return None
    try:
        line = (Path(run_dir) / LOCK_FILE).read_bytes()[:200].decode("utf-8", "replace")
    except OSError:
        return (None, "")
    m = re.match(r"pid (\d+) on (\S+)", line)
    if m is None or m.group(2) != platform.node():
        return (None, line.strip())
    return (int(m.group(1)), line.strip())


def lock_is_held(run_dir: str | Path) -> bool:
    """Whether some process holds the run folder's lock now.

    A momentary probe: it takes a shared lock and gives it back at once. A writer that
    starts just then tries again for :data:`PROBE_GRACE_S` before it is refused, so a status
    poll (``jobs status``, the app's jobs panel) never turns a start away.
    """
    path = Path(run_dir) / LOCK_FILE
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError as exc:
        if exc.errno in _BUSY:
            return True
        raise
    finally:
        os.close(fd)  # closing releases a lock taken here
    return False


class RunLock:
    """Exclusive OS lock on a run folder (``RUN_DIR/run.lock``), released by the kernel.

    Use as a context manager or with :meth:`acquire` / :meth:`release`. The lock file stays
    in the folder (removing it would let two processes lock two different files). ``name``:
    another lock file in the folder, for a writer that is not a UDN job (``trade`` takes
    ``trade.lock``, so that its refusal and a job's never name each other).
    """

    def __init__(self, run_dir: str | Path, name: str = LOCK_FILE) -> None:
        self.run_dir = Path(run_dir)
        self.path = self.run_dir / name
        self._fd: int | None = None
        self._holder = b""

    @property
    def held(self) -> bool:
        """Whether this object holds the lock."""
        return self._fd is not None

    def acquire(self) -> RunLock:
        """Take the lock or raise :class:`RunFolderBusy` naming the holder."""
        if self._fd is not None:
            return self
        self.run_dir.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                if exc.errno not in _BUSY:
                    raise
                holder = None if _retry_lock(fd, PROBE_GRACE_S) else _wait_for_holder(fd)
                if holder is not None:
                    who = holder.decode("utf-8", "replace").strip() or "another process"
                    busy = RunFolderBusy(
                        f"{self.run_dir} is in use ({who}): one process at a time may write a "
                        f"run folder; wait for it to end, or stop it with 'lenslesscam jobs "
                        f"cancel {self.run_dir}'")
                    busy.holder = holder.decode("utf-8", "replace").strip()
                    raise busy from None
        except BaseException:
            os.close(fd)
            raise
        self._fd = fd
        self._holder = f"pid {os.getpid()} on {platform.node()} since {_now()}\n".encode()
        with contextlib.suppress(OSError):  # informative only; never fails the run
            # Write the holder line before cutting the old contents (after a crash they are
            # the dead holder's line); a process refused before this write waits for it.
            os.pwrite(fd, self._holder, 0)
            os.ftruncate(fd, len(self._holder))
            os.posix_fallocate(fd, 0, RESERVE_BYTES)
        return self

    def intact(self) -> bool:
        """Whether the lock file is still in its folder, the file this lock holds.

        False once the run folder was deleted (the file unlinked), moved or replaced: the
        writer must stop (:class:`RunFolderGone`). Two ``stat`` calls; True when not held.
        """
        if self._fd is None:
            return True
        try:
            held = os.fstat(self._fd)
            now = os.stat(self.path)
        except OSError:
            return False
        return held.st_nlink > 0 and (held.st_dev, held.st_ino) == (now.st_dev, now.st_ino)

    def release_reserve(self) -> None:
        """Give the reserved space back to the file system (on a full disk)."""
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.ftruncate(self._fd, len(self._holder))

    def release(self) -> None:
        """Drop the lock (the file stays, emptied of its reserve)."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        with contextlib.suppress(OSError):
            os.ftruncate(fd, 0)
        with contextlib.suppress(OSError):
            fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)

    def __enter__(self) -> RunLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


def clean_temp_files(run_dir: str | Path, subdirs: tuple[str, ...] = ("previews",)) -> list[str]:
    """Remove temporary files left by writes that a kill interrupted; their relative names.

    Call only while holding the run's lock (no writer is active then).
    """
    rd = Path(run_dir)
    removed: list[str] = []
    for folder in (rd, *(rd / s for s in subdirs)):
        for p in temp_files(folder):
            with contextlib.suppress(FileNotFoundError):
                p.unlink()
                removed.append(p.relative_to(rd).as_posix())
    return removed


# --------------------------------------------------------------------------------------------
# Checkpoints
# --------------------------------------------------------------------------------------------


def _newer(what: str) -> NewerFormat:
    """The refusal of a run file a newer release wrote (``what``: the file and its version)."""
    return NewerFormat(f"{what} was written by a newer lenslesscam (this release reads "
                       f"{FORMAT_VERSION}): resume the run with that release; nothing was changed")


def _check_payload(ck: Any, where: str) -> dict[str, Any]:
    if not isinstance(ck, dict) or ck.get("format") != CHECKPOINT_FORMAT:
        raise FormatError(f"{where} is not a UDN checkpoint")
    v = ck.get("format_version", 0)
    if not isinstance(v, int):
        raise FormatError(f"{where}: checkpoint version {v!r} is not a version number")
    if v > FORMAT_VERSION:
        raise _newer(f"{where}: checkpoint version {v}")
    if not isinstance(ck.get("iteration"), int) or not isinstance(ck.get("state"), dict):
        raise FormatError(f"{where}: the checkpoint lacks its iteration or state")
    return ck


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return (text[0] if text else type(exc).__name__)[:200]


def _load_bytes(data: bytes, where: str, *, trusted: bool = False) -> dict[str, Any]:
    """Deserialise a checkpoint; ``trusted``: bytes this process has just serialised."""
    try:
        # A file from disk goes through the safe loader (tensors and plain data only). Bytes
        # this process serialised a moment ago (their hash checked) cannot hold anything else,
        # and the full unpickler reads them 3x faster.
        ck = torch.load(io.BytesIO(data), map_location="cpu", weights_only=not trusted)
    except Exception as exc:  # torch reports a damaged zip in many ways (RuntimeError, ...)
        raise FormatError(f"{where}: truncated or corrupt checkpoint ({len(data)} bytes; torch "
                          f"says: {_first_line(exc)})") from None
    return _check_payload(ck, where)


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read one checkpoint file (safe loader: tensors and plain data only); one-line errors."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no checkpoint")
    return _load_bytes(p.read_bytes(), str(p))


def _read_hashes(run_dir: Path) -> tuple[list[dict[str, Any]] | None, str | None]:
    """The recorded checkpoint hashes (None when there is no file) and a problem, if any."""
    p = run_dir / HASHES_FILE
    if not p.is_file():
        return None, None
    try:
        obj = json.loads(p.read_text(encoding="utf-8"))
        v = obj.get("format_version") if isinstance(obj, dict) else None
        if isinstance(v, int) and v > FORMAT_VERSION:
            raise _newer(f"{p}: format_version {v}")
        entries = obj["checkpoints"]
        if obj.get("format") != HASHES_FORMAT or not isinstance(entries, list) or not all(
                isinstance(e, dict) and isinstance(e.get("sha256"), str)
                and isinstance(e.get("iteration"), int) for e in entries):
            raise ValueError("unexpected content")
    except NewerFormat:
        raise
    except (OSError, ValueError, KeyError, TypeError) as exc:
        return None, f"{HASHES_FILE} is unreadable ({_first_line(exc)}); checkpoints unverified"
    return entries, None


def write_checkpoint(run_dir: str | Path, ck: dict[str, Any]) -> dict[str, Any]:
    """Write ``ck`` as the newest checkpoint, verified, keeping the previous one.

    Returns ``{"path", "iteration", "sha256", "bytes", "written_utc", "previous"}`` for the
    run record. Raises :class:`DiskFull` or :class:`CheckpointError`; then no temporary file is
    left and the checkpoints already there are untouched.
    """
    rd = Path(run_dir)
    it = int(ck["iteration"])
    buf = io.BytesIO()
    torch.save(ck, buf)
    data = buf.getvalue()
    sha = hashlib.sha256(data).hexdigest()
    target = rd / CHECKPOINT_FILE
    fd, tmp_name = tempfile.mkstemp(prefix=f".{CHECKPOINT_FILE}.", suffix=".tmp", dir=rd)
    tmp = Path(tmp_name)
    try:
        with os.fdopen(fd, "wb") as fh:
            _write_bytes(fh, data)
            fh.flush()
            os.fsync(fh.fileno())
        _verify(tmp, sha, it)
        os.chmod(tmp, _umask_mode())  # mkstemp made it 0600
        entries, _ = _read_hashes(rd)
        kept = [e for e in (entries or []) if e.get("sha256") != sha]
        new = {"sha256": sha, "iteration": it, "bytes": len(data), "written_utc": _now()}
        atomic_write_json(rd / HASHES_FILE, {
            "format": HASHES_FORMAT, "format_version": FORMAT_VERSION,
            "checkpoints": [new, *kept][:_KEEP_HASHES]})
        _rotate(rd)
        os.replace(tmp, target)
        fsync_dir(rd)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        if isinstance(exc, OSError) and is_disk_full(exc):
            raise DiskFull(f"disk full: no space left on the device of {rd} while writing the "
                           f"checkpoint of iteration {it}") from exc
        if isinstance(exc, (OSError, FormatError)):
            raise CheckpointError(f"could not write the checkpoint of iteration {it} in {rd}: "
                                  f"{_first_line(exc)}") from exc
        raise
    prev = None
    if (rd / PREVIOUS_CHECKPOINT_FILE).is_file() and kept:
        prev = {"path": PREVIOUS_CHECKPOINT_FILE, "iteration": kept[0]["iteration"],
                "sha256": kept[0]["sha256"]}
    return {"path": CHECKPOINT_FILE, "iteration": it, "sha256": sha, "bytes": len(data),
            "written_utc": new["written_utc"], "previous": prev}


def _write_bytes(fh: Any, data: bytes) -> None:
    """Write the serialised checkpoint (one function, so that tests can slow it down)."""
    fh.write(data)


def _verify(path: Path, sha: str, iteration: int) -> None:
    """Read a written checkpoint back: its bytes hash to ``sha`` and it loads."""
    data = path.read_bytes()
    if hashlib.sha256(data).hexdigest() != sha:
        raise FormatError(f"{path.name}: the bytes read back differ from those written")
    ck = _load_bytes(data, path.name, trusted=True)
    if ck["iteration"] != iteration:
        raise FormatError(f"{path.name}: read back iteration {ck['iteration']}, "
                          f"wrote {iteration}")


def _rotate(rd: Path) -> None:
    """The newest checkpoint becomes the previous one; ``checkpoint.pt`` stays in place.

    A hard link keeps ``checkpoint.pt`` present throughout (where links are not supported,
    the file is renamed: for an instant only the previous checkpoint exists).
    """
    cur = rd / CHECKPOINT_FILE
    if not cur.is_file():
        return
    fd, link_name = tempfile.mkstemp(prefix=f".{PREVIOUS_CHECKPOINT_FILE}.", suffix=".tmp",
                                     dir=rd)
    os.close(fd)
    link = Path(link_name)
    try:
        link.unlink()
        os.link(cur, link)
    except OSError:
        with contextlib.suppress(FileNotFoundError):
            link.unlink()
        os.replace(cur, rd / PREVIOUS_CHECKPOINT_FILE)
        return
    try:
        os.replace(link, rd / PREVIOUS_CHECKPOINT_FILE)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            link.unlink()
        raise


def load_latest_checkpoint(run_dir: str | Path
                           ) -> tuple[dict[str, Any] | None, dict[str, Any], list[str]]:
    """The newest usable checkpoint of a run folder.

    Returns ``(checkpoint or None, info, problems)``: ``info`` names the file, iteration and
    hash and whether the hash was verified; ``problems`` lists, one line each, every newer
    checkpoint that was passed over and why (missing, truncated, corrupt, hash mismatch).
    """
    rd = Path(run_dir)
    entries, problem = _read_hashes(rd)
    problems = [problem] if problem else []
    known = {e["sha256"]: e["iteration"] for e in entries or []}
    for name in (CHECKPOINT_FILE, PREVIOUS_CHECKPOINT_FILE):
        p = rd / name
        if not p.is_file():
            if name == CHECKPOINT_FILE:
                problems.append(f"{name} is missing")
            continue
        try:
            data = p.read_bytes()
        except OSError as exc:
            problems.append(f"{name} cannot be read ({_first_line(exc)})")
            continue
        sha = hashlib.sha256(data).hexdigest()
        if entries is not None and sha not in known:
            problems.append(f"{name} does not match its recorded hash (truncated or corrupt, "
                            f"{len(data)} bytes)")
            continue
        try:
            ck = _load_bytes(data, name)
        except NewerFormat:
            raise  # not damaged: a newer release's, which must neither be passed over nor lost
        except FormatError as exc:
            problems.append(str(exc))
            continue
        if entries is not None and known[sha] != ck["iteration"]:
            problems.append(f"{name}: iteration {ck['iteration']} differs from the recorded "
                            f"{known[sha]}")
            continue
        info = {"path": name, "iteration": int(ck["iteration"]), "sha256": sha,
                "verified": entries is not None}
        return ck, info, problems
    return None, {}, problems
