"""Light sources: one contract for every implementation (the serial driver against the PTY
simulator process), the firmware's protocol, and the coupling to the simulated camera."""

from __future__ import annotations

import json
from collections.abc import Iterator

import numpy as np
import pytest

from drivers.lightsource import (
    DeviceError,
    LightSource,
    LightSourceDisconnected,
    SerialPointSource,
)
from drivers.lightstate import LightMode, LightStateFile, read_light_state
from drivers.pointsource_sim import Firmware
from drivers.simcam import SimulatedCamera
from tests.drivers.conftest import SourceFactory

pytestmark = pytest.mark.timeout(60)


@pytest.fixture(params=["serial-pty"])
def light(request: pytest.FixtureRequest, sources: SourceFactory) -> Iterator[LightSource]:
    """A fresh, open light source of each implementation."""
    if request.param == "serial-pty":
        src = sources.start()
        dev = SerialPointSource(src.port, timeout_s=1.0)
    else:  # pragma: no cover - one implementation so far
        raise AssertionError(request.param)
    dev.open()
    try:
        yield dev
    finally:
        dev.close()


class TestLightSourceContract:
    """Every light source behaves the same through the LightSource protocol."""

    def test_is_a_light_source(self, light: LightSource) -> None:
        assert isinstance(light, LightSource)
        assert light.is_open

    def test_identify(self, light: LightSource) -> None:
        ident = light.identify()
        assert len(ident.split(",")) == 4

    def test_on_off(self, light: LightSource) -> None:
        assert light.is_on is False
        light.on()
        assert light.is_on is True and light.status().is_on
        light.off()
        assert light.is_on is False and not light.status().is_on

    @pytest.mark.parametrize(("value", "applied"), [(0.25, 0.25), (1.7, 1.0), (-0.2, 0.0)])
    def test_intensity_is_clipped(self, light: LightSource, value: float, applied: float) -> None:
        assert light.set_intensity(value) == pytest.approx(applied)
        assert light.intensity == pytest.approx(applied)
        assert light.status().intensity == pytest.approx(applied)

    @pytest.mark.parametrize("bad", [float("nan"), "0.5", True, None])
    def test_invalid_intensity_is_rejected_and_nothing_changes(
        self, light: LightSource, bad: object
    ) -> None:
        light.set_intensity(0.5)
        counter = light.status().counter
        with pytest.raises((ValueError, TypeError)):
            light.set_intensity(bad)  # type: ignore[arg-type]
        assert light.intensity == 0.5
        assert light.status().counter == counter

    def test_strobe(self, light: LightSource) -> None:
        light.strobe(120.0, 30.0)
        st = light.status()
        assert st.mode is LightMode.STROBE and st.is_on
        assert (st.strobe_delay_us, st.strobe_duration_us) == (120.0, 30.0)
        for delay, duration in ((-1.0, 10.0), (0.0, 0.0), (float("inf"), 5.0), (0.0, 2e7)):
            with pytest.raises(ValueError):
                light.strobe(delay, duration)
        assert light.status().counter == st.counter  # nothing was sent

    def test_error_queue(self, light: LightSource) -> None:
        assert light.errors() == []

    def test_close_and_context_manager(self, light: LightSource) -> None:
        light.close()
        assert not light.is_open
        with light:
            assert light.is_open and light.identify()
        assert not light.is_open


# --------------------------------------------------------------------------------------------
# the serial driver and the firmware


def test_device_errors_carry_the_code_and_are_queued(sim_source: object) -> None:
    with SerialPointSource(sim_source.port) as dev:  # type: ignore[attr-defined]
        with pytest.raises(DeviceError, match="error 1: unknown command 'BLINK'") as info:
            dev.command("BLINK")
        assert info.value.code == 1
        with pytest.raises(DeviceError) as info:
            dev.command("INT 2")  # the firmware checks the range too
        assert info.value.code == 2
        assert [code for code, _ in dev.errors()] == [1, 2]
        assert dev.errors() == []


def test_state_file_follows_every_confirmed_change(sources: SourceFactory) -> None:
    src = sources.start()
    reader = LightStateFile(src.state_path)
    with SerialPointSource(src.port) as dev:
        assert reader.light_state().mode is LightMode.OFF
        dev.set_intensity(0.4)
        dev.on()  # once OK came back, the file already says so
        st = reader.light_state()
        assert st.mode is LightMode.ON and st.intensity == pytest.approx(0.4)
        dev.strobe(10.0, 5.0)
        st2 = reader.light_state()
        assert st2.mode is LightMode.STROBE and st2.counter == st.counter + 1
        assert json.loads(src.state_path.read_text())["format"] == "lenslesscam-light-state"
    src.stop()
    assert read_light_state(src.state_path).mode is LightMode.OFF  # clean shutdown: dark


def test_the_simulated_camera_sees_the_source_through_the_state_file(
    sources: SourceFactory,
) -> None:
    src = sources.start()
    cam = SimulatedCamera(
        24, 16, light_state=src.state_path, pacing=False, noise=False, dark_offset_adu=0.0,
        exposure_us=1000.0, point_flux_e_per_ms=1e4, point_position=(8.0, 12.0),
        readout_pattern="global",
    )  # fmt: skip
    with SerialPointSource(src.port) as dev, cam:
        assert cam.snap().pixels.max() == 0
        dev.set_intensity(1.0)
        dev.on()
        lit = cam.snap()
        assert np.unravel_index(np.argmax(lit.pixels), lit.shape) == (8, 12)
        assert lit.extra["light"]["mode"] == "on"
        dev.strobe(5000.0, 100.0)  # the pulse comes after every row's exposure ended
        assert cam.snap().pixels.max() == 0
        dev.strobe(0.0, 500.0)  # half of the 1 ms exposure of every row (global overlap)
        half = cam.snap().pixels.astype(float)
        np.testing.assert_allclose(half.max(), lit.pixels.max() / 2, rtol=0.01)
        dev.off()
        assert cam.snap().pixels.max() == 0


def test_firmware_protocol_table(tmp_path: object) -> None:
    fw = Firmware()
    assert fw.handle("IDN?").startswith("OK LENSLESSCAM,POINTSOURCE-SIM,")
    assert fw.handle("ping") == "OK PONG"
    assert fw.handle("INT 0.5") == "OK 0.5000"
    assert fw.handle("INT?") == "OK 0.5000"
    assert fw.handle("ON") == "OK ON"
    assert fw.handle("STROBE 10 2.5") == "OK 10.0 2.5"
    assert fw.handle("STROBE?") == "OK 10.0 2.5"
    assert fw.handle("STATE?") == (
        "OK mode=strobe int=0.5000 delay_us=10.0 duration_us=2.5 counter=3"
    )
    assert fw.handle("INT nan").startswith("ERR 2 ")
    assert fw.handle("STROBE 1 0").startswith("ERR 2 ")
    assert fw.handle("ON now").startswith("ERR 2 ")
    assert fw.handle("").startswith("ERR 3 ")
    assert fw.handle("X" * 300).startswith("ERR 5 ")
    assert fw.handle("FOO").startswith("ERR 1 ")
    assert fw.handle("ERR?").startswith("OK 2 ")
    assert fw.handle("RESET") == "OK"
    assert fw.handle("ERR?") == "OK 0 no error"
    assert fw.handle("STATE?").startswith("OK mode=off int=0.0000")


def test_opening_a_missing_port_is_a_clear_error(tmp_path: object) -> None:
    dev = SerialPointSource(f"{tmp_path}/no-such-tty")
    with pytest.raises(LightSourceDisconnected, match="cannot open"):
        dev.open()
    with pytest.raises(LightSourceDisconnected, match="not connected"):
        dev.on()


def test_driver_composes_an_existing_port_object(sim_source: object) -> None:
    import serial

    port = serial.Serial(sim_source.port, timeout=1.0)  # type: ignore[attr-defined]
    dev = SerialPointSource(port)
    try:
        dev.open()
        dev.on()
        assert dev.status().is_on
        dev.reconnect()  # closes and reopens the same object
        assert port.is_open and dev.is_on
    finally:
        dev.close()
    assert not port.is_open


def test_firmware_can_serve_an_existing_serial_device(tmp_path: object) -> None:
    """``--port PATH``: the firmware opens one end of a serial pair that someone else made."""
    import os
    import pty
    import select
    import subprocess
    import sys
    import tty
    from pathlib import Path

    master, slave = pty.openpty()
    tty.setraw(master)
    path = os.ttyname(slave)
    state = Path(str(tmp_path)) / "s.json"
    root = str(Path(__file__).resolve().parents[2])
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([root, os.environ.get("PYTHONPATH", "")]))
    cmd = [sys.executable, "-m", "drivers.pointsource_sim", "--port", path]
    proc = subprocess.Popen([*cmd, "--state-file", str(state)], stdout=subprocess.PIPE, env=env)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline() == f"PORT {path}\n".encode()
        assert proc.stdout.readline() == b"READY\n"
        got = b""
        os.write(master, b"@5 ON\n")
        while b"@5 " not in got or not got.endswith(b"\n"):
            ready, _, _ = select.select([master], [], [], 5.0)
            assert ready, f"no reply, got {got!r}"
            got += os.read(master, 1024)
        lines = got.decode().splitlines()
        assert lines[0].startswith("READY LENSLESSCAM,POINTSOURCE-SIM")  # the boot banner
        assert lines[-1] == "@5 OK ON"
        assert read_light_state(state).mode is LightMode.ON
    finally:
        proc.terminate()
        proc.wait(5)
        assert proc.stdout is not None
        proc.stdout.close()
        os.close(master)
        os.close(slave)


def test_the_firmware_watches_the_parent_it_starts_with():
    """--parent-pid: the firmware watches its parent as it starts (the spawner, or a launcher
    that forked between them); a spawner gone before it started means exit at once (0)."""
    import os
    import subprocess
    import sys

    from drivers.pointsource_sim import _parent_to_watch

    assert _parent_to_watch(None) is None
    assert _parent_to_watch(os.getppid()) == os.getppid()
    # a launcher between: the spawner (alive) is not our parent; watch the launcher
    assert _parent_to_watch(os.getpid()) == os.getppid()
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    assert _parent_to_watch(gone.pid) == 0


# --------------------------------------------------------------------------------------------
# one process per port; strobe times at the resolution sent; open errors said once


def test_a_second_opener_of_the_port_is_refused_and_the_first_keeps_working(
        sim_source: object) -> None:
    """Two processes on one point source took each other's replies (partial replies, 'port
    vanished'): the port is opened exclusively and a second opener is refused in one line."""
    import subprocess
    import sys

    from drivers.lightsource import LightSourceBusy

    port = sim_source.port  # type: ignore[attr-defined]
    first = SerialPointSource(port, timeout_s=2.0)
    first.open()
    try:
        second = SerialPointSource(port, timeout_s=2.0)  # another opener, this process
        with pytest.raises(LightSourceBusy) as info:
            second.open()
        assert str(info.value) == (f"port {port} is in use by another process (close the "
                                   "other connection to the point source first)")
        assert not second.is_open
        # and another process
        code = ("import sys\nfrom drivers.lightsource import SerialPointSource, LightSourceBusy\n"
                f"try:\n    SerialPointSource({port!r}, timeout_s=2.0).open()\n"
                "except LightSourceBusy as e:\n    print(e); sys.exit(3)\n")
        proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                              timeout=30)
        assert proc.returncode == 3, proc.stderr
        assert f"port {port} is in use by another process" in proc.stdout
        first.on()  # undisturbed
        assert first.status().is_on
    finally:
        first.close()
    second.open()  # free again once the first closed it
    try:
        assert second.status().is_on
    finally:
        second.close()


def test_a_strobe_shorter_than_the_resolution_sent_is_refused_before_sending(
        light: LightSource) -> None:
    """0.04 us went out as 'STROBE 0.0 0.0', and the firmware's refusal blamed the hardware."""
    from drivers.lightsource import TIME_RESOLUTION_US

    counter = light.status().counter
    for short in (0.04, 0.049):
        with pytest.raises(ValueError, match=r"shorter than the source's 0\.1 us resolution"):
            light.strobe(0.0, short)
    assert light.status().counter == counter  # nothing was sent
    assert light.errors() == []
    light.strobe(0.0, TIME_RESOLUTION_US)
    assert light.status().strobe_duration_us == pytest.approx(0.1)


def test_a_port_that_does_not_open_is_said_once(tmp_path: object) -> None:
    """'cannot open point source on X: [Errno 2] could not open port X: [Errno 2] No such
    file or directory: 'X''."""
    missing = f"{tmp_path}/no-such-tty"
    with pytest.raises(LightSourceDisconnected) as info:
        SerialPointSource(missing).open()
    assert str(info.value) == f"cannot open point source on {missing}: No such file or directory"
