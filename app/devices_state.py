"""The camera and point-source connection states of the app, without Qt.

:class:`DeviceStates` is the state machine behind the main window's reconnection logic: what
state each device is in, which transitions are allowed, when a lost device is retried and when
it is given up. The window does the device work on its worker threads and reports outcomes
here; listeners (plain callables) hear every change, and the window turns them into Qt signals.
Testable without a display.
"""

from __future__ import annotations

import enum
from collections.abc import Callable

__all__ = ["CameraState", "DeviceStates", "LightAction", "LightState"]


class CameraState(enum.StrEnum):
    """Where the camera is."""

    DISCONNECTED = "disconnected"
    CONNECTING = "connecting"
    LIVE = "live"
    STOPPED = "stopped"
    RECONFIGURING = "reconfiguring"
    CALIBRATING = "calibrating"
    LOST = "lost"

    @property
    def connected(self) -> bool:
        """The camera is open and takes settings."""
        return self in (CameraState.LIVE, CameraState.STOPPED, CameraState.RECONFIGURING)

    @property
    def ready(self) -> bool:
        """The camera can start a workflow (calibration)."""
        return self in (CameraState.LIVE, CameraState.STOPPED)


class LightState(enum.StrEnum):
    """Where the point source is."""

    DISCONNECTED = "disconnected"
    CONNECTING = "connecting"
    CONNECTED = "connected"
    LOST = "lost"

    @property
    def watched(self) -> bool:
        """The source is checked periodically (to notice it is gone, or that it is back)."""
        return self in (LightState.CONNECTED, LightState.LOST)


class LightAction(enum.StrEnum):
    """What the periodic point-source check should do now."""

    NOTHING = "nothing"
    CHECK = "check"
    RECONNECT = "reconnect"


Listener = Callable[[str], None]


class DeviceStates:
    """Camera and point-source states with the reconnection rules.

    Rules:
    - a camera error while it is connected, live or reconfiguring makes it ``LOST`` (never when
      disconnected or while the window closes); a lost camera is retried until a reconnect
      works (``LIVE``) or the user disconnects (``DISCONNECTED``);
    - a point-source error while ``CONNECTED`` makes it ``LOST``; while ``LOST`` every check is a
      reconnect attempt; a good status makes it ``CONNECTED`` again.
    """

    def __init__(self) -> None:
        self.camera = CameraState.DISCONNECTED
        self.light = LightState.DISCONNECTED
        self.reconnect_attempts = 0
        self.closing = False
        self._camera_listeners: list[Listener] = []
        self._light_listeners: list[Listener] = []

    # -- listeners -----------------------------------------------------------------------------

    def on_camera_change(self, fn: Listener) -> None:
        """Call ``fn(state)`` after every camera state change."""
        self._camera_listeners.append(fn)

    def on_light_change(self, fn: Listener) -> None:
        """Call ``fn(state)`` after every point-source state change."""
        self._light_listeners.append(fn)

    # -- camera --------------------------------------------------------------------------------

    def set_camera(self, state: CameraState | str) -> CameraState:
        """Enter ``state`` (listeners are told); returns it."""
        self.camera = CameraState(state)
        for fn in list(self._camera_listeners):
            fn(self.camera.value)
        return self.camera

    def camera_failed(self) -> bool:
        """A camera call or the stream failed: True when this makes the camera ``LOST``."""
        if self.closing or self.camera in (CameraState.DISCONNECTED, CameraState.LOST):
            return False
        self.reconnect_attempts = 0
        self.set_camera(CameraState.LOST)
        return True

    def next_reconnect(self) -> int | None:
        """Number of the reconnect attempt to make now, or None when none is due."""
        if self.closing or self.camera is not CameraState.LOST:
            return None
        self.reconnect_attempts += 1
        return self.reconnect_attempts

    def reconnect_result(self, ok: bool) -> bool:
        """Outcome of an attempt: True when it still matters (the camera is still ``LOST``)."""
        if self.camera is not CameraState.LOST:
            return False
        if ok:
            self.set_camera(CameraState.LIVE)
        return True

    # -- point source --------------------------------------------------------------------------

    def set_light(self, state: LightState | str) -> LightState:
        """Enter ``state`` (listeners are told); returns it."""
        self.light = LightState(state)
        for fn in list(self._light_listeners):
            fn(self.light.value)
        return self.light

    def light_check(self, busy: bool) -> LightAction:
        """What the periodic check does now (nothing while the source's worker is busy)."""
        if busy or not self.light.watched:
            return LightAction.NOTHING
        return LightAction.RECONNECT if self.light is LightState.LOST else LightAction.CHECK

    def light_failed(self) -> bool:
        """A point-source call failed: True when the source is (now) ``LOST``."""
        if not self.light.watched:
            return False
        if self.light is not LightState.LOST:
            self.set_light(LightState.LOST)
        return True

    def light_ok(self) -> bool:
        """A good status arrived: True when this ends a loss (the source is back)."""
        if self.light is LightState.LOST:
            self.set_light(LightState.CONNECTED)
            return True
        return False
