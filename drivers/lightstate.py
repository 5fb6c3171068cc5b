"""The lit state of a (simulated) point source, shared through a small JSON file.

The simulated firmware (:mod:`drivers.pointsource_sim`) writes its state here *before* it
acknowledges a command, atomically (temporary file + ``os.replace``), so a reader sees either
the old state or the new one. The simulated camera (:class:`drivers.simcam.SimulatedCamera`)
reads it at the start of every frame, so after the driver got ``OK`` for ``ON`` the next
frame is lit.

Strobe mode models the bench wiring: the camera's trigger output drives the source's trigger
input, so each frame's pulse starts ``strobe_delay_us`` after that frame's trigger and lasts
``strobe_duration_us``.

This module is imported by the firmware process; it must stay light (no numpy).
"""

from __future__ import annotations

import contextlib
import json
import os
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
    payload = dict(state.to_dict(), written_at=time.time(), pid=os.getpid())
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            json.dump(payload, fh)
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def read_light_state(path: str | os.PathLike[str]) -> LightState:
    """Read a state file; a missing or unreadable file gives a dark, unavailable state."""
    try:
        with open(path, encoding="utf-8") as fh:
            return LightState.from_dict(json.load(fh))
    except (OSError, ValueError, KeyError, TypeError):
        return LightState(available=False)


#: a state file is a few hundred bytes; anything much larger is some other file
_MAX_STATE_BYTES = 64 * 1024


def check_light_state_file(path: str | os.PathLike[str]) -> LightState:
    """The state in a light-state file a user names (one that :func:`write_light_state` wrote).

    That is JSON, format ``lenslesscam-light-state``, a version this release reads.
    :func:`read_light_state` takes any unreadable file as a dark source (a state file may be
    missing for a while); this is for a file a user names. Raises :class:`ValueError` with one
    line naming the file and what is wrong, :class:`FileNotFoundError` for a missing one.
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
        return LightState.from_dict(d)
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{what} (bad or missing field: {exc})") from None


@runtime_checkable
class LightStateSource(Protocol):
    """Anything the simulated camera can ask for the current light state."""

    def light_state(self) -> LightState:
        """The state now."""
        ...


class LightStateFile:
    """Reads a state file, re-parsing only when it changed (inode, mtime, size)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self._key: tuple[int, int, int] | None = None
        self._state = LightState(available=False)

    def light_state(self) -> LightState:
        """The state now (dark and unavailable while the file is missing)."""
        try:
            st = os.stat(self.path)
        except OSError:
            self._key = None
            self._state = LightState(available=False)
            return self._state
        key = (st.st_ino, st.st_mtime_ns, st.st_size)
        if key != self._key:
            self._state = read_light_state(self.path)
            self._key = key if self._state.available else None
        return self._state

    def __repr__(self) -> str:
        return f"LightStateFile({str(self.path)!r})"
