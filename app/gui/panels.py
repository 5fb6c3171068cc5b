"""Control panels of the main window: devices, camera settings, preview settings.

The panels only hold widgets and emit signals with what the user asked for; the main window
does the work (on worker threads) and calls ``show_...`` / ``set_...`` methods back with what
the devices report. Updates from the devices happen under :class:`QSignalBlocker`, so they never
echo back as user requests.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping
from typing import Any

from PySide6.QtCore import QSignalBlocker, Qt, Signal
from PySide6.QtWidgets import (
    QCheckBox,
    QComboBox,
    QDoubleSpinBox,
    QFormLayout,
    QGroupBox,
    QHBoxLayout,
    QLabel,
    QPushButton,
    QVBoxLayout,
    QWidget,
)

from app.gui.devices import SCENES, CameraChoice, PortChoice
from app.gui.preview_engine import MODELS, RANGES, PreviewSettings
from app.gui.widgets import (
    ComboBox,
    DoubleSpinBox,
    ElidedLabel,
    SciSpinBox,
    SpinBox,
    double_spin,
)

__all__ = ["CameraControls", "DevicePanel", "PreviewControls", "set_status"]

_STATUS_COLOURS = {"ok": "#1a7f37", "busy": "#9a6700", "error": "#cf222e", "off": "#57606a"}


def set_status(label: QLabel, text: str, kind: str = "off") -> None:
    """Show ``text`` in ``label`` coloured by ``kind`` (ok, busy, error, off)."""
    label.setText(text)
    label.setStyleSheet(f"color: {_STATUS_COLOURS.get(kind, '#000')};")
    label.setProperty("kind", kind)


def _keep_focus_near(anchor: QWidget, disabled: list[QWidget], enabled: bool) -> None:
    """Move the focus to ``anchor`` when a widget of ``disabled`` that has it is disabled.

    Qt gives the focus of a disabled widget to the next one in the tab chain, and the
    Controls dock's scroll area then scrolls to it: disconnecting the point source with the
    camera disconnected scrolled the Devices box out of sight.
    """
    if not enabled and any(w.hasFocus() for w in disabled):
        anchor.setFocus(Qt.FocusReason.OtherFocusReason)


class DevicePanel(QGroupBox):
    """Camera and point-source choice, connect / disconnect, their status and errors."""

    refresh_requested = Signal()
    show_demo_changed = Signal(bool)
    connect_camera_requested = Signal(str)
    disconnect_camera_requested = Signal()
    scene_changed = Signal(str)
    connect_light_requested = Signal(str)
    disconnect_light_requested = Signal()
    light_on_changed = Signal(bool)
    intensity_changed = Signal(float)

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__("Devices", parent)
        self.camera_combo = ComboBox()
        self.camera_combo.setMinimumContentsLength(18)
        self.camera_combo.setSizeAdjustPolicy(
            QComboBox.SizeAdjustPolicy.AdjustToMinimumContentsLengthWithIcon
        )
        self.refresh_button = QPushButton("Refresh")
        self.refresh_button.setToolTip("Look for cameras and serial ports again")
        self.show_demo = QCheckBox("list demo cameras")
        self.show_demo.setToolTip("Also list the demo GenTL producers' cameras (viky, TLSimu) "
                                  "and the test suite's cached simulator")
        self.camera_connect = QPushButton("Connect")
        self.camera_disconnect = QPushButton("Disconnect")
        # one line each (a status that wrapped moved the buttons below it by a line when it
        # changed): cut with '…', the whole text in the tooltip and errors in the banner
        self.camera_status = ElidedLabel("not connected")
        self.scene_combo = ComboBox()
        for key, label in SCENES.items():
            self.scene_combo.addItem(label, key)

        self.port_combo = ComboBox()
        self.port_combo.setEditable(True)
        self.port_combo.setToolTip("Serial port of the point source (or type a path / URL)")
        self.light_connect = QPushButton("Connect")
        self.light_disconnect = QPushButton("Disconnect")
        self.light_status = ElidedLabel("not connected")
        self.light_on = QCheckBox("on")
        self.intensity = DoubleSpinBox()
        self.intensity.setRange(0.0, 1.0)
        self.intensity.setSingleStep(0.05)
        self.intensity.setDecimals(2)
        self.intensity.setValue(1.0)
        self.intensity.setKeyboardTracking(False)

        form = QFormLayout(self)
        row = QHBoxLayout()
        row.addWidget(self.camera_combo, 1)
        row.addWidget(self.refresh_button)
        form.addRow("Camera", row)
        form.addRow("", self.show_demo)
        row = QHBoxLayout()
        row.addWidget(self.camera_connect)
        row.addWidget(self.camera_disconnect)
        form.addRow("", row)
        form.addRow("", self.camera_status)
        form.addRow("Sim scene", self.scene_combo)
        form.addRow("Point source", self.port_combo)
        row = QHBoxLayout()
        row.addWidget(self.light_connect)
        row.addWidget(self.light_disconnect)
        form.addRow("", row)
        form.addRow("", self.light_status)
        row = QHBoxLayout()
        row.addWidget(self.light_on)
        row.addWidget(QLabel("intensity"))
        row.addWidget(self.intensity)
        form.addRow("Light", row)

        self.camera_combo.currentIndexChanged.connect(lambda _i: self._camera_tooltip())
        self.refresh_button.clicked.connect(self.refresh_requested)
        self.show_demo.toggled.connect(self.show_demo_changed)
        self.camera_connect.clicked.connect(self._connect_camera)
        self.camera_disconnect.clicked.connect(self.disconnect_camera_requested)
        self.scene_combo.currentIndexChanged.connect(
            lambda _i: self.scene_changed.emit(str(self.scene_combo.currentData()))
        )
        self.light_connect.clicked.connect(self._connect_light)
        self.light_disconnect.clicked.connect(self.disconnect_light_requested)
        self.light_on.toggled.connect(self.light_on_changed)
        self.intensity.valueChanged.connect(self.intensity_changed)
        self.set_camera_connected(False)
        self.set_light_connected(False)

    # -- lists ---------------------------------------------------------------------------------

    def set_cameras(self, choices: Iterable[CameraChoice], current: str | None = None) -> None:
        """Fill the camera list (keeps the selection when it is still there)."""
        keep = current if current is not None else self.camera_combo.currentData()
        with QSignalBlocker(self.camera_combo):
            self.camera_combo.clear()
            for c in choices:
                self.camera_combo.addItem(c.label, c.spec)
                self.camera_combo.setItemData(self.camera_combo.count() - 1, c.tooltip,
                                              Qt.ItemDataRole.ToolTipRole)
            i = self.camera_combo.findData(keep)
            self.camera_combo.setCurrentIndex(max(0, i))
        self._camera_tooltip()

    def _camera_tooltip(self) -> None:
        """The chosen camera's whole description as the list's tooltip."""
        tip = self.camera_combo.currentData(Qt.ItemDataRole.ToolTipRole)
        self.camera_combo.setToolTip(str(tip) if tip else "")

    def set_ports(self, choices: Iterable[PortChoice], current: str | None = None) -> None:
        """Fill the port list."""
        keep = current if current is not None else self.selected_port()
        with QSignalBlocker(self.port_combo):
            self.port_combo.clear()
            for c in choices:
                self.port_combo.addItem(c.label, c.port)
            i = self.port_combo.findData(keep)
            if i >= 0:
                self.port_combo.setCurrentIndex(i)
            elif keep:
                self.port_combo.setEditText(keep)

    def selected_camera(self) -> str:
        """Spec of the chosen camera."""
        data = self.camera_combo.currentData()
        return str(data) if data is not None else "sim"

    def selected_port(self) -> str:
        """Chosen port (a listed one, or the typed text)."""
        i = self.port_combo.currentIndex()
        text = self.port_combo.currentText().strip()
        if i >= 0 and self.port_combo.itemText(i) == text:
            return str(self.port_combo.itemData(i))
        return text

    def set_scene(self, name: str) -> None:
        """Select a scene without emitting."""
        with QSignalBlocker(self.scene_combo):
            i = self.scene_combo.findData(name)
            self.scene_combo.setCurrentIndex(max(0, i))

    # -- state ---------------------------------------------------------------------------------

    def _connect_camera(self) -> None:
        self.connect_camera_requested.emit(self.selected_camera())

    def _connect_light(self) -> None:
        self.connect_light_requested.emit(self.selected_port())

    _busy = False
    _camera: tuple[bool, bool] = (False, False)  # (connected, simulated)
    _light = False

    def set_camera_connected(self, connected: bool, simulated: bool = False) -> None:
        """Enable the buttons that make sense."""
        self._camera = (connected, simulated)
        _keep_focus_near(self.camera_connect, [self.camera_disconnect, self.scene_combo],
                         connected)
        self._enable()

    def set_light_connected(self, connected: bool) -> None:
        """Enable the light controls when connected."""
        self._light = connected
        _keep_focus_near(self.light_connect,
                         [self.light_disconnect, self.light_on, self.intensity], connected)
        self._enable()

    def set_busy(self, busy: bool) -> None:
        """Lock the box while a workflow (PSF capture, darks) drives the camera and light.

        Nothing here changes them meanwhile (ticking the light on during the darks spoiled a
        capture).
        """
        self._busy = busy
        self._enable()

    def _enable(self) -> None:
        free = not self._busy
        connected, simulated = self._camera
        for w in (self.camera_combo, self.camera_connect, self.refresh_button, self.show_demo,
                  self.port_combo, self.light_connect):
            w.setEnabled(free)
        self.camera_disconnect.setEnabled(free and connected)
        self.scene_combo.setEnabled(free and connected and simulated)
        for w in (self.light_disconnect, self.light_on, self.intensity):
            w.setEnabled(free and self._light)

    def show_light_state(self, on: bool | None, intensity: float | None) -> None:
        """Reflect the source's confirmed state."""
        with QSignalBlocker(self.light_on):
            self.light_on.setChecked(bool(on))
        # an off source reports 0 or its last level: keep the level it will be switched on at
        # (remembered from the last session)
        if intensity is not None and on:
            with QSignalBlocker(self.intensity):
                self.intensity.setValue(float(intensity))


class CameraControls(QGroupBox):
    """Live on/off, exposure, gain, shutter and timing, ROI, snap and save."""

    live_toggled = Signal(bool)
    property_changed = Signal(str, object)
    snap_requested = Signal()
    save_as_requested = Signal()
    roi_visible_changed = Signal(bool)
    roi_apply_requested = Signal()
    roi_reset_requested = Signal()

    #: property name -> (label, widget attribute)
    PROPERTIES = (
        "exposure_us",
        "gain",
        "shutter_mode",
        "readout_pattern",
        "line_time_us",
        "trigger_delay_us",
        "frame_rate_hz",
    )

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__("Camera", parent)
        from drivers.timing import ReadoutPattern, ShutterMode

        self.live = QPushButton("Live")
        self.live.setCheckable(True)
        self.exposure = double_spin(0.001, 10_000.0, 3, 1.0, " ms")
        self.gain = double_spin(0.0, 64.0, 2, 0.5, "")
        self.shutter_mode = ComboBox()
        for m in ShutterMode:
            self.shutter_mode.addItem(m.value, m.value)
        self.readout_pattern = ComboBox()
        for p in ReadoutPattern:
            self.readout_pattern.addItem(p.value, p.value)
        self.line_time = double_spin(0.01, 1000.0, 2, 1.0, " µs")
        self.trigger_delay = double_spin(0.0, 1e6, 1, 10.0, " µs")
        self.frame_rate = double_spin(0.1, 1000.0, 1, 1.0, " Hz")
        # beside the box (a line below it would move the controls under it): the rate the
        # exposure allows when it is less than the set one (the box keeps the set rate,
        # which the camera goes back to for a shorter exposure)
        self.frame_rate_note = QLabel("")
        self.frame_rate_note.setMinimumWidth(self.frame_rate_note.fontMetrics()
                                             .horizontalAdvance("→ 999.9 Hz") + 4)
        self.show_roi = QCheckBox("show ROI")
        self.roi_apply = QPushButton("Set camera ROI")
        self.roi_reset = QPushButton("Full sensor")
        self.snap = QPushButton("Snap && save")
        self.snap.setToolTip("Save the newest frame (TIFF + JSON metadata) to the save folder")
        self.save_as = QPushButton("Save as…")
        self.save_info = QLabel("")
        self.save_info.setWordWrap(True)

        form = QFormLayout(self)
        form.addRow(self.live)
        form.addRow("Exposure", self.exposure)
        form.addRow("Gain", self.gain)
        form.addRow("Shutter", self.shutter_mode)
        form.addRow("Readout", self.readout_pattern)
        form.addRow("Line time", self.line_time)
        form.addRow("Trigger delay", self.trigger_delay)
        row = QHBoxLayout()
        row.addWidget(self.frame_rate, 1)
        row.addWidget(self.frame_rate_note)
        form.addRow("Frame rate", row)
        row = QHBoxLayout()
        row.addWidget(self.show_roi)
        row.addWidget(self.roi_apply)
        row.addWidget(self.roi_reset)
        form.addRow(row)
        row = QHBoxLayout()
        row.addWidget(self.snap)
        row.addWidget(self.save_as)
        form.addRow(row)
        form.addRow(self.save_info)

        self.live.toggled.connect(self.live_toggled)
        self.exposure.valueChanged.connect(
            lambda v: self.property_changed.emit("exposure_us", float(v) * 1000.0)
        )
        self.gain.valueChanged.connect(lambda v: self.property_changed.emit("gain", float(v)))
        self.shutter_mode.currentIndexChanged.connect(
            lambda _i: self.property_changed.emit("shutter_mode", self.shutter_mode.currentData())
        )
        self.readout_pattern.currentIndexChanged.connect(
            lambda _i: self.property_changed.emit(
                "readout_pattern", self.readout_pattern.currentData()
            )
        )
        self.line_time.valueChanged.connect(
            lambda v: self.property_changed.emit("line_time_us", float(v))
        )
        self.trigger_delay.valueChanged.connect(
            lambda v: self.property_changed.emit("trigger_delay_us", float(v))
        )
        self.frame_rate.valueChanged.connect(
            lambda v: self.property_changed.emit("frame_rate_hz", float(v))
        )
        self.show_roi.toggled.connect(self.roi_visible_changed)
        self.roi_apply.clicked.connect(self.roi_apply_requested)
        self.roi_reset.clicked.connect(self.roi_reset_requested)
        self.snap.clicked.connect(self.snap_requested)
        self.save_as.clicked.connect(self.save_as_requested)
        self.set_connected(False)

    def _widgets(self) -> dict[str, QWidget]:
        return {
            "exposure_us": self.exposure,
            "gain": self.gain,
            "shutter_mode": self.shutter_mode,
            "readout_pattern": self.readout_pattern,
            "line_time_us": self.line_time,
            "trigger_delay_us": self.trigger_delay,
            "frame_rate_hz": self.frame_rate,
        }

    def set_connected(self, connected: bool) -> None:
        """Enable or disable everything."""
        for w in (self.live, self.snap, self.save_as, self.roi_apply, self.roi_reset,
                  self.show_roi, *self._widgets().values()):
            w.setEnabled(connected)

    def set_live(self, live: bool) -> None:
        """Reflect whether the live stream runs."""
        with QSignalBlocker(self.live):
            self.live.setChecked(live)
        self.live.setText("Live (running)" if live else "Live (stopped)")

    def show_values(
        self, values: Mapping[str, Any], ranges: Mapping[str, Any] | None = None
    ) -> None:
        """Show what the camera reports; a None value disables that control (not available)."""
        ranges = ranges or {}
        widgets = self._widgets()
        for name, w in widgets.items():
            v = values.get(name)
            w.setEnabled(v is not None)
            if v is None:
                continue
            with QSignalBlocker(w):
                if isinstance(w, QComboBox):
                    i = w.findData(str(getattr(v, "value", v)))
                    if i >= 0:
                        w.setCurrentIndex(i)
                elif isinstance(w, QDoubleSpinBox):
                    scale = 1e-3 if name == "exposure_us" else 1.0
                    r = ranges.get(name)
                    if r is not None and all(math.isfinite(x) for x in r):
                        w.setRange(float(r[0]) * scale, float(r[1]) * scale)
                    w.setValue(float(v) * scale)
        self._frame_rate_note(values.get("frame_rate_hz"), values.get("resulting_frame_rate_hz"),
                              values.get("exposure_us"))

    def _frame_rate_note(self, rate: Any, resulting: Any, exposure_us: Any) -> None:
        """'→ 8.3 Hz' beside the frame rate when the exposure (and readout) allow less."""
        note, tip = "", ""
        if rate is not None and resulting is not None and float(resulting) < 0.995 * float(rate):
            note = f"→ {float(resulting):.3g} Hz"
            exposure = f" ({float(exposure_us) / 1000:.4g} ms)" if exposure_us is not None else ""
            tip = (f"The camera delivers {float(resulting):.4g} Hz, not the set "
                   f"{float(rate):.4g} Hz: the exposure{exposure} and the readout take longer "
                   f"than one period. A shorter exposure goes back to the set rate.")
        self.frame_rate_note.setText(note)
        self.frame_rate_note.setToolTip(tip)
        self.frame_rate.setToolTip(tip)


class TauSpinBox(SciSpinBox):
    """A spin box for a TV weight: any value from 1e-9 up, up to 6 significant digits.

    The tau auto estimate ranges over 1e-7 to 1e-2.
    """


def _kept(box: QDoubleSpinBox, current: float | None) -> float:
    """``current`` when ``box`` shows it (the same text), else the box's value.

    A dark level of 100.4 is shown as 100, a tau of 1.23456e-4 as 0.000123: taking the shown
    value back (Enter in the box, a toggle elsewhere) would change the setting the engine
    runs and the file keeps without anyone editing it.
    """
    shown = float(box.value())
    if current is not None and box.textFromValue(float(current)) == box.textFromValue(shown):
        return float(current)
    return shown


class PreviewControls(QGroupBox):
    """Preview on/off, model, tau, iterations per frame, downsampling, dark level, PSF.

    The spin boxes' ranges are the settings' ranges (:data:`~app.gui.preview_engine.RANGES`);
    the settings without a control (threads, target frame rate, prox iterations) are kept
    from the last :meth:`set_settings`, so :meth:`settings` never resets them.
    """

    settings_changed = Signal(object)
    enabled_changed = Signal(bool)
    load_psf_requested = Signal()
    reset_requested = Signal()

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__("Live reconstruction preview", parent)
        self.enabled = QCheckBox("preview on")
        self.enabled.setChecked(True)
        self.model = ComboBox()
        for m in MODELS:
            self.model.addItem({"2d": "2D (FISTA-TV)", "video": "video (dual shutter)"}[m], m)
        self.tau = TauSpinBox()
        self.tau.setRange(*RANGES["tau"])
        self.tau.setSingleStep(0.0005)
        self.tau.setKeyboardTracking(False)
        self.tau_auto = QCheckBox("auto")
        self.tau_auto.setToolTip(
            "Choose tau from the frame itself (held-out pixels), again only when the scene, "
            "the PSF or the geometry changes; the value in the box serves until then"
        )
        self.iters = SpinBox()
        self.iters.setRange(*(int(v) for v in RANGES["iters_per_frame"]))
        self.iters.setKeyboardTracking(False)
        self.downsample = SpinBox()
        self.downsample.setRange(*(int(v) for v in RANGES["downsample"]))
        self.downsample.setKeyboardTracking(False)
        self.dark = DoubleSpinBox()
        self.dark.setRange(-1.0, RANGES["dark"][1])  # -1: auto
        self.dark.setDecimals(0)
        self.dark.setSpecialValueText("auto")
        self.dark.setKeyboardTracking(False)
        self.dark.setToolTip("Dark level in camera codes (auto: the camera's black level where "
                             "it reports one, else the frame's 1st percentile, as --dark auto)")
        self.bins = SpinBox()
        self.bins.setRange(*(int(v) for v in RANGES["video_bins"]))
        self.bins.setKeyboardTracking(False)
        self.psf_label = QLabel("PSF: none")
        self.psf_label.setWordWrap(True)
        self.load_psf = QPushButton("Load PSF…")
        self.reset = QPushButton("Restart")
        self.reset.setToolTip("Forget the warm start")

        form = QFormLayout(self)
        form.addRow(self.enabled)
        form.addRow("Model", self.model)
        tau_row = QHBoxLayout()
        tau_row.addWidget(self.tau, 1)
        tau_row.addWidget(self.tau_auto)
        form.addRow("tau", tau_row)
        form.addRow("Iterations/frame", self.iters)
        form.addRow("Downsampling", self.downsample)
        form.addRow("Dark level", self.dark)
        form.addRow("Video bins", self.bins)
        row = QHBoxLayout()
        row.addWidget(self.load_psf)
        row.addWidget(self.reset)
        form.addRow(row)
        form.addRow(self.psf_label)
        self._current = PreviewSettings()
        self.set_settings(self._current)

        for sig in (self.model.currentIndexChanged, self.tau.valueChanged, self.tau_auto.toggled,
                    self.iters.valueChanged, self.downsample.valueChanged,
                    self.dark.valueChanged, self.bins.valueChanged):
            sig.connect(self._emit)
        self.enabled.toggled.connect(self.enabled_changed)
        self.load_psf.clicked.connect(self.load_psf_requested)
        self.reset.clicked.connect(self.reset_requested)

    def settings(self) -> PreviewSettings:
        """The settings the controls show, with the others from the last :meth:`set_settings`."""
        cur = self._current
        dark = float(self.dark.value())
        return dataclasses.replace(
            cur,
            model=str(self.model.currentData()),
            tau=_kept(self.tau, cur.tau),
            tau_auto=self.tau_auto.isChecked(),
            iters_per_frame=int(self.iters.value()),
            downsample=int(self.downsample.value()),
            dark=None if dark < 0 else _kept(self.dark, cur.dark),
            video_bins=int(self.bins.value()),
        )

    def set_settings(self, s: PreviewSettings) -> None:
        """Show ``s`` without emitting (and keep the settings that have no control)."""
        self._current = s
        widgets = (self.model, self.tau, self.tau_auto, self.iters, self.downsample, self.dark,
                   self.bins)
        blockers = [QSignalBlocker(w) for w in widgets]
        self.model.setCurrentIndex(max(0, self.model.findData(s.model)))
        self.tau.setValue(s.tau)
        self.tau_auto.setChecked(s.tau_auto)
        self.iters.setValue(s.iters_per_frame)
        self.downsample.setValue(s.downsample)
        self.dark.setValue(-1.0 if s.dark is None else s.dark)
        self.bins.setValue(s.video_bins)
        del blockers
        self.bins.setEnabled(s.model == "video")

    def _emit(self, *_args: Any) -> None:
        s = self.settings()
        self._current = s
        self.bins.setEnabled(s.model == "video")
        self.settings_changed.emit(s)


def make_sidebar(*widgets: QWidget) -> QWidget:
    """A vertical stack of panels with a stretch at the bottom."""
    w = QWidget()
    lay = QVBoxLayout(w)
    lay.setContentsMargins(4, 4, 4, 4)
    for x in widgets:
        lay.addWidget(x)
    lay.addStretch(1)
    return w
