"""The lit state of a (simulated) point source, shared through a small JSON file.

The simulated firmware (:mod:`drivers.pointsource_sim`) writes its state here *before* it
acknowledges a command, atomically (temporary file + ``os.replace``), so a reader sees either
the old state or the new one. The simulated camera (:class:`drivers.simcam.SimulatedCamera`)
reads it at the start of every frame, so after the driver got ``OK`` for ``ON`` the next
frame is lit.

Strobe mode models the bench wiring: the camera's trigger output drives the source's trigger
input, so each frame's pulse starts ``strobe_delay_us`` after that frame's trigger and lasts
``strobe_duration_us``.

The file names its writer (``pid``, ``host`` and, on Linux, the process's start time
``pid_start``). A firmware that stops cleanly writes ``off`` as it exits, but one killed outright
(``kill -9``, a crash) cannot: its last state would stay lit for ever. So a reader on the same
host checks that the writer still runs (:func:`writer_running`); when it is gone the state reads
as dark and unavailable, as a missing file does.

This module is imported by the firmware process; it must stay light (no numpy).
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import socket
import tempfile
import time
from dataclasses import asdict, dataclass, replace
from enum import StrEnum
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

__all__ = [
    "LIGHT_STATE_FORMAT",
    "LightMode",
    "LightState",
    "LightStateFile",
    "LightStateSource",
    "check_light_state_file",
    "read_light_state",
    "write_light_state",
    "writer_running",
]

LIGHT_STATE_FORMAT = "lenslesscam-light-state"
LIGHT_STATE_VERSION = 1


class LightMode(StrEnum):
    """What the source emits."""

    OFF = "off"
    ON = "on"  # continuous
    STROBE = "strobe"  # one pulse per camera trigger


@dataclass(frozen=True)
class LightState:
    """Lit state: mode, intensity in [0, 1], strobe pulse, and a change counter.

    ``counter`` increases by one at every change the firmware applies; ``available`` is
    False when no state could be read (the source is then treated as dark).
    """

    mode: LightMode = LightMode.OFF
    intensity: float = 0.0
    strobe_delay_us: float = 0.0
    strobe_duration_us: float = 0.0
    counter: int = 0
    available: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "mode", LightMode(self.mode))

    @property
    def lit(self) -> bool:
        """Whether the source emits anything (on or strobing, intensity > 0)."""
        return self.mode is not LightMode.OFF and self.intensity > 0

    def evolve(self, **changes: Any) -> LightState:
        """A copy with ``changes`` applied and the counter incremented."""
        return replace(self, counter=self.counter + 1, **changes)

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form (format-versioned)."""
        d = asdict(self)
        d["mode"] = self.mode.value
        d.pop("available")
        return {"format": LIGHT_STATE_FORMAT, "format_version": LIGHT_STATE_VERSION, **d}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> LightState:
        """Inverse of :meth:`to_dict`."""
        if d.get("format") != LIGHT_STATE_FORMAT:
            raise ValueError(f"not a light state: format {d.get('format')!r}")
        return cls(
            mode=LightMode(d["mode"]),
            intensity=float(d["intensity"]),
            strobe_delay_us=float(d["strobe_delay_us"]),
            strobe_duration_us=float(d["strobe_duration_us"]),
            counter=int(d["counter"]),
        )


def write_light_state(path: str | os.PathLike[str], state: LightState) -> None:
    """Write ``state`` to ``path`` atomically (temporary file in the same folder + rename)."""
    target = Path(path)
    payload = dict(state.to_dict(), written_at=time.time(), pid=os.getpid(), host=_host(),
                   pid_start=_start_time(os.getpid()))
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            json.dump(payload, fh)
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _host() -> str:
    return socket.gethostname()


@functools.lru_cache(maxsize=8)
def _own_start_time(pid: int) -> int | None:
    return _read_start_time(pid)


def _start_time(pid: int) -> int | None:
    """Start time of process ``pid`` in clock ticks since boot (Linux ``/proc``), else None."""
    return _own_start_time(pid) if pid == os.getpid() else _read_start_time(pid)


def _read_start_time(pid: int) -> int | None:
    stat = _proc_stat(pid)
    if stat is None:
        return None
    try:
        return int(stat[19])  # field 22 of /proc/PID/stat; stat[0] is field 3
    except (IndexError, ValueError):
        return None


def _proc_stat(pid: int) -> list[str] | None:
    """The fields of ``/proc/PID/stat`` after the command name (state first), or None."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii", errors="replace") as fh:
            text = fh.read()
    except OSError:
        return None
    return text.rpartition(")")[2].split()


def writer_running(record: dict[str, Any]) -> bool:
    """Whether the process that wrote a state file (its ``pid``) still runs.

    Only a writer on this host can be checked (``host``); a file without a pid, or from another
    host, counts as running. A pid that no longer exists (``os.kill(pid, 0)``), a zombie (killed,
    not yet reaped) or a pid now used by a younger process (its start time differs from the
    ``pid_start`` recorded) is a writer that is gone.
    """
    pid = record.get("pid")
    if type(pid) is not int or pid <= 0 or os.name != "posix":  # (os.kill(pid, 0) kills on
        return True  # Windows; the simulated firmware runs on POSIX PTYs only)
    host = record.get("host")
    if host is not None and host != _host():
        return True
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # PermissionError: it exists, another user's
        return True
    stat = _proc_stat(pid)
    if stat is None:
        return True  # no /proc: os.kill said it exists
    if stat[:1] == ["Z"]:
        return False
    recorded = record.get("pid_start")
    return type(recorded) is not int or _start_time(pid) in (None, recorded)


def _read_record(path: str | os.PathLike[str]) -> tuple[LightState, dict[str, Any]]:
    """The state in a file and the file's record (dark and unavailable when unreadable)."""
    try:
        with open(path, encoding="utf-8") as fh:
            d = json.load(fh)
        return LightState.from_dict(d), d
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return LightState(available=False), {}


def read_light_state(path: str | os.PathLike[str]) -> LightState:
    """Read a state file.

    A missing or unreadable file, or one whose writer is gone (:func:`writer_running`), gives
    a dark, unavailable state.
    """
    state, record = _read_record(path)
    if state.available and not writer_running(record):
        return LightState(available=False)
    return state


#: a state file is a few hundred bytes; anything much larger is some other file
_MAX_STATE_BYTES = 64 * 1024


def check_light_state_file(path: str | os.PathLike[str]) -> LightState:
    """The state in a light-state file a user names (one that :func:`write_light_state` wrote).

    That is JSON, format ``lenslesscam-light-state``, a version this release reads.
    :func:`read_light_state` takes any unreadable file as a dark source (a state file may be
    missing for a while); this is for a file a user names. A valid file whose writer is gone
    (:func:`writer_running`) gives a dark, unavailable state (``available`` False). Raises
    :class:`ValueError` with one line naming the file and what is wrong,
    :class:`FileNotFoundError` for a missing one.
    """
    p = Path(path)
    what = f"{p} is not a light-state file of a simulated point source"
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file (the simulated source's state file)")
    if not p.is_file():
        raise ValueError(f"{what} (not a regular file)")
    if p.stat().st_size > _MAX_STATE_BYTES:
        raise ValueError(f"{what} ({p.stat().st_size} bytes; a state file is a small JSON file)")
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise ValueError(f"{what} (it is not text)") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{what} (not JSON: {exc.msg} at line {exc.lineno})") from None
    if not isinstance(d, dict) or d.get("format") != LIGHT_STATE_FORMAT:
        fmt = d.get("format") if isinstance(d, dict) else None
        raise ValueError(f"{what} (format {fmt!r}, expected {LIGHT_STATE_FORMAT!r})")
    version = d.get("format_version")
    if isinstance(version, float) and version.is_integer():  # 1.0 is 1, as for every file
        version = int(version)
    if type(version) is not int or not 1 <= version <= LIGHT_STATE_VERSION:
        raise ValueError(f"{p}: light-state format_version {version!r} is not one this "
                         f"release reads (1..{LIGHT_STATE_VERSION})")
    try:
        state = LightState.from_dict(d)
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{what} (bad or missing field: {exc})") from None
    return state if writer_running(d) else LightState(available=False)


@runtime_checkable
class LightStateSource(Protocol):
    """Anything the simulated camera can ask for the current light state."""

    def light_state(self) -> LightState:
        """The state now."""
        ...


class LightStateFile:
    """Reads a state file, re-parsing only when it changed (inode, mtime, size).

    Between changes it still checks, at every call, that the file's writer runs: a firmware
    killed outright leaves its last state behind unchanged, and that state must read as dark.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self._key: tuple[int, int, int] | None = None
        self._state = LightState(available=False)
        self._record: dict[str, Any] = {}

    def light_state(self) -> LightState:
        """The state now (dark and unavailable while the file is missing or its writer gone)."""
        try:
            st = os.stat(self.path)
        except OSError:
            self._key = None
            self._state = LightState(available=False)
            return self._state
        key = (st.st_ino, st.st_mtime_ns, st.st_size)
        if key != self._key:
            self._state, self._record = _read_record(self.path)
            self._key = key if self._state.available else None
        if self._state.available and not writer_running(self._record):
            return LightState(available=False)
        return self._state

    def __repr__(self) -> str:
        return f"LightStateFile({str(self.path)!r})"
