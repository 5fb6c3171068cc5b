"""Light sources: the :class:`LightSource` protocol and the serial point-source driver.

:class:`SerialPointSource` *has* a serial port (composition): give it a port URL/path (it
opens the port with pyserial) or an already-open pyserial-like object. It speaks the
line-based text protocol of ``docs/serial-protocol.md``:

- every command goes out tagged (``@17 ON``) and only the reply with the same tag counts, so
  a late reply to an earlier, timed-out command can never be taken for the current one;
- each attempt has ``timeout_s``; idempotent commands (all setters and queries except
  ``ERR?``, which pops the device's error queue) are retried ``retries`` more times after a
  timeout or a garbled reply; an ``ERR`` reply is never retried;
- if the port vanishes mid-command (the device unplugged, the simulator killed) the driver
  raises :class:`LightSourceDisconnected` at once, closes the port and refuses further
  commands until :meth:`SerialPointSource.reconnect`;
- the cached state (``is_on``, ``intensity``, strobe) changes only after an ``OK``; after a
  failed setter ``in_sync`` is False until :meth:`SerialPointSource.status` or
  :meth:`SerialPointSource.reconnect` reads the device again.
- a port given by path is opened exclusively (pyserial ``exclusive=True``, an advisory
  ``flock`` on POSIX): a second process opening the same source would read the first one's
  replies and corrupt its exchanges, so it is refused with :class:`LightSourceBusy`
  ("port X is in use by another process");
- strobe times go out with 0.1 us resolution (:data:`TIME_RESOLUTION_US`): a pulse shorter
  than that would be sent as 0 and is refused before anything is sent.

Public methods validate and clip (``intensity`` to [0, 1]); private ``_do_...`` methods talk
to the hardware.
"""

from __future__ import annotations

import errno
import logging
import math
import numbers
import re
import threading
import time
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Protocol, Self, runtime_checkable

from drivers.lightstate import LightMode

__all__ = [
    "TIME_RESOLUTION_US",
    "DeviceError",
    "LightSource",
    "LightSourceBusy",
    "LightSourceDisconnected",
    "LightSourceError",
    "LightSourceProtocolError",
    "LightSourceStatus",
    "LightSourceTimeout",
    "SerialPointSource",
]

_log = logging.getLogger(__name__)

MAX_TIME_US = 10_000_000.0
#: strobe delays and durations are sent with one decimal (``STROBE 120.0 30.0``)
TIME_RESOLUTION_US = 0.1


def _port_errors() -> tuple[type[BaseException], ...]:
    """Every exception a vanished port can raise: pyserial's, OS errors, and ``termios.error``.

    ``termios.error`` (raised by ``reset_input_buffer``/``flush`` on a PTY whose other end died)
    is not an ``OSError``; unless it is mapped here it escapes as a raw error and the port is
    never dropped.
    """
    import serial

    errors: tuple[type[BaseException], ...] = (serial.SerialException, OSError)
    try:
        import termios
    except ImportError:  # Windows: no termios
        return errors
    return (*errors, termios.error)


class LightSourceError(RuntimeError):
    """A light source could not do what was asked (the message says which and why)."""


class LightSourceTimeout(LightSourceError, TimeoutError):
    """No (complete) reply within the timeout, after all retries."""


class LightSourceProtocolError(LightSourceError):
    """A reply that does not follow the protocol (garbled line), after all retries."""


class LightSourceDisconnected(LightSourceError):
    """The port vanished (or was never opened); call ``reconnect()``."""


class LightSourceBusy(LightSourceDisconnected):
    """The port is held (exclusively) by another process: another driver, the app, a tool."""


class DeviceError(LightSourceError):
    """The device answered ``ERR code message``."""

    def __init__(self, code: int, message: str, command: str, device: str) -> None:
        self.code = code
        self.message = message
        self.command = command
        super().__init__(f"{device}: '{command}' failed: error {code}: {message}")


@dataclass(frozen=True)
class LightSourceStatus:
    """What the device reported (``in_sync``: the driver's cache agrees with it)."""

    mode: LightMode
    intensity: float
    strobe_delay_us: float
    strobe_duration_us: float
    counter: int
    identity: str
    in_sync: bool = True

    @property
    def is_on(self) -> bool:
        """Whether the source emits (continuous or strobed)."""
        return self.mode is not LightMode.OFF


@runtime_checkable
class LightSource(Protocol):
    """What every light source offers."""

    @property
    def is_open(self) -> bool:
        """Whether the connection is open."""
        ...

    def open(self) -> None:
        """Connect (idempotent)."""
        ...

    def close(self) -> None:
        """Disconnect (idempotent)."""
        ...

    def __enter__(self) -> Self:
        """Open and return self."""
        ...

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        """Close."""
        ...

    def on(self) -> None:
        """Continuous light."""
        ...

    def off(self) -> None:
        """No light (also disarms the strobe)."""
        ...

    @property
    def is_on(self) -> bool | None:
        """Last confirmed state (None before the first confirmation)."""
        ...

    @property
    def intensity(self) -> float | None:
        """Last confirmed intensity in [0, 1]."""
        ...

    def set_intensity(self, value: float) -> float:
        """Validate, clip to [0, 1], apply; return the applied value."""
        ...

    def strobe(self, delay_us: float, duration_us: float) -> None:
        """Arm strobe mode: one pulse of ``duration_us`` ``delay_us`` after each trigger."""
        ...

    def identify(self) -> str:
        """Vendor, model, serial number, firmware version."""
        ...

    def status(self) -> LightSourceStatus:
        """Read the state from the device."""
        ...

    def errors(self) -> list[tuple[int, str]]:
        """Drain the device's error queue (oldest first)."""
        ...


def _open_failure(exc: BaseException) -> str:
    """Why a port did not open, said once.

    pyserial wraps the system's error in its own message that names the port again
    ("[Errno 2] could not open port X: [Errno 2] No such file or directory: 'X'"); the
    system's reason is what the user needs.
    """
    inner = exc.__cause__ or exc.__context__
    if isinstance(inner, OSError) and inner.strerror:
        return inner.strerror
    if inner is not None and type(inner).__name__ == "error" and len(inner.args) == 2:
        return f"not a serial port ({inner.args[1]})"  # termios.error: a file, /dev/null
    return str(exc)


_STATE_RE = re.compile(
    r"mode=(\w+) int=([-\d.]+) delay_us=([-\d.]+) duration_us=([-\d.]+) counter=(\d+)"
)


class SerialPointSource:
    """Serial point source speaking the ``docs/serial-protocol.md`` protocol."""

    def __init__(
        self,
        port: str | Any,
        *,
        baudrate: int = 115_200,
        timeout_s: float = 0.5,
        retries: int = 2,
    ) -> None:
        if not (math.isfinite(timeout_s) and timeout_s > 0):
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        if int(retries) != retries or retries < 0:
            raise ValueError(f"retries must be an integer >= 0, got {retries!r}")
        if isinstance(port, str):
            self._url: str | None = port
            self._port: Any = None
        else:
            self._url = None
            self._port = port
        self.baudrate = int(baudrate)
        self.timeout_s = float(timeout_s)
        self.retries = int(retries)
        self._lock = threading.RLock()
        self._seq = 0
        self._connected = False
        self._identity = ""
        self._mode: LightMode | None = None
        self._intensity: float | None = None
        self._strobe: tuple[float, float] | None = None
        self._in_sync = False

    def describe(self) -> str:
        """Device description for messages."""
        where = self._url or getattr(self._port, "port", None) or "port object"
        return f"point source on {where}"

    def __repr__(self) -> str:
        return f"<SerialPointSource {self.describe()} {'open' if self._connected else 'closed'}>"

    # -- connection ----------------------------------------------------------------------------

    @property
    def is_open(self) -> bool:
        """Whether the port is open and the device answered."""
        return self._connected

    def open(self) -> None:
        """Open the port, check the device answers, read its state."""
        with self._lock:
            if self._connected:
                return
            self._open_port()
            self._connected = True
            try:
                self._identity = self._transact("IDN?")
                self._refresh()
            except LightSourceError:
                self._drop_port()
                raise

    def _open_port(self) -> None:
        import serial

        try:
            if self._url is not None:
                # exclusive: a second opener would take the first one's replies (POSIX flock;
                # pyserial's URL handlers such as loop:// accept and ignore it)
                self._port = serial.serial_for_url(
                    self._url, baudrate=self.baudrate, timeout=self.timeout_s, exclusive=True
                )
            elif not self._port.is_open:
                self._port.open()
        except (*_port_errors(), ValueError) as exc:
            self._port = None if self._url is not None else self._port
            if getattr(exc, "errno", None) in (errno.EAGAIN, errno.EWOULDBLOCK) \
                    and "lock" in str(exc).lower():  # pyserial's flock(LOCK_EX | LOCK_NB)
                where = self._url or getattr(self._port, "port", None) or "port object"
                raise LightSourceBusy(f"port {where} is in use by another process (close the "
                                      "other connection to the point source first)") from exc
            raise LightSourceDisconnected(
                f"cannot open {self.describe()}: {_open_failure(exc)}") from exc

    def _drop_port(self) -> None:
        self._connected = False
        self._in_sync = False
        port = self._port
        if port is not None:
            try:
                port.close()
            except Exception as exc:  # the port is already gone; nothing else to do
                _log.debug("%s: closing a vanished port: %s", self.describe(), exc)
        if self._url is not None:
            self._port = None

    def close(self) -> None:
        """Close the port (the device keeps its state)."""
        with self._lock:
            self._drop_port()

    def reconnect(self, port: str | None = None) -> None:
        """Close and reopen (optionally another ``port`` path), then re-read the state."""
        with self._lock:
            self._drop_port()
            if port is not None:
                self._url, self._port = port, None
            self.open()

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- the wire ------------------------------------------------------------------------------

    def command(self, line: str, *, idempotent: bool = False) -> str:
        """Send a raw protocol command; return the ``OK`` payload (for tools and tests)."""
        return self._transact(line, idempotent=idempotent)

    def _transact(self, command: str, *, idempotent: bool = True) -> str:
        port_errors = _port_errors()
        if "\n" in command or "\r" in command or not command.isascii():
            raise ValueError(f"invalid command {command!r}")
        with self._lock:
            if not self._connected or self._port is None:
                raise LightSourceDisconnected(f"{self.describe()} is not connected (reconnect())")
            attempts = 1 + (self.retries if idempotent else 0)
            failure: LightSourceError | None = None
            for attempt in range(1, attempts + 1):
                self._seq = (self._seq + 1) % 1_000_000
                tag = str(self._seq)
                try:
                    self._port.reset_input_buffer()
                    self._port.write(f"@{tag} {command}\n".encode("ascii"))
                    self._port.flush()
                    return self._parse(command, self._read_reply(tag))
                except (LightSourceTimeout, LightSourceProtocolError) as exc:
                    # (before OSError: LightSourceTimeout is a TimeoutError, an OSError)
                    failure = exc
                    _log.info(
                        "%s: '%s' attempt %d/%d: %s",
                        self.describe(),
                        command,
                        attempt,
                        attempts,
                        exc,
                    )
                except LightSourceError:
                    raise
                except port_errors as exc:
                    self._drop_port()
                    raise LightSourceDisconnected(
                        f"{self.describe()}: port vanished during '{command}': {exc}"
                    ) from exc
            assert failure is not None
            tries = f"{attempts} attempt{'s' if attempts > 1 else ''}"
            raise type(failure)(f"{failure} ({tries})") from failure

    def _read_reply(self, tag: str) -> str:
        deadline = time.monotonic() + self.timeout_s
        buf = b""
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                what = f"partial reply {buf!r}" if buf else "no reply"
                raise LightSourceTimeout(f"{self.describe()}: {what} within {self.timeout_s:.3g} s")
            self._port.timeout = remaining
            buf += self._port.read_until(b"\n")
            if not buf.endswith(b"\n"):
                continue
            raw, buf = buf, b""
            try:
                line = raw.decode("ascii").strip()
            except UnicodeDecodeError:
                raise LightSourceProtocolError(
                    f"{self.describe()}: garbled reply {raw!r}"
                ) from None
            if not line:
                continue
            if line.startswith("@"):
                got, _, rest = line[1:].partition(" ")
                if got == tag:
                    return str(rest)
                _log.debug("%s: dropping stale reply %r", self.describe(), line)
                continue
            if line.startswith("READY"):
                _log.info("%s: device restarted (%s)", self.describe(), line)
                self._in_sync = False
                continue
            raise LightSourceProtocolError(f"{self.describe()}: garbled reply {line!r}")

    def _parse(self, command: str, reply: str) -> str:
        if reply == "OK" or reply.startswith("OK "):
            return reply[3:].strip()
        if reply.startswith("ERR "):
            parts = reply.split(" ", 2)
            try:
                code = int(parts[1])
            except (IndexError, ValueError):
                raise LightSourceProtocolError(
                    f"{self.describe()}: malformed error reply {reply!r}"
                ) from None
            raise DeviceError(code, parts[2] if len(parts) > 2 else "", command, self.describe())
        raise LightSourceProtocolError(f"{self.describe()}: unexpected reply {reply!r}")

    def _setter(self, command: str) -> str:
        """A state-changing command: on any failure the cache is marked out of sync."""
        try:
            return self._transact(command)
        except LightSourceError:
            self._in_sync = False
            raise

    # -- state ---------------------------------------------------------------------------------

    @property
    def in_sync(self) -> bool:
        """False after a setter failed in a way that may have left the device changed."""
        return self._in_sync

    @property
    def mode(self) -> LightMode | None:
        """Last confirmed mode."""
        return self._mode

    @property
    def is_on(self) -> bool | None:
        """Last confirmed on/off (strobe counts as on)."""
        return None if self._mode is None else self._mode is not LightMode.OFF

    @property
    def intensity(self) -> float | None:
        """Last confirmed intensity."""
        return self._intensity

    @intensity.setter
    def intensity(self, value: float) -> None:
        self.set_intensity(value)

    @property
    def strobe_settings(self) -> tuple[float, float] | None:
        """Last confirmed (delay_us, duration_us)."""
        return self._strobe

    def _refresh(self) -> LightSourceStatus:
        payload = self._transact("STATE?")
        m = _STATE_RE.fullmatch(payload)
        if m is None:
            raise LightSourceProtocolError(f"{self.describe()}: bad STATE? reply {payload!r}")
        st = LightSourceStatus(
            mode=LightMode(m.group(1)),
            intensity=float(m.group(2)),
            strobe_delay_us=float(m.group(3)),
            strobe_duration_us=float(m.group(4)),
            counter=int(m.group(5)),
            identity=self._identity,
        )
        self._mode = st.mode
        self._intensity = st.intensity
        self._strobe = (st.strobe_delay_us, st.strobe_duration_us)
        self._in_sync = True
        return st

    # -- public commands (validate, then _do_...) ------------------------------------------------

    def on(self) -> None:
        """Continuous light at the set intensity."""
        self._do_on()

    def off(self) -> None:
        """Light off (strobe disarmed)."""
        self._do_off()

    def set_intensity(self, value: float) -> float:
        """Validate (a real number, not NaN), clip to [0, 1], apply; return the applied value."""
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise TypeError(f"intensity must be a real number, got {type(value).__name__}")
        v = float(value)
        if math.isnan(v):
            raise ValueError("intensity must not be NaN")
        clipped = min(1.0, max(0.0, v))
        if clipped != v:
            _log.info("%s: intensity %r clipped to %r", self.describe(), value, clipped)
        return self._do_set_intensity(clipped)

    def strobe(self, delay_us: float, duration_us: float) -> None:
        """Arm strobe mode: a pulse of ``duration_us`` starting ``delay_us`` after each trigger."""
        for name, v in (("delay_us", delay_us), ("duration_us", duration_us)):
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v):
                raise ValueError(f"strobe {name} must be a finite number, got {v!r}")
        if not 0 <= delay_us <= MAX_TIME_US:
            raise ValueError(f"strobe delay_us {delay_us} outside [0, {MAX_TIME_US:g}]")
        if not 0 < duration_us <= MAX_TIME_US:
            raise ValueError(f"strobe duration_us {duration_us} outside (0, {MAX_TIME_US:g}]")
        if round(duration_us, 1) < TIME_RESOLUTION_US:  # it would go out as 0.0
            raise ValueError(f"strobe duration_us {duration_us:g} is shorter than the source's "
                             f"{TIME_RESOLUTION_US:g} us resolution (it would be sent as 0)")
        self._do_strobe(float(delay_us), float(duration_us))

    def identify(self) -> str:
        """``vendor,model,serial,firmware`` as the device reports it."""
        self._identity = self._transact("IDN?")
        return self._identity

    def status(self) -> LightSourceStatus:
        """Read the device's state (and bring the cache in sync)."""
        with self._lock:
            return self._refresh()

    def errors(self) -> list[tuple[int, str]]:
        """Drain the device's error queue, oldest first (``ERR?`` is never retried)."""
        out: list[tuple[int, str]] = []
        for _ in range(32):
            payload = self._transact("ERR?", idempotent=False)
            code_s, _, msg = payload.partition(" ")
            code = int(code_s) if code_s.isdigit() else -1
            if code == 0:
                break
            out.append((code, msg))
        return out

    # -- hardware side ---------------------------------------------------------------------------

    def _do_on(self) -> None:
        with self._lock:
            self._setter("ON")
            self._mode = LightMode.ON

    def _do_off(self) -> None:
        with self._lock:
            self._setter("OFF")
            self._mode = LightMode.OFF

    def _do_set_intensity(self, value: float) -> float:
        with self._lock:
            payload = self._setter(f"INT {value:.4f}")
            try:
                applied = float(payload)
            except ValueError:
                self._in_sync = False
                raise LightSourceProtocolError(
                    f"{self.describe()}: bad INT reply {payload!r}"
                ) from None
            self._intensity = applied
            return applied

    def _do_strobe(self, delay_us: float, duration_us: float) -> None:
        with self._lock:
            payload = self._setter(f"STROBE {delay_us:.1f} {duration_us:.1f}")
            parts = payload.split()
            if len(parts) != 2:
                self._in_sync = False
                raise LightSourceProtocolError(f"{self.describe()}: bad STROBE reply {payload!r}")
            self._strobe = (float(parts[0]), float(parts[1]))
            self._mode = LightMode.STROBE
