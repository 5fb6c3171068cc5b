"""The camera / point-source state machine without Qt (app/devices_state.py)."""

from __future__ import annotations

import subprocess
import sys

from app.devices_state import CameraState, DeviceStates, LightAction, LightState


def test_camera_loss_and_reconnect_rules() -> None:
    d = DeviceStates()
    seen: list[str] = []
    d.on_camera_change(seen.append)
    assert not d.camera_failed()  # a disconnected camera cannot be lost
    assert d.next_reconnect() is None
    d.set_camera(CameraState.LIVE)
    assert d.camera == "live" and d.camera.connected and d.camera.ready
    assert d.camera_failed() and d.camera is CameraState.LOST
    assert not d.camera_failed()  # already lost: no second loss
    assert [d.next_reconnect(), d.next_reconnect()] == [1, 2]
    assert d.reconnect_result(False) and d.camera is CameraState.LOST
    assert d.reconnect_result(True) and d.camera is CameraState.LIVE
    assert not d.reconnect_result(True)  # a late answer after recovery does not matter
    d.set_camera(CameraState.LOST)
    d.set_camera(CameraState.DISCONNECTED)  # the user disconnects: no more attempts
    assert d.next_reconnect() is None
    d.set_camera(CameraState.LIVE)
    d.closing = True
    assert not d.camera_failed()  # closing: errors are expected, nothing reconnects
    assert seen == ["live", "lost", "live", "lost", "disconnected", "live"]
    assert not CameraState.CALIBRATING.ready and not CameraState.LOST.connected


def test_point_source_loss_and_recovery() -> None:
    d = DeviceStates()
    seen: list[str] = []
    d.on_light_change(seen.append)
    assert d.light_check(busy=False) is LightAction.NOTHING
    assert not d.light_failed()  # not connected: an error is not a loss
    d.set_light(LightState.CONNECTED)
    assert d.light_check(busy=False) is LightAction.CHECK
    assert d.light_check(busy=True) is LightAction.NOTHING
    assert d.light_failed() and d.light is LightState.LOST
    assert d.light_check(busy=False) is LightAction.RECONNECT
    assert d.light_ok() and d.light is LightState.CONNECTED
    assert not d.light_ok()
    assert seen == ["connected", "lost", "connected"]


def test_state_module_does_not_import_qt() -> None:
    code = ("import sys, app.devices_state; "
            "print(any(m.startswith(('PySide6', 'pyqtgraph')) for m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "False"
