"""The main window: devices, live view, live reconstruction preview, calibration, UDN jobs.

Threads: the GUI thread only displays. Everything that touches a device runs on that device's
:class:`~app.gui.workers.TaskQueue` (one QThread each, in order); the live view is a QTimer
that polls the camera's newest frame without waiting (:meth:`Camera.latest_frame` with timeout
0); the preview runs on its own QThread (:class:`~app.gui.workers.PreviewWorker`) and only ever
sees the newest frame.

Device loss: an error from the live stream (the camera timing out, or a run of bad frames: a
single bad frame is skipped by the stream and counted in the footer, ``FrameError``) or from
the point source (its port gone) is shown in the window's banner and the device panel, and a
reconnect is tried every ``reconnect_interval_ms`` until it works or the user disconnects. The
states and the reconnection rules live in :class:`app.devices_state.DeviceStates` (no Qt); the
window does the device work and reports the outcomes there.

Layout: the images in the centre; Controls (left), UDN jobs and the speed/accuracy trade
(bottom, tabbed) are docks that can be closed, moved, floated or tabbed (View menu). Footers
and status lines never widen the window: it fits a 1366x768 screen with every dock shown.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import re
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from PySide6.QtCore import QByteArray, QSignalBlocker, Qt, QTimer, Signal
from PySide6.QtGui import QAction, QCloseEvent
from PySide6.QtWidgets import (
    QDockWidget,
    QFileDialog,
    QLabel,
    QMainWindow,
    QScrollArea,
    QSplitter,
    QVBoxLayout,
    QWidget,
)

from app.devices_state import CameraState, DeviceStates, LightAction, LightState
from app.gui.devices import (
    SIM_CAMERA,
    SIM_CAMERA_CHOICE,
    SIM_PORT_CHOICE,
    Bench,
    CameraChoice,
    ReconnectCancelled,
    SimConfig,
    best_effort,
    list_camera_choices,
    list_port_choices,
)
from app.gui.image_view import ImagePanel, configure_pyqtgraph
from app.gui.jobs_core import Spawner, spawn_job_process
from app.gui.jobs_panel import JobsPanel, Measurement
from app.gui.panels import (
    CameraControls,
    DevicePanel,
    PreviewControls,
    make_sidebar,
    set_status,
)
from app.gui.preview_engine import (
    PreviewEngine,
    PreviewResult,
    PreviewSettings,
    saturation_verdict,
)
from app.gui.settings import AppSettings, default_jobs_dir, save_settings
from app.gui.trade_panel import TradePanel, frame_source
from app.gui.widgets import never_wider
from app.gui.workers import PreviewWorker, TaskQueue

__all__ = ["MainWindow", "WorkflowHandle", "load_psf_any"]

_log = logging.getLogger(__name__)



def _describe(exc: BaseException) -> str:
    text = str(exc)
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def frame_geometry(frame: Any) -> str:
    """Where a frame lies on its sensor, for the live view's footer.

    ``200x150 px, whole sensor``, or ``320x240 px, ROI at (100, 50) of 1440x1080, binning 2``
    (the ROI's corner in unbinned sensor pixels); ``sensor size unknown`` for a frame that does
    not say (:attr:`drivers.camera.Frame.sensor`).
    """
    h, w = frame.shape[:2]
    roi, binning, sensor = frame.roi, frame.binning, getattr(frame, "sensor", None)
    if sensor is None:
        where = f"ROI at ({roi.x}, {roi.y}), sensor size unknown"
    elif (roi.x, roi.y, roi.width, roi.height) == (0, 0, sensor[1], sensor[0]):
        where = "whole sensor"
    else:
        where = f"ROI at ({roi.x}, {roi.y}) of {sensor[1]}x{sensor[0]}"
    return f"{w}x{h} px, {where}" + (f", binning {binning}" if binning > 1 else "")


def _read_camera(cam: Any) -> tuple[dict[str, Any], dict[str, Any]]:
    """What the camera reports now (None where it lacks a feature), and the ranges."""
    values: dict[str, Any] = {}
    for name in CameraControls.PROPERTIES:
        try:
            v = getattr(cam, name)
        except Exception:  # FeatureNotAvailable or a device error: the control is disabled
            v = None
        values[name] = getattr(v, "value", v)
    try:
        values["resulting_frame_rate_hz"] = cam.resulting_frame_rate_hz
    except Exception:  # a device error: no note beside the frame rate
        values["resulting_frame_rate_hz"] = None
    ranges: dict[str, Any] = {}
    try:
        caps = cam.capabilities()
        ranges["exposure_us"] = caps.exposure_range_us
        ranges["gain"] = caps.gain_range
        ranges["frame_rate_hz"] = caps.frame_rate_range_hz
        values["bit_depth"] = cam.bit_depth
        values["sensor"] = (caps.sensor_height, caps.sensor_width)
        values["model"] = caps.model
    except Exception as exc:
        _log.warning("reading the camera's capabilities: %s", exc)
    try:
        roi = cam.roi
        values["roi"] = (roi.x, roi.y, roi.width, roi.height)
    except Exception:
        values["roi"] = None
    return values, ranges


#: what the preview panel says while the preview is off
_PREVIEW_OFF = "preview off"
_PREVIEW_HELD = "preview paused while the trade measures (it would share the cores it times)"
#: suffixes that name another file type: Save as refuses them (frames are saved as TIFF)
_OTHER_FILE_TYPES = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".gif", ".npy", ".npz",
                               ".fits", ".fit", ".mat", ".h5", ".json", ".csv", ".txt"})


class _Rate:
    """Events per second over the last few seconds; 0 once events stop coming.

    Ticks may be on any clock (a frame's own timestamp, the wall clock): "now" is the newest
    tick plus the monotonic time since it came (a wall-clock tick compared with the
    monotonic clock kept 9.99 fps for a stream that had stopped). A slow stream (one frame
    every 3 s) shows its one interval while the next frame is not overdue.
    """

    def __init__(self, window_s: float = 2.0) -> None:
        self.window_s = window_s
        self.times: collections.deque[float] = collections.deque()
        self._interval = 0.0
        self._arrived = 0.0  # time.monotonic() of the newest tick

    def tick(self, t: float | None = None) -> None:
        self._arrived = time.monotonic()
        now = self._arrived if t is None else t
        if self.times:
            self._interval = now - self.times[-1]
        self.times.append(now)
        while len(self.times) > 1 and now - self.times[0] > self.window_s:
            self.times.popleft()

    def rate(self, now: float | None = None) -> float:
        if not self.times:
            return 0.0
        t = self.times[-1] + (time.monotonic() - self._arrived) if now is None else now
        recent = [x for x in self.times if t - x <= self.window_s]
        if len(recent) >= 2 and recent[-1] > recent[0]:
            return (len(recent) - 1) / (recent[-1] - recent[0])
        if self._interval > 0 and t - self.times[-1] <= 2.0 * self._interval:
            return 1.0 / self._interval
        return 0.0


class WorkflowHandle:
    """A workflow started by :meth:`MainWindow.run_camera_workflow`; :meth:`cancel` it."""

    def __init__(self) -> None:
        self.workflow: Any = None
        self.task: Any = None

    def cancel(self) -> None:
        """Cancel at the workflow's next progress point (nothing is saved)."""
        if self.workflow is not None:
            self.workflow.cancel()


class MainWindow(QMainWindow):
    """The lenslesscam desktop app.

    Args:
        settings: what to start with (see :class:`~app.gui.settings.AppSettings`).
        settings_path: where :meth:`closeEvent` saves them (None: the user config file;
            ``False``-y Path("") disables saving).
        bench: the devices (default: a new :class:`~app.gui.devices.Bench`, simulated bench).
        autoconnect: connect the camera (and point source) from the settings at start.
        reconnect_interval_ms: time between reconnect attempts after a device is lost.
        light_check_interval_ms: time between checks of the point source.
        jobs_poll_ms: how often the jobs panel reads the jobs folder (and starts queued jobs).
        job_spawn: starts a UDN job's process (:func:`app.gui.jobs_core.spawn_job_process`).

    """

    camera_state_changed = Signal(str)
    frame_shown = Signal(object)
    preview_shown = Signal(object)
    light_state_changed = Signal(str)

    def __init__(
        self,
        settings: AppSettings | None = None,
        *,
        settings_path: Path | None = None,
        save_settings_on_close: bool = True,
        bench: Bench | None = None,
        autoconnect: bool = True,
        reconnect_interval_ms: int = 1000,
        light_check_interval_ms: int = 2000,
        jobs_poll_ms: int = 1000,
        job_spawn: Spawner = spawn_job_process,
    ) -> None:
        super().__init__()
        configure_pyqtgraph()
        self.setWindowTitle("lenslesscam")
        self.settings = settings or AppSettings()
        self._settings_path = settings_path
        self._save_on_close = save_settings_on_close
        self.bench = bench or Bench(SimConfig(scene=self.settings.sim_scene))
        self.reconnect_interval_ms = int(reconnect_interval_ms)
        self._jobs_poll_ms = int(jobs_poll_ms)
        self._job_spawn = job_spawn

        self.camera_queue = TaskQueue("camera", self)
        self.light_queue = TaskQueue("light", self)

        # state (Qt-free; its listeners re-emit the changes as Qt signals)
        self.devices = DeviceStates()
        self.devices.on_camera_change(self.camera_state_changed.emit)
        self.devices.on_light_change(self.light_state_changed.emit)
        self.last_frame: Any = None
        self._live_before_reconfigure = False  # the camera's state before a queued change
        self.frames_shown = 0
        self.previews_shown = 0
        self._preview_held = False  # by the trade panel while it measures (its timings)
        self.frames_skipped_saturated = 0
        self.last_error = ""
        self._bit_depth: int | None = None
        self._display_rate = _Rate()
        self._camera_rate = _Rate()
        self._preview_rate = _Rate()
        self._latency_ms: collections.deque[float] = collections.deque(maxlen=30)
        self._preview_latency_ms: collections.deque[float] = collections.deque(maxlen=30)
        self.psf_source = ""

        # widgets
        self.banner = QLabel("")
        self.banner.setObjectName("banner")
        self.banner.setWordWrap(True)
        self.banner.setStyleSheet(
            "QLabel#banner { background: #ffebe9; color: #82071e; padding: 4px;"
            " border: 1px solid #ff8182; }"
        )
        self.banner.setVisible(False)
        self.banner.setToolTip("click to dismiss")
        self.banner.mousePressEvent = lambda _e: self.show_error("")  # type: ignore[method-assign]
        self._banner_source = ""
        never_wider(self.banner)
        self.raw_panel = ImagePanel("Raw frame", with_roi=True, with_saturation=True,
                                    auto_levels_option=True)
        self.preview_panel = ImagePanel("Reconstruction preview", auto_levels_option=True)
        self.preview_panel.auto_levels.setChecked(True)
        split = QSplitter(Qt.Orientation.Horizontal)
        split.addWidget(self.raw_panel)
        split.addWidget(self.preview_panel)
        split.setSizes([1, 1])
        central = QWidget()
        lay = QVBoxLayout(central)
        lay.setContentsMargins(2, 2, 2, 2)
        lay.addWidget(self.banner)
        lay.addWidget(split, 1)
        self.setCentralWidget(central)

        self.device_panel = DevicePanel()
        self.camera_controls = CameraControls()
        self.preview_controls = PreviewControls()
        side = make_sidebar(self.device_panel, self.camera_controls, self.preview_controls)
        scroll = QScrollArea()
        scroll.setWidget(side)
        scroll.setWidgetResizable(True)
        scroll.setMinimumWidth(side.sizeHint().width()
                               + scroll.verticalScrollBar().sizeHint().width() + 4)
        scroll.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.controls_dock = QDockWidget("Controls", self)
        self.controls_dock.setObjectName("controls-dock")
        self.controls_dock.setWidget(scroll)
        self.addDockWidget(Qt.DockWidgetArea.LeftDockWidgetArea, self.controls_dock)
        self.status_label = QLabel("")
        never_wider(self.status_label)
        self.statusBar().addWidget(self.status_label, 1)

        # preview
        # a bad key keeps its default; the other preview settings are kept
        # (a number outside its range, RANGES, is clamped: the controls show what runs)
        ps, problems = PreviewSettings.from_dict_lenient(self.settings.preview)
        if problems:
            _log.warning("preview settings: ignoring %s", "; ".join(problems))
            self._status("preview settings: ignoring " + "; ".join(problems))
        self.settings.preview = ps.to_dict()
        self.preview_controls.set_settings(ps)
        self.preview_controls.enabled.setChecked(self.settings.preview_enabled)
        if not self.settings.preview_enabled:  # an empty panel said nothing at start
            self.preview_panel.set_message(_PREVIEW_OFF)
        self.engine = PreviewEngine(None, ps)
        self.preview_worker = PreviewWorker(self.engine)
        self.preview_worker.result.connect(self._on_preview)
        self.preview_worker.error.connect(self._on_preview_error)

        # timers
        self.poll_timer = QTimer(self)
        self.poll_timer.setInterval(max(5, round(1000.0 / max(1.0, self.settings.display_hz))))
        self.poll_timer.timeout.connect(self._poll)
        self._reconnect_cancel = threading.Event()  # the attempt under way's (set: ended)
        self.reconnect_timer = QTimer(self)
        self.reconnect_timer.setSingleShot(True)
        self.reconnect_timer.setInterval(self.reconnect_interval_ms)
        self.reconnect_timer.timeout.connect(self._try_reconnect_camera)
        self.light_timer = QTimer(self)
        self.light_timer.setInterval(int(light_check_interval_ms))
        self.light_timer.timeout.connect(self._check_light)
        self.readout_timer = QTimer(self)
        self.readout_timer.setInterval(250)
        self.readout_timer.timeout.connect(self._update_readouts)
        self.readout_timer.start()

        self._connect_signals()
        self._build_menu()
        self._build_docks()
        if self.jobs_panel.folder_problem is not None:  # also logged by the panel
            self._status(self.jobs_panel.folder_problem)
        self.device_panel.set_scene(self.settings.sim_scene)
        with QSignalBlocker(self.device_panel.intensity):
            self.device_panel.intensity.setValue(min(max(self.settings.light_intensity, 0.0), 1.0))
        self.camera_controls.show_roi.setChecked(self.settings.show_roi)
        self.device_panel.show_demo.setChecked(self.settings.show_demo_cameras)
        # discovery may block (GenTL producers): the lists fill in from the worker
        self.device_panel.set_cameras([SIM_CAMERA_CHOICE], self.settings.camera)
        self.device_panel.set_ports([SIM_PORT_CHOICE], self.settings.light_port)
        self._restore_geometry()
        if self.settings.psf_path:
            self._load_psf(self.settings.psf_path, at_start=True)
        if autoconnect:
            self.connect_camera(self.settings.camera or SIM_CAMERA)
            if self.settings.connect_light and self.settings.light_port:
                self.connect_light(self.settings.light_port)
        self.refresh_devices()

    # -- wiring --------------------------------------------------------------------------------

    def _connect_signals(self) -> None:
        dp = self.device_panel
        dp.refresh_requested.connect(self.refresh_devices)
        dp.show_demo_changed.connect(self._show_demo_changed)
        dp.connect_camera_requested.connect(self.connect_camera)
        dp.disconnect_camera_requested.connect(self.disconnect_camera)
        dp.scene_changed.connect(self.set_scene)
        dp.connect_light_requested.connect(self.connect_light)
        dp.disconnect_light_requested.connect(self.disconnect_light)
        dp.light_on_changed.connect(self.set_light_on)
        dp.intensity_changed.connect(self.set_light_intensity)
        cc = self.camera_controls
        cc.live_toggled.connect(self.set_live)
        cc.property_changed.connect(self.set_camera_property)
        cc.snap_requested.connect(self.snap_and_save)
        cc.save_as_requested.connect(self._save_as)
        cc.roi_visible_changed.connect(self.raw_panel.set_roi_visible)
        cc.roi_apply_requested.connect(self.apply_roi)
        cc.roi_reset_requested.connect(self.reset_roi)
        pc = self.preview_controls
        pc.settings_changed.connect(self.set_preview_settings)
        pc.enabled_changed.connect(self._preview_enabled)
        pc.load_psf_requested.connect(self._choose_psf)
        pc.reset_requested.connect(self.engine.reset)

    def _build_menu(self) -> None:
        m = self.menuBar().addMenu("&File")
        act = QAction("Snap && save", self)
        act.setShortcut("Ctrl+S")
        act.triggered.connect(self.snap_and_save)
        m.addAction(act)
        act = QAction("Load PSF…", self)
        act.triggered.connect(self._choose_psf)
        m.addAction(act)
        m.addSeparator()
        act = QAction("Quit", self)
        act.setShortcut("Ctrl+Q")
        act.triggered.connect(self.close)
        m.addAction(act)
        self.view_menu = self.menuBar().addMenu("&View")
        self.tools_menu = self.menuBar().addMenu("&Tools")
        self.toolbar = self.addToolBar("Main")
        self.toolbar.setObjectName("main-toolbar")
        self.toolbar.addAction(m.actions()[0])
        self.calibration_action = QAction("Calibration wizard…", self)
        self.calibration_action.triggered.connect(self.open_calibration_wizard)
        self.tools_menu.addAction(self.calibration_action)
        self.toolbar.addAction(self.calibration_action)
        self.calibration_wizard: Any = None

    def _build_docks(self) -> None:
        """UDN jobs and the speed/accuracy trade: bottom docks, tabbed; the View menu."""
        if not self.settings.jobs_dir:
            self.settings.jobs_dir = str(default_jobs_dir())
        self.jobs_panel = JobsPanel(self.settings.jobs_dir, self.current_measurement, self,
                                    poll_ms=self._jobs_poll_ms, spawn=self._job_spawn)
        self.jobs_panel.last_job = dict(self.settings.last_job)
        self.jobs_dock = self._dock("UDN jobs", "jobs-dock", self.jobs_panel)
        self.trade_panel = TradePanel(self.current_measurement, self.set_preview_tau, self)
        self.trade_panel.measuring.connect(self._hold_preview)
        self.trade_dock = self._dock("Speed / accuracy trade", "trade-dock", self.trade_panel)
        self.addDockWidget(Qt.DockWidgetArea.BottomDockWidgetArea, self.jobs_dock)
        self.addDockWidget(Qt.DockWidgetArea.BottomDockWidgetArea, self.trade_dock)
        self.tabifyDockWidget(self.jobs_dock, self.trade_dock)
        self.jobs_dock.raise_()
        self.trade_dock.hide()
        for dock, text in ((self.controls_dock, "Controls"), (self.jobs_dock, "UDN jobs panel"),
                           (self.trade_dock, "Speed/accuracy trade panel")):
            act = dock.toggleViewAction()
            act.setText(text)
            self.view_menu.addAction(act)
        act = QAction("New UDN job…", self)
        act.triggered.connect(self.jobs_panel.new_job_dialog)
        self.toolbar.addAction(act)

    def _dock(self, title: str, name: str, widget: QWidget) -> QDockWidget:
        dock = QDockWidget(title, self)
        dock.setObjectName(name)
        dock.setWidget(widget)
        return dock

    def open_calibration_wizard(self) -> Any:
        """Show the calibration wizard: one per window (non-modal), made on first use.

        Reopened, it is the same wizard: a run still ending is shown as it is (so it stays
        reachable), else its first page with what was typed this session.
        """
        from app.gui.calibration_wizard import CalibrationWizard

        wiz = self.calibration_wizard
        if wiz is None:
            wiz = CalibrationWizard(self)
            self.calibration_wizard = wiz
        elif not wiz.isVisible():
            wiz.reopen()
        wiz.show()
        wiz.raise_()
        return wiz

    def current_measurement(self) -> Measurement | None:
        """The newest frame with the preview's PSF and dark level (for jobs and the trade)."""
        if self.last_frame is None:
            return None
        return Measurement(self.last_frame, self.engine.psf, self.psf_source,
                           self.settings.psf_path, self.engine.settings.dark)

    def set_preview_tau(self, tau: float) -> None:
        """Use ``tau`` in the preview (controls and engine), the automatic tau switched off.

        With *auto* on (the default) the engine kept its own estimate and the tau given was
        put in the box and ignored; the status line says that *auto* went off.
        """
        import dataclasses

        from app.gui.preview_engine import clamp_setting

        if not math.isfinite(tau):
            self.show_error(f"tau {tau!r} is not a number; the preview keeps its tau")
            return
        was_auto = self.preview_controls.settings().tau_auto
        s = dataclasses.replace(self.preview_controls.settings(),
                                tau=clamp_setting("tau", float(tau)), tau_auto=False)
        self.preview_controls.set_settings(s)
        self.set_preview_settings(s)
        if was_auto:
            self._status(f"preview tau {s.tau:.3g}: automatic tau off (tick auto to choose "
                         "it from the frame again)")

    # -- states ----------------------------------------------------------------------------

    @property
    def camera_state(self) -> CameraState:
        """The camera's state (:class:`~app.devices_state.CameraState`, a str-Enum)."""
        return self.devices.camera

    @property
    def light_state(self) -> LightState:
        """The point source's state (:class:`~app.devices_state.LightState`, a str-Enum)."""
        return self.devices.light

    @property
    def reconnect_attempts(self) -> int:
        """Reconnect attempts since the camera was lost."""
        return self.devices.reconnect_attempts

    # -- messages ------------------------------------------------------------------------------

    def show_error(self, text: str, source: str = "other") -> None:
        """Show ``text`` in the banner (empty: hide it).

        ``source`` (camera, light, other) says which device's success may clear it
        (:meth:`clear_error`).
        """
        self.last_error = text or self.last_error
        self.banner.setText(text)
        self.banner.setVisible(bool(text))
        self._banner_source = source if text else ""

    def clear_error(self, *sources: str) -> None:
        """Hide the banner if it shows an error of one of ``sources``.

        A point source that connects clears a point-source error and leaves a camera's (and a
        camera that connects leaves a point source's: it stayed until the camera connected).
        """
        if self.banner.isVisible() and self._banner_source in sources:
            self.show_error("")

    def _status(self, text: str) -> None:
        self.status_label.setText(text)

    def _set_camera_state(self, state: CameraState | str, text: str = "",
                          kind: str = "off") -> None:
        st = CameraState(state)
        set_status(self.device_panel.camera_status, text or st.value, kind)
        self.camera_controls.set_connected(st.connected)
        self.device_panel.set_camera_connected(st is not CameraState.DISCONNECTED,
                                               self.bench.is_simulated)
        self.device_panel.set_busy(st is CameraState.CALIBRATING)
        self.camera_controls.set_live(st is CameraState.LIVE)
        if st is CameraState.LIVE:
            self.poll_timer.start()
        else:
            self.poll_timer.stop()
        self.devices.set_camera(st)

    # -- camera --------------------------------------------------------------------------------

    def refresh_devices(self) -> None:
        """List cameras and serial ports again (on the camera worker: discovery may block)."""
        show_demo = self.device_panel.show_demo.isChecked()

        def work() -> tuple[Any, Any]:
            return list_camera_choices(show_demo), list_port_choices()

        def done(r: tuple[Any, Any]) -> None:
            cams = list(r[0])
            spec = self.bench.camera_spec
            if spec and spec not in {c.spec for c in cams}:
                # an open device may be missing from discovery (a GenTL producer does not
                # list a device that is open): keep it selectable
                cams.append(CameraChoice(spec, spec.partition(":")[0], f"{spec} (open)"))
            self.device_panel.set_cameras(cams, spec or self.settings.camera)
            self.device_panel.set_ports(r[1], self.bench.light_port or self.settings.light_port)
            self._status(f"{len(cams)} camera(s), {len(r[1])} point-source port(s) found")

        self.camera_queue.submit(work, name="refresh", on_done=done,
                                 on_error=lambda e: self.show_error(f"refresh: {_describe(e)}"))

    def _show_demo_changed(self, on: bool) -> None:
        self.settings.show_demo_cameras = on
        self.refresh_devices()

    def connect_camera(self, spec: str) -> None:
        """Open camera ``spec`` (closing the current one), apply the settings, start live."""
        self._cancel_reconnect()
        self.poll_timer.stop()
        self._set_camera_state("connecting", f"connecting to {spec}…", "busy")
        s = self.settings
        bench = self.bench

        def work() -> tuple[dict[str, Any], dict[str, Any]]:
            cam = bench.open_camera(spec)
            for name, value in (("exposure_us", s.exposure_us), ("gain", s.gain),
                                ("frame_rate_hz", s.frame_rate_hz),
                                ("shutter_mode", s.shutter_mode)):
                if value in ("", None):
                    continue
                try:
                    setattr(cam, name, value)
                except Exception as exc:  # a saved value the device refuses: keep its own
                    _log.info("%s: not restoring %s=%r: %s", spec, name, value, exc)
            cam.start_live()
            return _read_camera(cam)

        def done(r: tuple[dict[str, Any], dict[str, Any]]) -> None:
            values, ranges = r
            self.settings.camera = spec
            self._camera_values(values, ranges)
            desc = values.get("model") or spec
            self._camera_name = f"{spec}: {desc}"
            self._set_camera_state("live", f"{self._camera_name} – live", "ok")
            self.clear_error("camera", "other")
            self._configure_psf_for_camera()

        def failed(exc: BaseException) -> None:
            msg = f"Camera {spec}: cannot connect: {_describe(exc)}"
            self._set_camera_state("disconnected", msg, "error")
            self.show_error(msg, "camera")

        self.camera_queue.submit(work, name=f"connect {spec}", on_done=done, on_error=failed)

    def _camera_values(self, values: dict[str, Any], ranges: dict[str, Any]) -> None:
        """Show what the camera reports, and remember those (not the asked) values."""
        self.camera_controls.show_values(values, ranges)
        for name in ("exposure_us", "gain", "frame_rate_hz", "shutter_mode"):
            v = values.get(name)
            if v is not None:
                setattr(self.settings, name, str(v) if name == "shutter_mode" else float(v))
        bd = values.get("bit_depth")
        self._bit_depth = int(bd) if bd else None
        self.raw_panel.saturation_level = (1 << self._bit_depth) - 1 if self._bit_depth else None

    def _configure_psf_for_camera(self) -> None:
        if self.settings.psf_path:
            return
        if self.bench.is_simulated:
            self.engine.set_psf(self.bench.sim_psf)
            self.psf_source = "simulated bench (tutorial PSF)"
        else:
            self.engine.set_psf(None)
            self.psf_source = ""
            self.preview_panel.set_message(
                "no PSF for this camera: load one (File > Load PSF) or run the calibration "
                "wizard")
        self._show_psf_label()

    def _show_psf_label(self) -> None:
        # a long file name has no spaces to wrap at: allow breaks after _ - . / (zero-width
        # spaces), or the label widens the controls past the window at 1366x768
        src = str(self.psf_source or "")
        shown = re.sub(r"([_\-./])", "\\1\u200b", src)
        text = f"PSF: {shown}" if src else "PSF: none – load one or run the calibration wizard"
        self.preview_controls.psf_label.setText(text)
        self.preview_controls.psf_label.setToolTip(src)

    def _cancel_reconnect(self) -> None:
        """Stop reconnect attempts, and end one under way within its next 0.2 s slice."""
        self.reconnect_timer.stop()
        self._reconnect_cancel.set()

    def disconnect_camera(self) -> None:
        """Stop and close the camera (also stops reconnect attempts)."""
        self._cancel_reconnect()
        self._set_camera_state("disconnected", "disconnecting…", "busy")
        bench = self.bench

        def done(_r: Any) -> None:
            self._set_camera_state("disconnected", "not connected", "off")
            self.clear_error("camera", "other")

        self.camera_queue.submit(bench.close_camera, name="disconnect", on_done=done,
                                 on_error=lambda e: done(None))

    def set_live(self, on: bool) -> None:
        """Start or stop the live stream."""
        cam = self.bench.camera
        if cam is None:
            return
        self.poll_timer.stop()
        self._set_camera_state("reconfiguring", "starting…" if on else "stopping…", "busy")

        def work() -> None:
            cam.stop()
            if on:
                cam.start_live()

        def done(_r: Any) -> None:
            self._set_camera_state("live" if on else "stopped",
                                   f"{self._camera_name} – "
                                   + ("live" if on else "stopped (not streaming)"), "ok")

        self.camera_queue.submit(work, name="live", on_done=done, on_error=self._camera_failed)

    def set_camera_property(self, name: str, value: Any) -> None:
        """Set one camera property (on the worker); the controls then show what it reports."""
        cam = self.bench.camera
        if cam is None or value is None:
            return

        def work() -> tuple[dict[str, Any], dict[str, Any]]:
            setattr(cam, name, value)
            return _read_camera(cam)

        def failed(exc: BaseException) -> None:
            self._status(f"{name} = {value!r} refused: {_describe(exc)}")
            self.show_error(f"Camera: {name} = {value!r} refused: {_describe(exc)}", "camera")
            self.camera_queue.submit(lambda: _read_camera(cam), name="read back",
                                     on_done=lambda r: self._camera_values(*r))

        self.camera_queue.submit(work, name=f"set {name}",
                                 on_done=lambda r: self._camera_values(*r), on_error=failed)

    def set_scene(self, name: str) -> None:
        """Change the simulated camera's scene."""
        self.settings.sim_scene = name
        cam = self.bench.camera
        if cam is None or not self.bench.is_simulated:
            return
        from app.gui.devices import set_sim_scene

        sim = self.bench.sim
        self.camera_queue.submit(lambda: set_sim_scene(cam, name, sim.peak_fraction,
                                                       sim.scene_fill), name="scene",
                                 on_error=lambda e: self.show_error(f"scene: {_describe(e)}"))

    def apply_roi(self) -> None:
        """Set the camera's ROI to the rectangle drawn on the raw frame (restarts live)."""
        rect = self.raw_panel.roi_rect()
        frame = self.last_frame
        if rect is None or frame is None:
            self._status("show the ROI and draw it on the raw frame first")
            return
        from drivers.camera import Roi

        b = frame.binning
        x, y, w, h = rect
        roi = Roi(frame.roi.x + x * b, frame.roi.y + y * b, w * b, h * b)
        self._reconfigure(lambda cam: setattr(cam, "roi", roi), f"ROI {roi.width}x{roi.height}")

    def reset_roi(self) -> None:
        """Full-sensor ROI (restarts live)."""
        def full(cam: Any) -> None:
            from drivers.camera import Roi

            caps = cam.capabilities()
            cam.roi = Roi(0, 0, caps.sensor_width, caps.sensor_height)

        self._reconfigure(full, "full sensor")

    def _reconfigure(self, change: Any, what: str) -> None:
        cam = self.bench.camera
        if cam is None:
            return
        if self.camera_state is CameraState.RECONFIGURING:
            # a second click while the first change runs: live as before the first (it read
            # "not live" and left the camera stopped with a green status line)
            was_live = self._live_before_reconfigure
        else:
            was_live = self.camera_state is CameraState.LIVE
            self._live_before_reconfigure = was_live
        self._set_camera_state("reconfiguring", f"setting {what}…", "busy")

        def work() -> tuple[dict[str, Any], dict[str, Any]]:
            cam.stop()
            try:
                change(cam)
            finally:
                if was_live:
                    cam.start_live()
            return _read_camera(cam)

        def done(r: tuple[dict[str, Any], dict[str, Any]]) -> None:
            self._camera_values(*r)
            self.engine.reset()
            self._set_camera_state("live" if was_live else "stopped", what, "ok")

        def failed(exc: BaseException) -> None:
            self.show_error(f"Camera: {what}: {_describe(exc)}", "camera")
            self._set_camera_state("live" if was_live else "stopped", f"{what} failed", "error")

        self.camera_queue.submit(work, name=what, on_done=done, on_error=failed)

    def _camera_failed(self, exc: BaseException) -> None:
        """A camera task failed: the device may be gone; try to reconnect."""
        self._camera_lost(exc)

    # -- live view -----------------------------------------------------------------------------

    def _poll(self) -> None:
        if self.camera_state is not CameraState.LIVE:
            return
        cam = self.bench.camera
        if cam is None:
            return
        try:
            frame = cam.latest_frame(0.0)
        except Exception as exc:  # the stream ended with an error: the device is lost
            self._camera_lost(exc)
            return
        if frame is not None:
            self._show_frame(frame)

    def _show_frame(self, frame: Any) -> None:
        prev, self.last_frame = self.last_frame, frame
        if prev is None or frame_source(prev) != frame_source(frame):
            self.trade_panel.notice_source()  # a trade measured on the other no longer holds
        self.raw_panel.set_image(frame.pixels)
        now = time.time()
        self._latency_ms.append((now - frame.timestamp) * 1000.0)
        self._display_rate.tick()
        self._camera_rate.tick(frame.timestamp)
        self.frames_shown += 1
        if (self.preview_controls.enabled.isChecked() and self.engine.has_psf
                and not self._preview_held):
            known = self.raw_panel.saturation_level is not None
            refusal, warning = saturation_verdict(
                self.raw_panel.saturated if known else 0, frame.pixels.size)
            if refusal is not None:
                self.frames_skipped_saturated += 1
                self.preview_panel.set_message(refusal)
            else:
                if warning:
                    self.preview_panel.set_message(warning)
                elif self.preview_panel.message.text().startswith("warning:"):
                    self.preview_panel.set_message("")
                self.preview_worker.submit(frame)
        self.frame_shown.emit(frame)

    def _update_readouts(self) -> None:
        parts: list[str] = []
        cam = self.bench.camera
        if self.camera_state is CameraState.LIVE and cam is not None:
            try:
                stats = cam.stream_stats()
                dropped = stats.dropped
                bad = int(getattr(stats, "bad", 0))  # frames the stream skipped as bad
                last_bad = getattr(stats, "last_bad", None)
            except Exception:
                dropped, bad, last_bad = -1, 0, None
            self.raw_panel.footer.setToolTip(f"last bad frame: {last_bad}" if bad else "")
            lat = float(np.median(self._latency_ms)) if self._latency_ms else float("nan")
            parts.append(f"camera {self._camera_rate.rate():.1f} fps")
            parts.append(f"shown {self._display_rate.rate():.1f} fps")
            parts.append(f"dropped {dropped}" + (f", bad {bad}" if bad else ""))
            parts.append(f"latency {lat:.0f} ms")
            if self.raw_panel.saturation_level is not None:
                parts.append(f"saturated {self.raw_panel.saturated} px")
            st = self.raw_panel.roi_stats()
            if st is not None:
                parts.append(f"ROI mean {st[0]:.0f} max {st[1]:.0f}")
            if self.last_frame is not None:
                parts.append(frame_geometry(self.last_frame))
        else:
            parts.append(self.camera_state)
        self.raw_panel.footer.setText(" · ".join(parts))
        ps = self.preview_worker.slot.stats()
        if self._preview_latency_ms:
            plat = float(np.median(self._preview_latency_ms))
            self.preview_panel.footer.setText(
                f"preview {self._preview_rate.rate():.1f}/s · latency {plat:.0f} ms · "
                f"stale dropped {ps.dropped} · {self._last_preview_info}"
            )

    _last_preview_info = ""
    _camera_name = "camera"

    # -- loss and reconnection ----------------------------------------------------------------

    def _camera_lost(self, exc: BaseException) -> None:
        if not self.devices.camera_failed():
            return
        msg = f"Camera lost – reconnecting…: {_describe(exc)}"
        self._set_camera_state(CameraState.LOST, msg, "error")
        self.show_error(msg, "camera")
        self._status(msg)  # not the last "reconnected after N attempt(s)" beside the banner
        self.reconnect_timer.start()

    def _try_reconnect_camera(self) -> None:
        n = self.devices.next_reconnect()
        if n is None:
            return
        bench = self.bench

        cancel = self._reconnect_cancel = threading.Event()  # set by Disconnect / Connect

        def work() -> tuple[dict[str, Any], dict[str, Any], Any]:
            cam = bench.camera
            if cam is None:
                raise RuntimeError("no camera")
            best_effort(f"stopping {cam.describe()} before reconnecting", cam.stop)
            frame = bench.reconnect_camera(
                check_timeout_s=min(2.0, self.reconnect_interval_ms / 1000), cancel=cancel)
            return (*_read_camera(cam), frame)

        def done(r: tuple[dict[str, Any], dict[str, Any], Any]) -> None:
            if self.camera_state is not CameraState.LOST:
                return
            values, ranges, frame = r
            self._camera_values(values, ranges)
            self._set_camera_state(CameraState.LIVE, f"reconnected after {n} attempt(s) – live",
                                   "ok")
            self.clear_error("camera", "other")
            self._status(f"camera reconnected after {n} attempt(s)")
            self._show_frame(frame)  # the check's frame: at a long exposure the next is late

        def failed(exc: BaseException) -> None:
            if isinstance(exc, ReconnectCancelled) or self.devices.closing:
                return  # ended by Disconnect, another camera or the window closing
            if not self.devices.reconnect_result(False):
                return
            msg = f"Camera lost – reconnect attempt {n} failed, retrying…: {_describe(exc)}"
            set_status(self.device_panel.camera_status, msg, "error")
            self.show_error(msg, "camera")
            self.reconnect_timer.start()

        self.camera_queue.submit(work, name="reconnect camera", on_done=done, on_error=failed)

    # -- point source --------------------------------------------------------------------------

    def _set_light_state(self, state: LightState | str, text: str, kind: str) -> None:
        st = LightState(state)
        set_status(self.device_panel.light_status, text, kind)
        self.device_panel.set_light_connected(st is LightState.CONNECTED)
        if st.watched:
            self.light_timer.start()
        else:
            self.light_timer.stop()
        self.devices.set_light(st)

    def connect_light(self, port: str) -> None:
        """Connect the point source on ``port`` (``sim``: spawn the simulated firmware)."""
        if not port:
            return
        self._set_light_state("connecting", f"connecting to {port}…", "busy")
        bench = self.bench

        def work() -> Any:
            light = bench.open_light(port)
            return light.identify(), light.status()

        def done(r: Any) -> None:
            ident, st = r
            self.settings.light_port = port
            self.settings.connect_light = True
            self._set_light_state("connected", f"{ident}", "ok")
            self.device_panel.show_light_state(st.is_on, st.intensity)
            self.clear_error("light")  # an earlier failure of the point source is over

        def failed(exc: BaseException) -> None:
            msg = f"Point source {port}: cannot connect: {_describe(exc)}"
            self._set_light_state("disconnected", msg, "error")
            self.show_error(msg, "light")

        self.light_queue.submit(work, name="connect light", on_done=done, on_error=failed)

    def disconnect_light(self) -> None:
        """Switch the source off and close it."""
        self.settings.connect_light = False
        self._set_light_state("disconnected", "disconnecting…", "busy")
        def done(_r: Any) -> None:
            self._set_light_state("disconnected", "not connected", "off")
            self.clear_error("light")  # disconnected on purpose: its error is not news

        self.light_queue.submit(self.bench.close_light, name="disconnect light", on_done=done,
                                on_error=done)

    def set_light_on(self, on: bool) -> None:
        """Switch the source on (at the set intensity) or off."""
        bench = self.bench
        level = float(self.device_panel.intensity.value())

        def work() -> Any:
            light = bench.light
            if light is None:
                raise RuntimeError("no point source connected")
            if on:
                light.set_intensity(level)
                light.on()
            else:
                light.off()
            return light.status()

        self.light_queue.submit(work, name="light on/off", on_done=self._light_status,
                                on_error=self._light_lost)

    def set_light_intensity(self, value: float) -> None:
        """Set the source's intensity."""
        bench = self.bench

        def work() -> Any:
            if bench.light is None:
                raise RuntimeError("no point source connected")
            bench.light.set_intensity(float(value))
            return bench.light.status()

        self.light_queue.submit(work, name="intensity", on_done=self._light_status,
                                on_error=self._light_lost)

    def _light_status(self, st: Any) -> None:
        self.device_panel.show_light_state(st.is_on, st.intensity)
        if self.light_state is LightState.LOST:
            self._set_light_state(LightState.CONNECTED, f"reconnected: {st.identity}", "ok")
            self.clear_error("light")

    def _check_light(self) -> None:
        action = self.devices.light_check(self.light_queue.busy)
        if action is LightAction.NOTHING:
            return
        bench = self.bench
        if action is LightAction.RECONNECT:
            self.light_queue.submit(lambda: (bench.reconnect_light(), bench.check_light())[1],
                                    name="reconnect light", on_done=self._light_status,
                                    on_error=self._light_still_lost)
        else:
            self.light_queue.submit(bench.check_light, name="check light",
                                    on_done=self._light_status, on_error=self._light_lost)

    def _light_lost(self, exc: BaseException) -> None:
        if not self.light_state.watched:
            self.show_error(f"Point source: {_describe(exc)}", "light")
            return
        msg = f"Point source lost – reconnecting…: {_describe(exc)}"
        self._set_light_state(LightState.LOST, msg, "error")
        self.show_error(msg, "light")

    def _light_still_lost(self, exc: BaseException) -> None:
        if self.light_state is LightState.LOST:
            msg = f"Point source lost – retrying…: {_describe(exc)}"
            set_status(self.device_panel.light_status, msg, "error")
            self.show_error(msg, "light")

    # -- preview -------------------------------------------------------------------------------

    def set_preview_settings(self, s: PreviewSettings) -> None:
        """New preview settings (applied at the next frame)."""
        self.settings.preview = s.to_dict()
        self.engine.set_settings(s)

    def _preview_enabled(self, on: bool) -> None:
        self.settings.preview_enabled = on
        if not on:
            self.preview_panel.set_message(_PREVIEW_OFF)
        elif self.preview_panel.message.text() == _PREVIEW_OFF:  # on again, camera stopped
            self.preview_panel.set_message("")

    def _hold_preview(self, held: bool) -> None:
        """Hold the live preview while the trade panel measures, and say so.

        The preview's FISTA on the same cores made a trade's wall times about twice what they
        are alone (0.93 s against 0.46 s for one setting): a budget chosen from them was wrong.
        """
        self._preview_held = held
        if held:
            self.preview_panel.set_message(_PREVIEW_HELD)
        elif self.preview_panel.message.text() == _PREVIEW_HELD:
            self.preview_panel.set_message("")

    def _on_preview(self, res: PreviewResult) -> None:
        note = self.preview_panel.message.text()
        self.preview_panel.set_image(res.image, res.levels)
        if note.startswith("warning:"):
            self.preview_panel.set_message(note)
        elif not self.settings.preview_enabled:  # a frame that was under way when it went off
            self.preview_panel.set_message(_PREVIEW_OFF)
        self._preview_rate.tick()
        self._preview_latency_ms.append(res.latency_s * 1000.0)
        self._last_preview_info = (f"{res.shape[1]}x{res.shape[0]} · {res.iterations} it/frame"
                                   f"{' (rate-limited)' if res.note else ''} · residual "
                                   f"{res.residual:.3f}"
                                   f"{' · ' + res.tau_note if res.tau_note else ''}"
                                   f"{' · ' + res.dark_note if res.dark_note else ''}"
                                   f"{' · ' + res.model_note if res.model_note else ''}")
        self.previews_shown += 1
        self.preview_shown.emit(res)

    def _on_preview_error(self, text: str) -> None:
        self.preview_panel.set_message(text)

    def _choose_psf(self) -> None:
        path, _ = QFileDialog.getOpenFileName(
            self, "Load PSF", self.settings.calibration_dir or str(Path.home()),
            "PSF (*.tif *.tiff *.npy *.npz *.png *.mat);;All files (*)")
        if path:
            self._load_psf(path)

    def _load_psf(self, path: str, *, at_start: bool = False) -> bool:
        """Use the PSF in ``path`` for the preview (a calibration file or an image).

        A PSF that cannot serve the running camera's frames (another sensor size) is refused
        and the preview keeps its PSF: it replaced it and was remembered, so every frame failed,
        after a restart too. ``at_start``: the last session's PSF; when it cannot be loaded the
        banner says so and the preview takes the bench's default (it showed "PSF: none").
        """
        from app.gui.preview_engine import psf_sensor_problem
        from recon.inputwarnings import collect_input_warnings

        try:
            # this thread's PSF warnings only (a catch of warnings is process-wide), shown in
            # the banner and the log below, not on stderr
            with collect_input_warnings(emit=False) as doubts:
                psf = load_psf_any(path)
            planes = psf.shape[0] if psf.ndim == 3 and psf.shape[0] > 1 else 0
            if planes:
                raise ValueError(_stack_message(planes))
            # the running camera's (a frame of a camera since disconnected refused a PSF)
            frame = self.last_frame if self.camera_state is CameraState.LIVE else None
            sensor = getattr(frame, "sensor", None) if frame is not None else None
            if sensor is not None:
                roi = frame.roi
                problem = psf_sensor_problem(psf.shape, sensor=sensor, binning=frame.binning,
                                             roi=(roi.x, roi.y, roi.width, roi.height))
                if problem is not None:
                    raise ValueError(f"{problem} (not loaded: the preview keeps its PSF)")
            self.engine.set_psf(psf)
        except Exception as exc:
            planes = _psf_stack_planes(path) if isinstance(exc, ValueError) else 0
            text = _stack_message(planes) if planes else _describe(exc)
            _log.warning("PSF %s: %s", path, exc)
            if at_start:  # not the bench's default kept silently behind a remembered path
                self.settings.psf_path = ""
                self.show_error(f"PSF {path} of the last session: {text}; not used (Load "
                                "PSF… to choose one)", "psf")
            else:
                self.show_error(f"PSF {path}: {text}", "psf")
            return False
        self.clear_error("psf")  # an earlier load's refusal is not this PSF's
        self.settings.psf_path = str(path)
        self.psf_source = f"{Path(path).name} ({psf.shape[-2]}x{psf.shape[-1]})"
        self._show_psf_label()
        for d in doubts:
            _log.warning("PSF %s: %s", path, d)
        if doubts:  # loaded, but the user should know (it went to stderr only)
            self.show_error(f"PSF {Path(path).name} loaded, but: {'; '.join(doubts)}", "psf")
        return True

    def use_psf(self, psf: Any, source: str, path: str = "") -> None:
        """Use ``psf`` for the preview (from the calibration wizard)."""
        self.engine.set_psf(psf)
        self.settings.psf_path = path
        self.psf_source = source
        self._show_psf_label()

    # -- workflows (calibration) ---------------------------------------------------------------

    def run_camera_workflow(
        self,
        make_steps: Any,
        *,
        name: str,
        hide_scene: bool = False,
        on_progress: Any = None,
        on_done: Any = None,
        on_error: Any = None,
    ) -> WorkflowHandle:
        """Run a calibration workflow on the camera's worker, the live view paused.

        ``make_steps(camera, light_source)`` returns the workflow's generator. Progress, the
        result and errors arrive on the GUI thread; the live view resumes afterwards.
        ``hide_scene``: with the simulated camera, show no scene meanwhile (point source only).
        """
        from calibration.workflow import Workflow

        handle = WorkflowHandle()
        cam, light = self.bench.camera, self.bench.light
        if cam is None or not self.camera_state.ready:
            exc = RuntimeError(f"the camera is not ready ({self.camera_state})")
            if on_error is not None:
                on_error(exc)
            return handle
        was_live = self.camera_state is CameraState.LIVE
        wf = Workflow(make_steps(cam, light), name)  # nothing runs until iterated
        handle.workflow = wf
        hide = hide_scene and self.bench.is_simulated
        self._set_camera_state("calibrating", f"{name} running…", "busy")

        def work() -> Any:
            cam.stop()
            scene = cam.scene if hide else None
            if hide:
                cam.scene = None
            try:
                yield from wf
                return wf.result
            finally:
                if hide:
                    cam.scene = scene
                if was_live:
                    best_effort(f"restarting live view on {cam.describe()}", cam.start_live)

        def resume() -> None:
            if self.camera_state is CameraState.CALIBRATING:
                self._set_camera_state("live" if was_live else "stopped",
                                       f"{self._camera_name} – "
                                       + ("live" if was_live else "stopped"), "ok")
            # a workflow changes settings (auto-exposure): show what the camera runs at now
            self.camera_queue.submit(lambda: _read_camera(cam), name="read back",
                                     on_done=lambda r: self._camera_values(*r))

        def done(result: Any) -> None:
            resume()
            if on_done is not None:
                on_done(result)

        def failed(exc: BaseException) -> None:
            resume()
            if on_error is not None:
                on_error(exc)

        handle.task = self.camera_queue.submit(work, name=name, on_done=done, on_error=failed,
                                               on_progress=on_progress)
        return handle

    # -- snap & save ---------------------------------------------------------------------------

    def save_dir(self) -> Path:
        """Folder for snapshots."""
        from app.locations import default_snaps_dir

        return Path(self.settings.save_dir or default_snaps_dir())

    def snap_and_save(self, path: str | Path | None = None, *,
                      remember: Path | None = None) -> None:
        """Save the newest frame (live) or snap one (stopped), with its metadata.

        ``remember``: the folder that becomes the save folder once the save worked (a failed
        Save as… moved it first, and every later Snap & save failed, after a restart too).
        """
        target = Path(path) if path else self.save_dir()
        extra = {"camera_spec": self.bench.camera_spec,
                 "scene": self.settings.sim_scene if self.bench.is_simulated else None}
        from app.gui.snapshots import save_frame

        cam = self.bench.camera
        frame = self.last_frame if self.camera_state is CameraState.LIVE else None
        if frame is None and cam is None:
            self.show_error("Snap: no camera connected", "snap")
            return

        def work() -> list[Path]:
            f = frame if frame is not None else cam.snap()
            self.last_saved_frame = f
            return save_frame(f, target, extra)

        def done(paths: list[Path]) -> None:
            if remember is not None:
                self.settings.save_dir = str(remember)
            self.last_saved = paths[0]
            self.camera_controls.save_info.setText(f"saved {paths[0]}")
            self._status(f"saved {paths[0]}")
            self.clear_error("snap")  # a save that works ends the last one's error

        def failed(exc: BaseException) -> None:
            self.camera_controls.save_info.setText("not saved")  # not the last file's "saved"
            self.show_error(f"Snap: {_describe(exc)}", "snap")

        self.camera_queue.submit(work, name="snap", on_done=done, on_error=failed)

    last_saved: Path | None = None
    last_saved_frame: Any = None

    def _save_as(self) -> None:
        path, _ = QFileDialog.getSaveFileName(self, "Save frame", str(self.save_dir()),
                                              "TIFF (*.tif)")
        if path:
            if Path(path).is_dir():  # a folder chosen: the frame's own name in it (it was
                # written as '<folder>.tif' beside it)
                self.snap_and_save(path, remember=Path(path))
                return
            if Path(path).suffix.lower() not in {".tif", ".tiff", *_OTHER_FILE_TYPES}:
                # the dialog's TIFF filter: 'name' made a folder 'name/', 'exp_2.5ms' was
                # refused as a '.5ms' file; another file type (.png) is still said to be one
                path += ".tif"
            self.snap_and_save(path, remember=Path(path).parent)

    # -- settings and closing ------------------------------------------------------------------

    def _restore_geometry(self) -> None:
        g = self.settings.window_geometry
        if g:
            with contextlib.suppress(Exception):
                self.restoreGeometry(QByteArray.fromBase64(g.encode("ascii")))
        else:
            # a comfortable size, within the screen's free area (a 1366x768 laptop included)
            screen = self.screen()
            avail = screen.availableGeometry() if screen is not None else None
            w, h = 1400, 860
            if avail is not None and avail.width() > 0:
                w, h = min(w, avail.width()), min(h, avail.height())
            self.resize(w, h)
        st = self.settings.window_state
        restored = False
        if st:
            with contextlib.suppress(Exception):
                restored = bool(self.restoreState(QByteArray.fromBase64(st.encode("ascii"))))
        if not restored:
            # the images get the height; the jobs panel a strip at the bottom
            self.resizeDocks([self.jobs_dock], [220], Qt.Orientation.Vertical)

    def collect_settings(self) -> AppSettings:
        """Current settings (window geometry included)."""
        s = self.settings
        s.window_geometry = bytes(self.saveGeometry().toBase64().data()).decode("ascii")
        s.window_state = bytes(self.saveState().toBase64().data()).decode("ascii")
        s.preview = self.preview_controls.settings().to_dict()
        s.preview_enabled = self.preview_controls.enabled.isChecked()
        s.light_intensity = float(self.device_panel.intensity.value())
        s.show_roi = self.camera_controls.show_roi.isChecked()
        s.last_job = dict(self.jobs_panel.last_job)
        if not s.jobs_dir:
            s.jobs_dir = str(default_jobs_dir())
        return s

    def closeEvent(self, event: QCloseEvent) -> None:
        """Save the settings, stop the workers, close the devices (jobs keep running)."""
        if self.devices.closing:
            super().closeEvent(event)
            return
        self.devices.closing = True
        self._reconnect_cancel.set()  # a reconnect check under way ends within 0.2 s
        for t in (self.poll_timer, self.reconnect_timer, self.light_timer, self.readout_timer):
            t.stop()
        if self._save_on_close:
            try:
                save_settings(self.collect_settings(), self._settings_path)
            except OSError as exc:
                _log.error("saving the settings: %s", exc)
        self.jobs_panel.stop()
        self.trade_panel.stop()
        if self.calibration_wizard is not None:
            self.calibration_wizard.close()
        self.preview_worker.stop()
        self.camera_queue.shutdown()
        self.light_queue.shutdown()
        self.bench.close()
        super().closeEvent(event)


def _stack_message(planes: int) -> str:
    return (f"this is a stack of {planes} PSFs (a depth calibration); the live preview takes "
            "one PSF: choose one plane or a 2D PSF file")


def _psf_stack_planes(path: str | Path) -> int:
    """How many PSFs the file holds when it is a stack of several (else 0)."""
    from recon.readers import load_psf_stack

    try:
        stack = load_psf_stack(path, normalise=None)
    except Exception:  # not a stack either: the loader's own message is the one to show
        return 0
    return int(stack.shape[0]) if stack.ndim == 3 and stack.shape[0] > 1 else 0


def load_psf_any(path: str | Path) -> Any:
    """A PSF (H, W) for the preview: a PSF calibration file, else any image file.

    The one reader, :func:`recon.readers.load_psf_any`, which the CLI's plan and trade hash too.
    """
    from recon.readers import load_psf_any as _load

    return _load(path)
