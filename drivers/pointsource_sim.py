"""Simulated point-source firmware: its own process on one end of a real serial line (a PTY).

Run it as::

    python -m drivers.pointsource_sim --pty [--link PATH] [--state-file PATH]
    python -m drivers.pointsource_sim --port /dev/pts/N [--state-file PATH]

``--pty`` creates a pseudo-terminal pair, keeps the master end, and prints the other end's
path (``PORT /dev/pts/N``) on stdout; ``--link`` also points a stable symlink at it (a
restarted simulator keeps the same port name). ``--port`` opens an existing serial device
instead (one end of a ``socat`` pair, a USB loopback). When the line is in raw mode and the
simulator listens it prints ``READY`` on stdout; only then may a driver send commands
(setting raw mode flushes queued bytes).

The protocol is in ``docs/serial-protocol.md``. Every state change is written to the state
file (:mod:`drivers.lightstate`, atomically) *before* the ``OK`` reply, which is how the
simulated camera knows when the source is lit.

Fault injection for tests: ``DEBUG GARBAGE n`` (the next n replies are noise),
``DEBUG SLOW ms`` (every later command waits ms before it is applied and answered),
``DEBUG SILENT n`` (the next n commands get no reply); the same as ``--garbage``,
``--slow-ms`` and ``--silent`` at start. DEBUG commands themselves are never delayed or
garbled.

:func:`spawn_simulated_source` starts this process for tests, the CLI and the app, in its own
session (``start_new_session``): a Ctrl-C, SIGHUP or ``timeout`` aimed at the terminal's
foreground process group then reaches only the parent, which switches the light off *before*
it stops the firmware (a firmware that died first made that clean-up fail and warn). Out of
reach of those signals, the firmware watches its parent instead (``--parent-pid``) and exits
when the parent is gone, so a parent killed outright leaves no orphan behind.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import os
import re
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import tty
from collections import deque
from pathlib import Path
from typing import NamedTuple

from drivers.lightstate import LightMode, LightState, write_light_state

__all__ = ["Firmware", "SimulatedSource", "main", "spawn_simulated_source"]

VENDOR = "LENSLESSCAM"
MODEL = "POINTSOURCE-SIM"
FIRMWARE_VERSION = "1.0"
MAX_LINE = 256
MAX_TIME_US = 10_000_000.0
_TAG = re.compile(r"@([A-Za-z0-9]{1,16}) (.*)")

# error codes (see docs/serial-protocol.md)
E_UNKNOWN = 1
E_ARGUMENT = 2
E_SYNTAX = 3
E_TOO_LONG = 5
E_INTERNAL = 6


class Firmware:
    """The command interpreter, independent of the serial line (so it can be unit tested)."""

    def __init__(
        self,
        state_file: str | os.PathLike[str] | None = None,
        *,
        serial_number: str = "SN0001",
        garbage: int = 0,
        slow_ms: float = 0.0,
        silent: int = 0,
    ) -> None:
        self.state_file = None if state_file is None else Path(state_file)
        self.serial_number = serial_number
        self.state = LightState()
        self.errors: deque[tuple[int, str]] = deque(maxlen=16)
        self.garbage = int(garbage)
        self.slow_ms = float(slow_ms)
        self.silent = int(silent)
        self.publish()

    @property
    def identity(self) -> str:
        """The IDN reply payload."""
        return f"{VENDOR},{MODEL},{self.serial_number},{FIRMWARE_VERSION}"

    def publish(self) -> None:
        """Write the state file (atomically)."""
        if self.state_file is not None:
            write_light_state(self.state_file, self.state)

    def _apply(self, **changes: object) -> None:
        new = self.state.evolve(**changes)
        if self.state_file is not None:
            write_light_state(self.state_file, new)  # published before the OK
        self.state = new

    def _err(self, code: int, message: str) -> str:
        self.errors.append((code, message))
        return f"ERR {code} {message}"

    def handle(self, line: str) -> str:
        """Execute one command line (without tag) and return the reply line."""
        if len(line) > MAX_LINE:
            return self._err(E_TOO_LONG, f"line longer than {MAX_LINE} characters")
        words = line.strip().split()
        if not words:
            return self._err(E_SYNTAX, "empty command")
        cmd, args = words[0].upper(), words[1:]
        try:
            return self._dispatch(cmd, args)
        except _ArgError as exc:
            return self._err(E_ARGUMENT, str(exc))
        except OSError as exc:
            return self._err(E_INTERNAL, f"state not published: {exc.strerror}")

    def _dispatch(self, cmd: str, args: list[str]) -> str:
        s = self.state
        if cmd in ("IDN?", "*IDN?"):
            _nargs(cmd, args, 0)
            return f"OK {self.identity}"
        if cmd == "PING":
            _nargs(cmd, args, 0)
            return "OK PONG"
        if cmd == "ON":
            _nargs(cmd, args, 0)
            if s.mode is not LightMode.ON:
                self._apply(mode=LightMode.ON)
            return "OK ON"
        if cmd == "OFF":
            _nargs(cmd, args, 0)
            if s.mode is not LightMode.OFF:
                self._apply(mode=LightMode.OFF)
            return "OK OFF"
        if cmd == "INT":
            _nargs(cmd, args, 1)
            v = _number(args[0], "intensity", 0.0, 1.0)
            if v != s.intensity:
                self._apply(intensity=v)
            return f"OK {self.state.intensity:.4f}"
        if cmd == "INT?":
            _nargs(cmd, args, 0)
            return f"OK {s.intensity:.4f}"
        if cmd == "STROBE":
            _nargs(cmd, args, 2)
            d = _number(args[0], "delay_us", 0.0, MAX_TIME_US)
            w = _number(args[1], "duration_us", 0.0, MAX_TIME_US)
            if w <= 0:
                raise _ArgError("duration_us must be > 0")
            self._apply(mode=LightMode.STROBE, strobe_delay_us=d, strobe_duration_us=w)
            return f"OK {d:.1f} {w:.1f}"
        if cmd == "STROBE?":
            _nargs(cmd, args, 0)
            return f"OK {s.strobe_delay_us:.1f} {s.strobe_duration_us:.1f}"
        if cmd == "STATE?":
            _nargs(cmd, args, 0)
            return (
                f"OK mode={s.mode.value} int={s.intensity:.4f} delay_us={s.strobe_delay_us:.1f} "
                f"duration_us={s.strobe_duration_us:.1f} counter={s.counter}"
            )
        if cmd == "ERR?":
            _nargs(cmd, args, 0)
            if not self.errors:
                return "OK 0 no error"
            code, msg = self.errors.popleft()
            return f"OK {code} {msg}"
        if cmd == "RESET":
            _nargs(cmd, args, 0)
            self.errors.clear()
            self._apply(
                mode=LightMode.OFF, intensity=0.0, strobe_delay_us=0.0, strobe_duration_us=0.0
            )
            return "OK"
        if cmd == "DEBUG":
            return self._debug(args)
        return self._err(E_UNKNOWN, f"unknown command '{cmd}'")

    def _debug(self, args: list[str]) -> str:
        if len(args) != 2:
            raise _ArgError("DEBUG takes a fault name and a number")
        what, n = args[0].upper(), args[1]
        if what == "GARBAGE":
            self.garbage = int(_number(n, "count", 0, 1000))
        elif what == "SLOW":
            self.slow_ms = _number(n, "ms", 0.0, 60_000.0)
        elif what == "SILENT":
            self.silent = int(_number(n, "count", 0, 1000))
        else:
            raise _ArgError(f"unknown fault '{what}' (GARBAGE, SLOW, SILENT)")
        return "OK"


class _ArgError(ValueError):
    pass


def _nargs(cmd: str, args: list[str], n: int) -> None:
    if len(args) != n:
        raise _ArgError(f"{cmd} takes {n} argument(s), got {len(args)}")


def _number(text: str, name: str, lo: float, hi: float) -> float:
    try:
        v = float(text)
    except ValueError:
        raise _ArgError(f"{name} is not a number: '{text}'") from None
    if not (lo <= v <= hi):  # also rejects nan
        raise _ArgError(f"{name} {text} outside [{lo:g}, {hi:g}]")
    return v


# --------------------------------------------------------------------------------------------
# the serial line


def _garbage_line() -> bytes:
    junk = os.urandom(12)
    return bytes(b if 0x20 <= b < 0x7F and b != ord("@") else 0x80 | (b & 0x7F) for b in junk)


def _parent_to_watch(spawner: int | None) -> int | None:
    """The parent pid to watch for ``--parent-pid SPAWNER``: our parent as we start.

    That is the spawner itself, or a launcher between us that forked (and ends with the
    spawner's process). A spawner already gone before we started leaves nothing to watch for:
    then we exit at once (our parent is 1 or a subreaper) by returning a pid that cannot be our
    parent (0).
    """
    if spawner is None:
        return None
    ppid = os.getppid()
    if ppid != spawner:
        try:
            os.kill(spawner, 0)
        except ProcessLookupError:
            return 0  # the spawner died before we started
        except PermissionError:
            pass
    return ppid


def serve(fd: int, fw: Firmware, stop: list[bool], wakeup: int | None = None,
          parent: int | None = None) -> None:
    """Read command lines from ``fd`` and answer them until ``stop[0]`` is set.

    ``wakeup``: a pipe that a signal handler writes to (``signal.set_wakeup_fd``), so a stop
    request does not wait for the select timeout. ``parent``: stop as well once this process
    is no longer our parent (it exited or was killed; checked at least every 0.5 s).
    """
    buf = b""
    watch = [fd] if wakeup is None else [fd, wakeup]
    while not stop[0]:
        if parent is not None and os.getppid() != parent:
            break  # orphaned: whoever started us is gone
        try:
            ready, _, _ = select.select(watch, [], [], 0.5)
        except InterruptedError:
            continue
        if wakeup is not None and wakeup in ready:
            with contextlib.suppress(BlockingIOError):
                os.read(wakeup, 512)
            continue
        if fd not in ready:
            continue
        try:
            data = os.read(fd, 4096)
        except OSError as exc:
            if exc.errno in (errno.EIO, errno.EAGAIN, errno.EINTR):
                time.sleep(0.05)  # nobody on the other end right now
                continue
            raise
        if not data:
            time.sleep(0.05)
            continue
        buf += data
        while b"\n" in buf:
            raw, buf = buf.split(b"\n", 1)
            _answer(fd, fw, raw.rstrip(b"\r"))
        if len(buf) > 4 * MAX_LINE:  # no newline in sight: drop it
            buf = b""
            _write(fd, fw.handle("x" * (MAX_LINE + 1)).encode() + b"\n")


def _answer(fd: int, fw: Firmware, raw: bytes) -> None:
    text = raw.decode("ascii", errors="replace")
    m = _TAG.fullmatch(text)
    prefix, body = (f"@{m.group(1)} ", m.group(2)) if m else ("", text)
    if not body.strip():
        return
    is_debug = body.strip().upper().startswith("DEBUG")
    if not is_debug and fw.slow_ms > 0:
        time.sleep(fw.slow_ms / 1000.0)
    if "\ufffd" in body:
        reply = fw._err(E_SYNTAX, "non-ASCII bytes in command")
    else:
        reply = fw.handle(body)
    if not is_debug and fw.silent > 0:
        fw.silent -= 1
        return
    if not is_debug and fw.garbage > 0:
        fw.garbage -= 1
        _write(fd, _garbage_line() + b"\n")
        return
    _write(fd, (prefix + reply).encode("ascii", errors="replace") + b"\n")


def _write(fd: int, data: bytes) -> None:
    while data:
        try:
            n = os.write(fd, data)
        except OSError as exc:
            if exc.errno in (errno.EAGAIN, errno.EINTR):
                time.sleep(0.01)
                continue
            if exc.errno == errno.EIO:
                return  # nobody listening; the reply is lost, as on a real line
            raise
        data = data[n:]


def _link(target: str, link: Path) -> None:
    tmp = link.with_name(f".{link.name}.{os.getpid()}.tmp")
    with contextlib.suppress(FileNotFoundError):
        tmp.unlink()
    os.symlink(target, tmp)
    os.replace(tmp, link)


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point of the simulated firmware."""
    p = argparse.ArgumentParser(prog="python -m drivers.pointsource_sim", description=__doc__)
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--pty", action="store_true", help="create a PTY pair, print its path")
    where.add_argument("--port", help="open this existing serial device")
    p.add_argument("--link", type=Path, help="with --pty: symlink pointing at the port")
    p.add_argument("--state-file", type=Path, help="publish the lit state here")
    p.add_argument("--serial-number", default="SN0001")
    p.add_argument("--garbage", type=int, default=0, help="garble the first N replies")
    p.add_argument("--slow-ms", type=float, default=0.0, help="delay every command")
    p.add_argument("--silent", type=int, default=0, help="do not answer the first N commands")
    p.add_argument("--parent-pid", type=int,
                   help="exit when process PARENT_PID is no longer this process's parent")
    p.add_argument("--remove-when-orphaned", type=Path, metavar="DIR",
                   help="with --parent-pid: a temporary folder of the parent's (the state "
                        "file's), removed when the firmware exits because the parent is gone")
    args = p.parse_args(argv)

    keep: list[int] = []
    if args.pty:
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no line editing; flushes anything queued
        keep.append(slave)  # keep the slave open: reads on master then never hit EIO
        fd, port = master, os.ttyname(slave)
        if args.link is not None:
            _link(port, args.link)
            port_shown = str(args.link)
        else:
            port_shown = port
    else:
        fd = os.open(args.port, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(fd)
        port_shown = args.port

    fw = Firmware(
        args.state_file,
        serial_number=args.serial_number,
        garbage=args.garbage,
        slow_ms=args.slow_ms,
        silent=args.silent,
    )
    stop = [False]

    def on_signal(signum: int, frame: object) -> None:
        stop[0] = True

    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_r, False)
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    _write(fd, f"READY {fw.identity}\n".encode())
    print(f"PORT {port_shown}", flush=True)
    print("READY", flush=True)
    parent = _parent_to_watch(args.parent_pid)
    try:
        serve(fd, fw, stop, wake_r, parent)
    finally:
        with contextlib.suppress(OSError):
            fw.state = fw.state.evolve(mode=LightMode.OFF)
            fw.publish()  # a firmware that shuts down leaves the light off
        if args.pty and args.link is not None:
            with contextlib.suppress(OSError):
                if os.readlink(args.link) == port:
                    args.link.unlink()
        for f in [fd, *keep, wake_r, wake_w]:
            with contextlib.suppress(OSError):
                os.close(f)
        if (args.remove_when_orphaned is not None and parent is not None
                and os.getppid() != parent):
            # the parent was killed outright (SIGKILL) and could not remove its folder
            shutil.rmtree(args.remove_when_orphaned, ignore_errors=True)
    return 0


# --------------------------------------------------------------------------------------------
# spawning it


class SimulatedSource(NamedTuple):
    """A running simulator process: the port to open, the process, the state file."""

    port: str
    process: subprocess.Popen[bytes]
    state_path: Path

    def stop(self, timeout_s: float = 5.0) -> None:
        """Terminate the process (kill it if it does not exit) and reap it."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        else:
            self.process.wait()

    def kill(self) -> None:
        """Kill the process at once (no clean shutdown) and reap it."""
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait()


def spawn_simulated_source(
    state_path: str | os.PathLike[str] | None = None,
    *,
    link: str | os.PathLike[str] | None = None,
    extra_args: tuple[str, ...] = (),
    timeout_s: float = 15.0,
    owned_folder: str | os.PathLike[str] | None = None,
) -> SimulatedSource:
    """Start the simulated firmware on a fresh PTY and wait until it is READY.

    ``state_path`` defaults to a new temporary folder's ``light-state.json``; ``link`` gives
    the port a stable name. Returns ``(port, process, state_path)``; call ``.stop()``.

    The process runs in its own session, so the terminal's Ctrl-C (SIGINT to the foreground
    process group) does not kill it before the caller has switched the light off; it exits by
    itself when the caller's process ends without stopping it. ``owned_folder``: a temporary
    folder of the caller's (holding the state file) that the firmware removes when it exits
    that way, since the caller, killed outright, could not; the default state file's folder is
    such a folder.
    """
    if state_path is None:
        owned_folder = tempfile.mkdtemp(prefix="lenslesscam-light-")
        state_path = Path(owned_folder) / "light-state.json"
    state = Path(state_path)
    cmd = [sys.executable, "-m", "drivers.pointsource_sim", "--pty", "--state-file", str(state),
           "--parent-pid", str(os.getpid())]
    if owned_folder is not None:
        cmd += ["--remove-when-orphaned", str(owned_folder)]
    if link is not None:
        cmd += ["--link", str(link)]
    cmd += list(extra_args)
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parent.parent)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH", "")) if p)
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, env=env,
                            start_new_session=True)
    assert proc.stdout is not None
    out = b""
    port = None
    deadline = time.monotonic() + timeout_s
    try:
        while b"READY\n" not in out:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(f"simulated source not READY within {timeout_s} s")
            ready, _, _ = select.select([proc.stdout], [], [], remaining)
            if not ready:
                continue
            chunk = os.read(proc.stdout.fileno(), 4096)
            if not chunk:
                raise RuntimeError(f"simulated source exited early (code {proc.wait()})")
            out += chunk
        for line in out.decode().splitlines():
            if line.startswith("PORT "):
                port = line[5:].strip()
        if port is None:
            raise RuntimeError(f"simulated source did not say its port: {out!r}")
    except BaseException:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        proc.stdout.close()
        raise
    proc.stdout.close()
    return SimulatedSource(port, proc, state)


if __name__ == "__main__":
    sys.exit(main())
