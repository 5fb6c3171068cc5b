"""What a bench camera app is expected to do: fit the screen, leave the wheel to the scroll area,
the pixel under the cursor, continuous auto-levels, an
image menu that exports, no reconstruction of a saturated frame, real devices first."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PySide6.QtCore import QPoint, QPointF, Qt
from PySide6.QtGui import QWheelEvent
from PySide6.QtWidgets import QAbstractSpinBox, QApplication, QComboBox, QLabel

pytestmark = pytest.mark.gui


def test_window_fits_a_1366x768_screen_with_every_panel_shown(live_window: Any,
                                                             qtbot: Any) -> None:
    w = live_window
    for dock in (w.controls_dock, w.jobs_dock, w.trade_dock):
        dock.show()
    w.camera_controls.show_roi.setChecked(True)  # the ROI readout joins the footer
    w.show_error("Camera lost: " + "a very long error message " * 20)
    w._status("a long status line " * 30)
    n = w.frames_shown
    qtbot.waitUntil(lambda: w.frames_shown > n + 2, timeout=10_000)
    w._update_readouts()
    assert "ROI mean" in w.raw_panel.footer.text()
    QApplication.processEvents()
    hint = w.minimumSizeHint()
    # a 1024 px wide screen too: the panels' bold titles held the window at 1042 px
    assert hint.width() <= 1024 and hint.height() <= 768, hint
    lay = w.layout().minimumSize()
    assert lay.width() <= 1024 and lay.height() <= 768, lay
    w.resize(1366, 740)
    qtbot.waitUntil(lambda: w.width() <= 1366, timeout=5_000)
    assert w.width() <= 1366 and w.height() <= 768
    # the camera list shows its choice whole ("Simulated camera (bundled" was cut there); the
    # details are in the tooltip
    combo = w.device_panel.camera_combo
    QApplication.processEvents()
    assert _text_fits(combo), (combo.currentText(), combo.width())
    assert combo.toolTip().startswith(combo.currentText()) and "PSF" in combo.toolTip()
    # the docks can be closed, and tabbed: jobs and trade share the bottom area
    for dock in (w.controls_dock, w.jobs_dock, w.trade_dock):
        assert dock.features() & dock.DockWidgetFeature.DockWidgetClosable
    assert w.trade_dock in w.tabifiedDockWidgets(w.jobs_dock)


def _text_fits(combo: QComboBox) -> bool:
    """Whether the combo box's edit field is as wide as its current text."""
    from PySide6.QtWidgets import QStyle, QStyleOptionComboBox

    opt = QStyleOptionComboBox()
    combo.initStyleOption(opt)
    field = combo.style().subControlRect(QStyle.ComplexControl.CC_ComboBox, opt,
                                         QStyle.SubControl.SC_ComboBoxEditField, combo)
    return field.width() >= combo.fontMetrics().horizontalAdvance(combo.currentText())


def test_spin_boxes_take_the_wheel_only_when_focused(live_window: Any, qtbot: Any) -> None:
    from app.gui.widgets import WheelOnFocus

    w = live_window
    # every spin box and combo box of the window (and the job dialog) guards the wheel
    dlg = w.jobs_panel.new_job_dialog()
    boxes = [*w.findChildren(QAbstractSpinBox), *w.findChildren(QComboBox),
             *dlg.findChildren(QAbstractSpinBox), *dlg.findChildren(QComboBox)]
    assert len(boxes) > 20
    plain = [b for b in boxes if not isinstance(b, WheelOnFocus)
             and b.parent() is not None and not isinstance(b.parent(), QAbstractSpinBox)]
    assert not plain, [type(b).__name__ + " " + b.objectName() for b in plain]
    dlg.reject()

    box = w.camera_controls.frame_rate
    qtbot.waitUntil(box.isEnabled, timeout=5_000)
    before = box.value()
    pos = QPointF(box.width() / 2, box.height() / 2)

    def wheel() -> QWheelEvent:
        return QWheelEvent(pos, box.mapToGlobal(pos), QPoint(0, 0), QPoint(0, -120),
                           Qt.MouseButton.NoButton, Qt.KeyboardModifier.NoModifier,
                           Qt.ScrollPhase.NoScrollPhase, False)

    w.raw_panel.setFocus()
    assert not box.hasFocus()
    ev = wheel()
    QApplication.sendEvent(box, ev)
    assert box.value() == before and not ev.isAccepted()  # passed on to the scroll area
    assert box.focusPolicy() == Qt.FocusPolicy.StrongFocus
    w.activateWindow()
    box.setFocus()
    qtbot.waitUntil(box.hasFocus, timeout=2_000)
    QApplication.sendEvent(box, wheel())
    assert box.value() < before  # focused: the wheel steps it


def test_saturated_frame_is_not_reconstructed(live_window: Any, qtbot: Any) -> None:
    w = live_window
    qtbot.waitUntil(lambda: w.previews_shown >= 1, timeout=20_000)
    w.set_live(False)
    qtbot.waitUntil(lambda: w.camera_state == "stopped", timeout=5_000)
    f = w.last_frame
    top = (1 << f.bit_depth) - 1
    full = dataclasses.replace(f, pixels=np.full_like(f.pixels, top), frame_id=f.frame_id + 1)
    n_prev = w.previews_shown
    submitted = w.preview_worker.slot.stats().submitted
    w._show_frame(full)
    assert w.frames_skipped_saturated == 1
    assert "saturated" in w.preview_panel.message.text()
    assert "not reconstructed" in w.preview_panel.message.text()
    assert w.preview_worker.slot.stats().submitted == submitted  # never handed to the solver
    # a good frame is reconstructed again
    w._show_frame(dataclasses.replace(f, frame_id=f.frame_id + 2))
    qtbot.waitUntil(lambda: w.previews_shown > n_prev, timeout=20_000)
    assert np.all(np.isfinite(w.preview_panel.image))


def test_cursor_readout_auto_levels_and_image_menu(live_window: Any, qtbot: Any,
                                                   tmp_path: Path) -> None:
    import tifffile

    w = live_window
    panel = w.raw_panel
    img = panel.image
    # pixel value and position under the cursor
    scene_pos = panel.view.mapViewToScene(QPointF(12.5, 7.5))
    panel._mouse_moved(scene_pos)
    assert panel.cursor == (12, 7, pytest.approx(float(img[7, 12])))
    assert "x 12" in panel.cursor_label.text() and "y 7" in panel.cursor_label.text()
    panel._mouse_moved(panel.view.mapViewToScene(QPointF(-5.0, -5.0)))
    assert panel.cursor is None and panel.cursor_label.text() == ""
    # continuous auto-levels for the live frame
    assert panel.auto_levels.isVisible() and not panel.auto_levels.isChecked()
    panel.set_levels(0.0, 1.0)
    n = w.frames_shown
    qtbot.waitUntil(lambda: w.frames_shown > n + 1, timeout=10_000)
    assert panel.levels == (0.0, 1.0)  # fixed levels stay
    panel.auto_levels.setChecked(True)
    n = w.frames_shown
    qtbot.waitUntil(lambda: w.frames_shown > n + 1, timeout=10_000)
    lo, hi = panel.levels
    assert hi == pytest.approx(float(panel.image.max())) and lo == pytest.approx(
        float(panel.image.min()))
    # the image menu exports the view and saves the data
    menu = panel.context_menu()
    texts = [a.text() for a in menu.actions()]
    assert "Export view as PNG…" in texts and "Save image data as TIFF…" in texts
    png = panel.export_view(tmp_path / "view.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    tif = panel.save_data(tmp_path / "data.tif")
    with tifffile.TiffFile(tif) as t:
        assert t.asarray().shape == panel.image.shape
        assert '"format": "lenslesscam-view"' in t.pages[0].description
    # (GUI review) what the menu's saves say outlives the next frames (a failure was cleared
    # by the next frame, 50 ms later; a success said nothing); a bare name gets the suffix
    from PySide6.QtWidgets import QFileDialog

    answers = iter([str(tmp_path / "afile" / "v.png"), str(tmp_path / "bare")])
    (tmp_path / "afile").write_text("x")
    orig = QFileDialog.getSaveFileName
    QFileDialog.getSaveFileName = staticmethod(lambda *a, **k: (next(answers), ""))
    try:
        panel._ask_export_view()
        n = w.frames_shown
        qtbot.waitUntil(lambda: w.frames_shown > n + 2, timeout=10_000)
        assert panel.message.text().startswith(f"not saved: {tmp_path / 'afile' / 'v.png'}: ")
        panel._ask_save_data()
        qtbot.waitUntil(lambda: w.frames_shown > n + 4, timeout=10_000)
        assert panel.message.text() == f"saved {tmp_path / 'bare.tif'}"
        assert (tmp_path / "bare.tif").is_file()
    finally:
        QFileDialog.getSaveFileName = orig


def test_device_list_real_first_demo_only_on_request(monkeypatch: pytest.MonkeyPatch) -> None:
    from app.gui import devices
    from drivers import registry

    infos = [registry.CameraInfo("sim", "sim", "sim", demo=True),
             registry.CameraInfo("genicam:0", "genicam", "Viky [viky.cti]", demo=True),
             registry.CameraInfo("genicam:1", "genicam", "Hamamatsu [dcam.cti]"),
             registry.CameraInfo("v4l2:0", "v4l2", "/dev/video0 webcam")]
    monkeypatch.setattr(registry, "list_cameras", lambda **_k: infos)
    specs = [c.spec for c in devices.list_camera_choices()]
    assert specs == ["genicam:1", "v4l2:0", "sim"]
    specs = [c.spec for c in devices.list_camera_choices(show_demo=True)]
    assert specs == ["genicam:1", "v4l2:0", "sim", "genicam:0"]


def test_demo_producers_are_recognised() -> None:
    from drivers.genicam import gentl_cache_dir, is_demo_producer

    assert is_demo_producer("/usr/lib/python3/site-packages/genicam/viky.cti")
    assert is_demo_producer(gentl_cache_dir() / "genicam-1.5.0" / "TLSimu.cti")
    assert is_demo_producer(gentl_cache_dir() / "other" / "vendor.cti")
    assert not is_demo_producer("/opt/hamamatsu/dcam/dcamgentl.cti")


def test_producer_warnings_are_logged_once(caplog: pytest.LogCaptureFixture,
                                           capfd: pytest.CaptureFixture[str]) -> None:
    import os

    from app.gui import devices

    line = b"GenTL producer does not implement DSGetNumFlows (test)\n"
    with caplog.at_level("WARNING", logger="app.gui.devices"):
        for _ in range(3):
            with devices._producer_output_logged_once():
                os.write(2, line)
                os.write(2, b"another line\n")
    warned = [r for r in caplog.records if "DSGetNumFlows (test)" in r.getMessage()]
    assert len(warned) == 1
    err = capfd.readouterr().err
    assert "DSGetNumFlows" not in err and err.count("another line") == 3


def test_garbage_is_collected_in_the_gui_thread_only(live_window: Any, qtbot: Any) -> None:
    """A worker thread that ran the cyclic collector could destroy a Qt object and deadlock with
    the GUI thread (seen as a GUI test hung in a paint event): the window turns automatic
    collection off and collects on a GUI-thread timer."""
    import gc
    import threading

    from app.gui import image_view

    assert not gc.isenabled()
    assert image_view._collector is not None and image_view._collector.timer.isActive()
    where: list[str] = []

    class Cycle:
        def __init__(self) -> None:
            self.me = self

        def __del__(self) -> None:
            where.append(threading.current_thread().name)

    Cycle()
    kept: list[Any] = []  # live allocations raise the collector's count (freed ones do not)
    worker = threading.Thread(target=lambda: kept.append([[] for _ in range(50_000)]),
                              name="worker")  # would have run a collection there
    worker.start()
    worker.join()
    assert where == []  # not collected in the worker
    kept.append([[] for _ in range(3 * gc.get_threshold()[0])])
    qtbot.waitUntil(lambda: bool(where), timeout=10_000)
    assert where == [threading.main_thread().name]


def test_point_source_buttons_stay_put_when_the_camera_status_wraps(qtbot: Any) -> None:
    """A camera status that wraps to a second line (reconnecting, an error) leaves the
    point-source row where it was (it moved 14 px down and back); in a scroll area, as the
    controls dock holds it."""
    from PySide6.QtWidgets import QScrollArea

    from app.gui.panels import DevicePanel, set_status

    panel = DevicePanel()
    scroll = QScrollArea()
    scroll.setWidgetResizable(True)
    scroll.setWidget(panel)
    qtbot.addWidget(scroll)
    scroll.resize(400, 700)
    scroll.show()
    set_status(panel.camera_status, "sim: SimulatedCamera - live", "ok")
    qtbot.wait(100)
    y0 = panel.light_connect.y()
    long = ("Camera lost: the camera did not answer within the timeout (GenTL error -1011, "
            "device lost) – reconnect attempt 3 failed, retrying…")
    set_status(panel.camera_status, long, "error")
    qtbot.wait(100)
    assert panel.light_connect.y() == y0
    # one line, cut with '…'; the whole text is the label's text and its tooltip
    assert panel.camera_status.text() == long and panel.camera_status.toolTip() == long
    shown = QLabel.text(panel.camera_status)
    assert shown.endswith("…") and long.startswith(shown[:-1])
    set_status(panel.camera_status, "not connected", "off")
    qtbot.wait(100)
    assert panel.light_connect.y() == y0 and QLabel.text(panel.camera_status) == "not connected"
    set_status(panel.camera_status, "Camera lost:\nline two", "error")  # an exception's text
    qtbot.wait(100)
    assert panel.light_connect.y() == y0
    assert QLabel.text(panel.camera_status) == "Camera lost: line two"


def test_disconnecting_keeps_the_focus_in_the_devices_box(qtbot: Any) -> None:
    """The point source's Disconnect, focused when it is disabled, hands the focus to its
    Connect (Qt gave it to the next control in the tab chain, and the Controls dock scrolled
    the Devices box out of sight)."""
    from app.gui.panels import DevicePanel

    panel = DevicePanel()
    qtbot.addWidget(panel)
    panel.show()
    qtbot.waitExposed(panel)
    panel.activateWindow()
    panel.set_light_connected(True)
    panel.light_disconnect.setFocus()
    qtbot.waitUntil(panel.light_disconnect.hasFocus, timeout=2_000)
    panel.set_light_connected(False)
    assert panel.light_connect.hasFocus()
    panel.set_camera_connected(True, simulated=True)
    panel.camera_disconnect.setFocus()
    qtbot.waitUntil(panel.camera_disconnect.hasFocus, timeout=2_000)
    panel.set_camera_connected(False)
    assert panel.camera_connect.hasFocus()
