"""Serial faults: each gives a clear error, never a hang or a half-applied state, and the
driver recovers after reconnecting to a restarted simulator."""

from __future__ import annotations

import threading
import time

import pytest

from drivers.lightsource import (
    LightSourceDisconnected,
    LightSourceProtocolError,
    LightSourceTimeout,
    SerialPointSource,
)
from drivers.lightstate import LightMode, read_light_state
from tests.drivers.conftest import SourceFactory

pytestmark = pytest.mark.timeout(60)


def _restart_and_recover(sources: SourceFactory, dev: SerialPointSource) -> None:
    """Stop every simulator, start a fresh one on the same port name, reconnect, use it."""
    sources.stop_all()
    sources.start()
    dev.timeout_s = 0.5
    dev.reconnect()
    assert dev.in_sync and dev.is_on is False  # a restarted device comes up dark
    dev.set_intensity(0.3)
    dev.on()
    st = dev.status()
    assert st.is_on and st.intensity == pytest.approx(0.3)


def test_simulator_killed_mid_command(sources: SourceFactory) -> None:
    src = sources.start()
    dev = SerialPointSource(str(sources.link), timeout_s=5.0)
    with dev:
        dev.command("DEBUG SLOW 3000")  # the next command takes 3 s inside the "firmware"
        killer = threading.Timer(0.3, src.kill)
        killer.start()
        t0 = time.monotonic()
        with pytest.raises(LightSourceDisconnected, match="port vanished during 'ON'"):
            dev.on()
        elapsed = time.monotonic() - t0
        killer.join()
        assert elapsed < 2.0  # noticed at once, not after the 5 s timeout
        assert dev.is_on is False  # no OK: the cache still says off
        assert not dev.in_sync and not dev.is_open
        assert read_light_state(src.state_path).mode is LightMode.OFF  # never applied
        with pytest.raises(LightSourceDisconnected, match="not connected"):
            dev.set_intensity(0.5)
        _restart_and_recover(sources, dev)


def test_garbage_replies(sources: SourceFactory) -> None:
    sources.start()
    with SerialPointSource(str(sources.link), timeout_s=0.5, retries=2) as dev:
        dev.command("DEBUG GARBAGE 1")  # one garbled reply: the retry absorbs it
        dev.on()
        assert dev.is_on is True and dev.in_sync
        dev.command("DEBUG GARBAGE 100")  # a babbling device
        t0 = time.monotonic()
        with pytest.raises(LightSourceProtocolError, match=r"garbled reply .*\(3 attempts\)"):
            dev.off()
        assert time.monotonic() - t0 < 1.0
        assert dev.is_on is True and not dev.in_sync  # cache unchanged, flagged unsure
        _restart_and_recover(sources, dev)


def test_slow_reply_past_the_timeout(sources: SourceFactory) -> None:
    sources.start()
    with SerialPointSource(str(sources.link), timeout_s=0.15, retries=1) as dev:
        dev.command("DEBUG SLOW 400")
        t0 = time.monotonic()
        with pytest.raises(LightSourceTimeout, match=r"within 0.15 s \(2 attempts\)"):
            dev.set_intensity(0.8)
        assert 0.25 < time.monotonic() - t0 < 1.0  # two attempts, then a clear error
        assert dev.intensity == 0.0 and not dev.in_sync
        _restart_and_recover(sources, dev)


def test_late_replies_are_never_taken_for_the_current_command(sources: SourceFactory) -> None:
    sources.start()
    with SerialPointSource(str(sources.link), timeout_s=0.15, retries=0) as dev:
        dev.command("DEBUG SLOW 300")
        with pytest.raises(LightSourceTimeout):
            dev.on()  # its "OK ON" arrives late, while the next command waits
        dev.timeout_s = 2.0
        dev.command("DEBUG SLOW 0")
        assert dev.command("INT?", idempotent=True) == "0.0000"  # not the stale "ON"
        st = dev.status()
        assert st.mode is LightMode.ON and dev.in_sync  # status() re-syncs the cache


def test_unanswered_command_is_retried(sources: SourceFactory) -> None:
    sources.start("--silent", "1")
    with SerialPointSource(str(sources.link), timeout_s=0.2, retries=1) as dev:
        # opening sent IDN? which the device swallowed; the retry got the answer
        assert dev.identify().startswith("LENSLESSCAM")
        dev.command("DEBUG SILENT 1")
        with pytest.raises(LightSourceTimeout):
            dev.command("RESET")  # not idempotent: no retry


def test_simulator_killed_between_commands_is_a_disconnect(sources: SourceFactory) -> None:
    """A PTY whose firmware died raises termios.error (not an OSError) in pyserial: it must
    still become LightSourceDisconnected, and the dead port must be dropped."""
    src = sources.start()
    dev = SerialPointSource(str(sources.link), timeout_s=1.0)
    with dev:
        dev.on()
        src.kill()
        with pytest.raises(LightSourceDisconnected, match="port vanished during 'OFF'"):
            dev.off()
        assert not dev.is_open and not dev.in_sync
        with pytest.raises(LightSourceDisconnected, match="not connected"):
            dev.status()
        _restart_and_recover(sources, dev)
