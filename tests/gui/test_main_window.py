"""The main window on the simulated bench: live view, preview, controls, snap, unplug/replug."""

from __future__ import annotations

import json
import re
import time
from pathlib import Path
from typing import Any

import pytest
from PySide6.QtCore import Qt
from PySide6.QtWidgets import QLabel

pytestmark = pytest.mark.gui


def test_app_starts_live_with_preview_and_point_source(bench_window: Any,
                                                       qtbot: Any) -> None:
    w = bench_window
    assert w.bench.is_simulated
    assert w.raw_panel.image is not None and w.raw_panel.image.shape == (150, 200)
    qtbot.waitUntil(lambda: w.previews_shown >= 3, timeout=20_000)
    assert w.preview_panel.image.shape == (150, 200)
    assert w.preview_panel.image.dtype.name == "float32"
    qtbot.waitUntil(lambda: w.light_state == "connected", timeout=15_000)
    w._update_readouts()
    assert "fps" in w.raw_panel.footer.text() and "latency" in w.raw_panel.footer.text()
    assert "200x150 px, whole sensor" in w.raw_panel.footer.text()  # Frame.sensor, shown
    assert "preview" in w.preview_panel.footer.text()
    assert not w.banner.isVisible()


def test_preview_controls_reach_the_engine(live_window: Any, qtbot: Any) -> None:
    w = live_window
    w.preview_controls.downsample.setValue(2)
    w.preview_controls.iters.setValue(2)
    qtbot.waitUntil(lambda: w.preview_panel.image is not None
                    and w.preview_panel.image.shape == (75, 100), timeout=20_000)
    assert w.engine.settings.iters_per_frame == 2
    assert w.settings.preview["downsample"] == 2


def test_exposure_control_sets_the_camera(live_window: Any, qtbot: Any) -> None:
    w = live_window
    w.camera_controls.exposure.setValue(5.0)  # ms
    qtbot.waitUntil(lambda: abs(w.bench.camera.exposure_us - 5000.0) < 20, timeout=5_000)
    qtbot.waitUntil(lambda: w.last_frame is not None and w.last_frame.exposure_us < 6000,
                    timeout=5_000)


def test_a_frame_rate_the_exposure_limits_says_so_beside_the_box(live_window: Any,
                                                                  qtbot: Any) -> None:
    """The box kept the set rate while the exposure gave fewer frames, with nothing beside it:
    now '→ N Hz' and a tooltip; the box keeps the set rate, and the note goes with a short
    exposure."""
    w = live_window
    cc = w.camera_controls
    rate = cc.frame_rate.value()
    cc.exposure.setValue(1000.0 / rate * 3)  # ms: three periods
    qtbot.waitUntil(lambda: cc.frame_rate_note.text().startswith("→"), timeout=5_000)
    got = float(re.search(r"→ ([\d.]+) Hz", cc.frame_rate_note.text()).group(1))
    assert got == pytest.approx(w.bench.camera.resulting_frame_rate_hz, rel=0.01)
    assert got < rate / 2.5
    assert cc.frame_rate.value() == pytest.approx(rate)  # the setting, not the result
    assert "exposure" in cc.frame_rate.toolTip() and "exposure" in cc.frame_rate_note.toolTip()
    cc.exposure.setValue(1000.0 / rate / 4)
    qtbot.waitUntil(lambda: cc.frame_rate_note.text() == "", timeout=5_000)
    assert cc.frame_rate.toolTip() == ""


def test_refused_setting_is_shown_not_raised(live_window: Any, qtbot: Any) -> None:
    w = live_window
    w.set_camera_property("gain", 1000.0)  # the simulated camera allows [1, 64]
    qtbot.waitUntil(lambda: w.banner.isVisible(), timeout=5_000)
    assert "gain" in w.banner.text()
    assert w.camera_state == "live"
    n = w.frames_shown
    qtbot.waitUntil(lambda: w.frames_shown > n + 2, timeout=5_000)


def test_a_save_that_works_ends_the_last_ones_error_and_a_name_gets_tif(
        live_window: Any, qtbot: Any, tmp_path: Path, monkeypatch: Any) -> None:
    """Save as 'myframe.png' left its error banner through later saves that worked; 'myframe'
    (no suffix, the dialog's TIFF filter) made a folder 'myframe/' with the frame in it."""
    from PySide6.QtWidgets import QFileDialog

    w = live_window
    picked = [str(tmp_path / "myframe.png")]
    monkeypatch.setattr(QFileDialog, "getSaveFileName",
                        staticmethod(lambda *a, **k: (picked[0], "TIFF (*.tif)")))
    w._save_as()
    qtbot.waitUntil(lambda: w.banner.isVisible(), timeout=10_000)
    assert "frames are saved as .tif" in w.banner.text()
    picked[0] = str(tmp_path / "myframe")
    w._save_as()
    qtbot.waitUntil(lambda: w.last_saved is not None, timeout=10_000)
    assert Path(w.last_saved) == tmp_path / "myframe.tif" and Path(w.last_saved).is_file()
    assert not (tmp_path / "myframe").exists()
    assert not w.banner.isVisible()
    picked[0] = str(tmp_path / "exp_2.5ms")  # a dot in the name is not a file type
    w._save_as()
    qtbot.waitUntil(lambda: Path(w.last_saved).name == "exp_2.5ms.tif", timeout=10_000)
    assert not w.banner.isVisible()
    # (GUI review) a failed save does not move the save folder; a folder chosen gets the frame
    # in it under its own name (it was written as '<folder>.tif' beside it)
    assert w.settings.save_dir == str(tmp_path)
    (tmp_path / "afile").write_text("x")
    picked[0] = str(tmp_path / "afile" / "x.tif")
    w._save_as()
    qtbot.waitUntil(lambda: w.banner.isVisible(), timeout=10_000)
    assert w.settings.save_dir == str(tmp_path)
    assert w.camera_controls.save_info.text() == "not saved"
    (tmp_path / "frames").mkdir()
    picked[0] = str(tmp_path / "frames")
    w._save_as()
    qtbot.waitUntil(lambda: Path(w.last_saved).parent == tmp_path / "frames", timeout=10_000)
    assert not (tmp_path / "frames.tif").exists()
    assert w.settings.save_dir == str(tmp_path / "frames")


def test_snap_and_save_writes_tiff_with_metadata(live_window: Any, qtbot: Any,
                                                 tmp_path: Path) -> None:
    import tifffile

    w = live_window
    w.camera_controls.snap.click()
    qtbot.waitUntil(lambda: w.last_saved is not None, timeout=10_000)
    tif = Path(w.last_saved)
    assert tif.parent == tmp_path / "snaps"
    with tifffile.TiffFile(tif) as f:
        meta = json.loads(f.pages[0].description)
        pixels = f.asarray()
    assert meta["format"] == "lenslesscam-frame" and meta["format_version"] == 1
    assert meta["backend"] == "sim" and meta["app"]["scene"] == "im65"
    assert pixels.shape == (150, 200) and pixels.dtype.name == "uint16"
    assert meta["sensor"] == [150, 200]  # the sensor it came from (rows, columns)
    assert json.loads(tif.with_suffix(".json").read_text())["frame_id"] == meta["frame_id"]


def test_roi_applies_to_the_camera_and_preview_follows(live_window: Any, qtbot: Any) -> None:
    w = live_window
    w.camera_controls.show_roi.setChecked(True)
    w.raw_panel.roi.setPos([40, 30])
    w.raw_panel.roi.setSize([100, 80])
    w.camera_controls.roi_apply.click()
    qtbot.waitUntil(lambda: w.last_frame is not None and w.last_frame.shape == (80, 100),
                    timeout=10_000)
    n = w.previews_shown
    qtbot.waitUntil(lambda: w.previews_shown > n + 1, timeout=20_000)
    assert w.preview_panel.image.shape == (150, 200)  # the ROI is a mask on the full model
    w.camera_controls.roi_reset.click()
    qtbot.waitUntil(lambda: w.last_frame.shape == (150, 200), timeout=10_000)


def _lose_camera(w: Any, qtbot: Any) -> Any:
    """Unplug the live simulated camera (short stall timeout) and wait until it is lost."""
    cam = w.bench.camera
    cam.stream_timeout_s = 0.5
    w.set_live(True)  # restart the stream with the short stall timeout
    qtbot.waitUntil(lambda: w.camera_state == "live", timeout=5_000)
    cam.simulate_unplug()
    qtbot.waitUntil(lambda: w.camera_state == "lost", timeout=10_000)
    return cam


def test_camera_unplug_shows_error_and_reconnects(live_window: Any, qtbot: Any) -> None:
    w = live_window
    cam = _lose_camera(w, qtbot)
    assert w.banner.isVisible() and "Camera lost" in w.banner.text()
    assert "CameraTimeout" in w.banner.text()
    qtbot.waitUntil(lambda: w.reconnect_attempts >= 2, timeout=10_000)
    # the attempt count comes before the cause: the one-line status, cut to its width, kept
    # "Camera lost: CameraTimeout: ... –" and lost the count
    qtbot.waitUntil(lambda: "failed" in w.device_panel.camera_status.text(), timeout=10_000)
    shown = QLabel.text(w.device_panel.camera_status)
    assert re.match(r"Camera lost – reconnect attempt \d+ failed", shown), shown
    # the window stays usable: a control still works while the camera is gone
    w.preview_controls.tau.setValue(1e-3)
    assert w.engine.settings.tau == pytest.approx(1e-3)
    cam.simulate_replug()
    qtbot.waitUntil(lambda: w.camera_state == "live", timeout=10_000)
    n = w.frames_shown
    qtbot.waitUntil(lambda: w.frames_shown > n + 3, timeout=10_000)
    assert not w.banner.isVisible()


def test_disconnect_ends_a_reconnect_check_at_a_long_exposure(live_window: Any, qtbot: Any,
                                                              monkeypatch: Any) -> None:
    """A reconnect check waits two frame times for its frame (21 s at a 10 s exposure); it
    held the camera worker all that time, so Disconnect (queued behind it) waited as long."""
    w = live_window
    cam = _lose_camera(w, qtbot)
    monkeypatch.setattr(cam, "expected_frame_s", lambda: 10.0)  # a 10 s exposure, say
    qtbot.waitUntil(lambda: w.reconnect_attempts >= 1 and w.camera_queue.busy, timeout=10_000)
    time.sleep(0.3)  # the check is waiting for its frame
    t0 = time.monotonic()
    w.disconnect_camera()  # "disconnecting…" until the camera worker has closed it
    qtbot.waitUntil(lambda: "not connected" in QLabel.text(w.device_panel.camera_status),
                    timeout=3_000)
    assert time.monotonic() - t0 < 2.0
    qtbot.wait(300)
    assert w.camera_state == "disconnected"  # the ended attempt does not bring it back
    assert not w.reconnect_timer.isActive()  # nor arms another attempt
    assert "failed" not in QLabel.text(w.device_panel.camera_status)


def test_a_reconnected_camera_shows_the_check_frame_at_once(live_window: Any,
                                                            qtbot: Any) -> None:
    """The reconnect check's frame is shown: at a long exposure the next one comes a frame
    time later."""
    w = live_window
    cam = _lose_camera(w, qtbot)
    n = w.frames_shown
    shown: list[Any] = []
    w.frame_shown.connect(shown.append)
    cam.simulate_replug()
    qtbot.waitUntil(lambda: w.camera_state == "live", timeout=10_000)
    assert w.frames_shown > n and shown  # shown in the same turn as the state change


def test_bad_frames_are_skipped_and_counted_in_the_footer(live_window: Any, qtbot: Any,
                                                         monkeypatch: Any) -> None:
    from drivers.camera import FrameError

    w = live_window
    cam = w.bench.camera
    grab, calls = cam._stream_grab, [0]

    def sometimes_bad(poll_s: float) -> Any:
        calls[0] += 1
        if calls[0] % 3 == 0:
            raise FrameError("frame 9: corrupt data")
        return grab(poll_s)

    monkeypatch.setattr(cam, "_stream_grab", sometimes_bad)
    w.set_live(True)  # restart the stream with the flaky grab
    qtbot.waitUntil(lambda: w.camera_state == "live", timeout=5_000)
    n = w.frames_shown
    qtbot.waitUntil(lambda: w.frames_shown > n + 3 and cam.stream_stats().bad >= 2,
                    timeout=10_000)
    w._update_readouts()
    assert w.camera_state == "live" and not w.banner.isVisible()  # not "Camera lost"
    shown = re.search(r"dropped \d+, bad (\d+)", w.raw_panel.footer.text())
    assert shown and int(shown.group(1)) >= 2, w.raw_panel.footer.text()
    assert "corrupt data" in w.raw_panel.footer.toolTip()


def test_point_source_death_is_shown_and_recovered(bench_window: Any, qtbot: Any) -> None:
    w = bench_window
    qtbot.waitUntil(lambda: w.light_state == "connected", timeout=15_000)
    old_pid = w.bench.sim_source.process.pid
    w.bench.sim_source.kill()
    qtbot.waitUntil(lambda: w.light_state == "lost", timeout=10_000)
    assert "Point source lost" in w.banner.text()
    qtbot.waitUntil(lambda: w.light_state == "connected", timeout=20_000)
    assert w.bench.sim_source.process.pid != old_pid
    w.device_panel.light_on.setChecked(True)
    qtbot.waitUntil(lambda: w.bench.light.is_on is True, timeout=5_000)


def test_bad_camera_spec_is_an_error_in_the_window(make_window: Any, qtbot: Any) -> None:
    from app.gui.settings import AppSettings

    w = make_window(AppSettings(camera="v4l2:/nonexistent/video", connect_light=False))
    qtbot.waitUntil(lambda: w.banner.isVisible(), timeout=20_000)
    assert w.camera_state == "disconnected"
    assert "cannot connect" in w.banner.text()
    w.connect_camera("sim")  # and the window still works
    qtbot.waitUntil(lambda: w.frames_shown >= 2, timeout=20_000)


def test_settings_persist_between_sessions(make_window: Any, qtbot: Any) -> None:
    from app.gui.settings import load_settings, settings_path

    w = make_window()
    qtbot.waitUntil(lambda: w.camera_state == "live", timeout=20_000)
    w.preview_controls.iters.setValue(7)
    w.device_panel.scene_combo.setCurrentIndex(w.device_panel.scene_combo.findData("im740"))
    w.camera_controls.exposure.setValue(8.0)
    qtbot.waitUntil(lambda: abs(w.bench.camera.exposure_us - 8000.0) < 20, timeout=5_000)
    # the settings keep what the camera reports, which reaches the window after the camera
    # has it (the worker's answer is queued to the GUI thread): under load it came later
    qtbot.waitUntil(lambda: abs((w.settings.exposure_us or 0) - 8000.0) < 20, timeout=5_000)
    # the light's level and "show ROI" came back as 1.00 and unticked; a preview turned off
    # came back as an empty panel that said nothing
    w.device_panel.intensity.setValue(0.35)
    w.camera_controls.show_roi.setChecked(True)
    w.preview_controls.enabled.setChecked(False)
    w.close()
    assert settings_path().exists()
    s = load_settings()
    assert s.preview["iters_per_frame"] == 7 and s.sim_scene == "im740"
    assert s.exposure_us == pytest.approx(8000.0)
    assert s.light_intensity == pytest.approx(0.35) and s.show_roi and not s.preview_enabled
    w2 = make_window(s)
    qtbot.waitUntil(lambda: w2.camera_state == "live", timeout=20_000)
    assert w2.preview_controls.iters.value() == 7
    assert w2.device_panel.scene_combo.currentData() == "im740"
    assert w2.device_panel.intensity.value() == pytest.approx(0.35)
    assert w2.camera_controls.show_roi.isChecked()
    assert w2.preview_panel.message.text() == "preview off"
    w2.set_live(False)  # on again with the camera stopped: no frame comes to replace it
    w2.preview_controls.enabled.setChecked(True)
    assert w2.preview_panel.message.text() != "preview off"
    qtbot.waitUntil(lambda: abs(w2.bench.camera.exposure_us - 8000.0) < 20, timeout=5_000)


def test_one_bad_preview_key_keeps_the_other_preview_settings(
        make_window: Any, qtbot: Any, caplog: pytest.LogCaptureFixture) -> None:
    """A bad value for one preview key used to reset every preview setting to its default."""
    import json
    import logging

    from app.gui.settings import AppSettings, load_settings, settings_path

    settings_path().parent.mkdir(parents=True, exist_ok=True)
    d = AppSettings(frame_rate_hz=10.0, connect_light=False).to_dict()
    d["preview"] = {"iters_per_frame": 7, "downsample": 2, "tau": "abc", "tau_auto": False}
    settings_path().write_text(json.dumps(d), encoding="utf-8")
    with caplog.at_level(logging.WARNING, logger="app.gui.main_window"):
        w = make_window(load_settings())
    lines = [r.getMessage() for r in caplog.records if "preview settings" in r.getMessage()]
    assert len(lines) == 1, lines
    assert "tau='abc'" in lines[0] and "iters_per_frame" not in lines[0]
    s = w.preview_controls.settings()
    assert (s.iters_per_frame, s.downsample, s.tau_auto) == (7, 2, False)
    assert s.tau == pytest.approx(3e-4)  # the default
    assert w.engine.settings.iters_per_frame == 7


def test_bad_serial_port_is_an_error_in_the_window(bench_window: Any, qtbot: Any) -> None:
    w = bench_window
    qtbot.waitUntil(lambda: w.light_state == "connected", timeout=15_000)
    w.device_panel.port_combo.setEditText("/dev/does-not-exist")
    w.device_panel.light_connect.click()
    qtbot.waitUntil(lambda: w.banner.isVisible(), timeout=10_000)
    assert "Point source /dev/does-not-exist: cannot connect" in w.banner.text()
    assert w.light_state == "disconnected" and w.camera_state == "live"
    # a camera that connects leaves the point source's error: it is still true ...
    shown = w.frames_shown
    w.connect_camera("sim")
    qtbot.waitUntil(lambda: w.camera_state == "live" and w.frames_shown > shown + 2,
                    timeout=20_000)
    assert w.banner.isVisible() and "/dev/does-not-exist" in w.banner.text()
    # ... the point source connecting clears it (it stayed through that, before)
    w.connect_light("sim")
    qtbot.waitUntil(lambda: w.light_state == "connected", timeout=15_000)
    assert not w.banner.isVisible()
    # and a click dismisses the banner
    w.show_error("Point source: something", "light")
    qtbot.mouseClick(w.banner, Qt.MouseButton.LeftButton)
    assert not w.banner.isVisible()


def test_a_long_psf_file_name_wraps_inside_the_controls(live_window: Any, qtbot: Any,
                                                       tmp_path: Any) -> None:
    """An unbreakable file name widened the controls past their viewport at 1366x768, cutting
    off buttons on the right."""
    import numpy as np

    w = live_window
    w.resize(1366, 768)
    qtbot.wait(300)
    scroll = w.controls_dock.widget()
    name = "psf_calibration_diffusercam_benchA_20261126-192351_final_v2.npy"
    np.save(tmp_path / name, w.bench.sim_psf)
    w._load_psf(str(tmp_path / name))
    qtbot.wait(300)
    assert name in w.preview_controls.psf_label.toolTip()
    assert scroll.widget().width() <= scroll.viewport().width()


def test_a_doubtful_psf_is_loaded_and_said_so_in_the_banner(live_window: Any,
                                                           tmp_path: Any) -> None:
    """A constant PSF (a flat or dark frame?) was accepted with its warning on stderr only."""
    import numpy as np

    w = live_window
    np.save(tmp_path / "flat.npy", np.ones(w.bench.sim_psf.shape, np.float32))
    assert w._load_psf(str(tmp_path / "flat.npy"))
    assert "flat.npy loaded, but" in w.banner.text() and "constant" in w.banner.text()
    np.save(tmp_path / "neg.npy", -np.ones(w.bench.sim_psf.shape, np.float32))
    assert not w._load_psf(str(tmp_path / "neg.npy"))
    assert "all zero or negative" in w.banner.text()


def test_the_footer_says_where_a_frame_lies_on_its_sensor() -> None:
    """Frames carried their sensor's size since the preview began checking PSFs with it, but
    the app showed only the frame's pixel count: a ROI could not be told from a small sensor."""
    import numpy as np

    from app.gui.main_window import frame_geometry
    from drivers.camera import Frame, Roi

    def frame(roi: Roi, binning: int, sensor: tuple[int, int] | None) -> Frame:
        pixels = np.zeros((roi.height // binning, roi.width // binning), np.uint16)
        return Frame(pixels=pixels, frame_id=1, timestamp=0.0, exposure_us=None, gain=None,
                     roi=roi, binning=binning, pixel_format="Mono16", bit_depth=16,
                     timing=None, backend="test", camera_id="t", sensor=sensor)

    assert frame_geometry(frame(Roi(0, 0, 1440, 1080), 1, (1080, 1440))) == (
        "1440x1080 px, whole sensor")
    assert frame_geometry(frame(Roi(100, 50, 640, 480), 2, (1080, 1440))) == (
        "320x240 px, ROI at (100, 50) of 1440x1080, binning 2")
    assert frame_geometry(frame(Roi(0, 0, 640, 480), 1, None)) == (
        "640x480 px, ROI at (0, 0), sensor size unknown")


def test_preview_settings_without_controls_survive_load_toggle_save(make_window: Any) -> None:
    """threads, target_fps and prox_iters have no control: the controls' settings() reset them
    to their defaults when anything was touched, and the file kept the defaults. A tau or dark
    level finer than the boxes show came back rounded (3e-6 as 0)."""
    import torch

    from app.gui.settings import AppSettings, load_settings, save_settings, settings_path

    mine = {"threads": 2, "target_fps": 5.0, "prox_iters": 7, "tau": 2.5e-6, "dark": 100.4,
            "iters_per_frame": 4}
    save_settings(AppSettings(frame_rate_hz=10.0, connect_light=False, preview=mine,
                              display_hz=30.0))
    threads = torch.get_num_threads()
    try:
        w = make_window(load_settings(), autoconnect=False)
        pc = w.preview_controls
        pc.tau_auto.setChecked(not pc.tau_auto.isChecked())  # the user touches one control
        for s in (pc.settings(), w.engine.settings):
            assert (s.threads, s.target_fps, s.prox_iters) == (2, 5.0, 7)
            assert (s.tau, s.dark, s.iters_per_frame) == (2.5e-6, 100.4, 4)
        assert pc.tau.text() == "2.5e-06" and pc.iters.value() == 4
        w.close()
    finally:
        torch.set_num_threads(threads)
    whole = json.loads(settings_path().read_text(encoding="utf-8"))
    assert whole["display_hz"] == 30.0  # was read back from the 33 ms timer: 30.303
    saved = whole["preview"]
    assert {k: saved[k] for k in mine} == mine
    assert saved["tau_auto"] is False  # the touched control (on by default)


def test_out_of_range_preview_settings_are_clamped_and_the_controls_show_what_runs(
        make_window: Any, caplog: pytest.LogCaptureFixture) -> None:
    """video_bins 1000000 in the settings file was used as is (2.6 GB, 16 s frames; closing
    the app then aborted) while the Video bins box showed 32."""
    import logging

    from app.gui.settings import AppSettings, load_settings, save_settings

    save_settings(AppSettings(frame_rate_hz=10.0, connect_light=False, preview={
        "model": "video", "video_bins": 1_000_000, "iters_per_frame": 5000, "tau_auto": False}))
    with caplog.at_level(logging.WARNING, logger="app.gui.main_window"):
        w = make_window(load_settings(), autoconnect=False)
    lines = [r.getMessage() for r in caplog.records if "preview settings" in r.getMessage()]
    assert len(lines) == 1 and "video_bins=1000000" in lines[0] and "using 32" in lines[0]
    assert "iters_per_frame=5000" in lines[0] and "using 200" in lines[0]
    assert "video_bins=1000000" in w.status_label.text()
    pc = w.preview_controls
    assert (pc.bins.value(), pc.iters.value()) == (32, 200)
    assert pc.settings() == w.engine.settings
    assert (w.engine.settings.video_bins, w.engine.settings.iters_per_frame) == (32, 200)
    assert w.engine.settings.model == "video" and w.engine.settings.tau_auto is False


def test_a_psf_stack_is_refused_in_words_for_the_user(make_window: Any, tmp_path: Path) -> None:
    """A (5, H, W) PSF file said "for a stack of PSFs use load_psf_stack" (a Python function)."""
    import numpy as np

    w = make_window(autoconnect=False)
    stack = np.random.default_rng(0).random((5, 150, 200)).astype(np.float32)
    np.save(tmp_path / "psf3d.npy", stack)
    assert not w._load_psf(str(tmp_path / "psf3d.npy"))
    text = w.banner.text()
    assert "stack of 5 PSFs (a depth calibration)" in text and "choose one plane" in text
    assert "load_psf_stack" not in text and not w.engine.has_psf
    np.save(tmp_path / "plane2.npy", stack[2])
    assert w._load_psf(str(tmp_path / "plane2.npy")) and w.engine.has_psf


def test_a_jobs_folder_that_is_a_file_is_said_at_start(make_window: Any, tmp_path: Path,
                                                       caplog: pytest.LogCaptureFixture) -> None:
    """jobs_dir pointing at a file failed only when a job was queued."""
    import logging

    from app.gui.settings import AppSettings

    afile = tmp_path / "afile"
    afile.write_text("i am a file")
    with caplog.at_level(logging.WARNING):
        w = make_window(AppSettings(frame_rate_hz=10.0, connect_light=False,
                                    jobs_dir=str(afile)), autoconnect=False)
    assert "is a file, not a folder" in w.status_label.text()
    assert "is a file, not a folder" in w.jobs_panel.message.text()
    assert any("is a file, not a folder" in r.getMessage() for r in caplog.records)


def test_the_footer_rate_of_a_slow_stream_and_of_one_that_stopped() -> None:
    """At 0.3 frames a second the footer said 0.0 fps; a stream that stopped kept its last
    rate ('camera 11.6 fps' while no frame came)."""
    from app.gui.main_window import _Rate

    r = _Rate(window_s=2.0)
    for t in (0.0, 3.0, 6.0):
        r.tick(t)
    assert r.rate(now=7.0) == pytest.approx(1 / 3)
    assert r.rate(now=13.0) == 0.0  # the next frame is overdue: stopped
    fast = _Rate(window_s=2.0)
    for i in range(21):
        fast.tick(i * 0.1)
    assert fast.rate(now=2.0) == pytest.approx(10.0)
    assert fast.rate(now=10.0) == 0.0
    # ticks on the wall clock (a frame's timestamp), read without a "now": the time since
    # the newest tick decides, whatever the clock (9.99 fps stayed for a stopped stream)
    import time

    wall = _Rate(window_s=2.0)
    t0 = time.time()
    for i in range(11):
        wall.tick(t0 - 1.0 + i * 0.1)
    assert wall.rate() == pytest.approx(10.0, rel=0.05)
    wall._arrived -= 3.0  # as if the newest frame came 3 s ago
    assert wall.rate() == 0.0


def test_the_devices_box_is_locked_while_a_workflow_drives_the_devices(live_window: Any,
                                                                       qtbot: Any) -> None:
    """During a PSF capture the light's on box, its Disconnect, the camera's Connect and
    the scene stayed usable: ticking the light on during the darks spoiled the capture."""
    w = live_window
    dp = w.device_panel
    dp.set_light_connected(True)  # as with a point source connected
    free = (dp.camera_combo, dp.camera_connect, dp.camera_disconnect, dp.scene_combo,
            dp.port_combo, dp.light_connect, dp.light_disconnect, dp.light_on, dp.intensity)
    assert all(x.isEnabled() for x in free)
    w._set_camera_state("calibrating", "PSF capture running…", "busy")
    assert not any(x.isEnabled() for x in free), [x for x in free if x.isEnabled()]
    w._set_camera_state("live", "live", "ok")
    assert all(x.isEnabled() for x in free)
    dp.set_light_connected(False)
    assert not dp.light_on.isEnabled() and dp.light_connect.isEnabled()


def test_a_tau_applied_to_the_preview_is_the_tau_it_runs(live_window: Any, qtbot: Any) -> None:
    """*Apply to preview* (the trade's suggestion) put its tau in the box and the settings
    while *auto* (the default) stayed on, so the preview went on with its own estimate and
    nothing said so. The applied tau now runs, *auto* is off and the status line says it."""
    w = live_window
    assert w.preview_controls.settings().tau_auto  # the default
    seen: list[float] = []
    w.preview_shown.connect(lambda res: seen.append(res.tau))
    w.set_preview_tau(0.02)
    assert not w.preview_controls.tau_auto.isChecked() and not w.engine.settings.tau_auto
    assert "automatic tau off" in w.status_label.text()
    qtbot.waitUntil(lambda: len(seen) >= 3, timeout=20_000)
    assert seen[-1] == pytest.approx(0.02)


def test_the_preview_is_held_while_the_trade_measures(live_window: Any, qtbot: Any) -> None:
    """A trade measured with the live preview running timed its settings on shared cores
    (0.93 s against 0.46 s alone): the preview now waits for it, and says why."""
    from recon.trade import Config

    w = live_window
    qtbot.waitUntil(lambda: w.previews_shown >= 2, timeout=20_000)
    panel = w.trade_panel
    panel.downsample.setValue(4)
    panel.grid = [Config("fista", t, (10, 20)) for t in (1e-4, 1e-3, 1e-2, 3e-2)]
    panel.measure_current()
    assert panel.running, panel.suggestion.text()
    assert "paused while the trade measures" in w.preview_panel.message.text()
    # once the trade is under way (a preview frame in flight when it began has ended) no
    # preview runs beside it, while the live view goes on
    qtbot.waitUntil(lambda: len(panel.rows) >= 2 or not panel.running, timeout=60_000)
    n, frames = w.previews_shown, w.frames_shown
    qtbot.waitUntil(lambda: not panel.running, timeout=60_000)
    assert w.previews_shown == n and w.frames_shown > frames
    assert "paused" not in w.preview_panel.message.text()
    qtbot.waitUntil(lambda: w.previews_shown > n + 2, timeout=20_000)  # back afterwards


def test_a_psf_of_another_sensor_is_refused_and_the_last_sessions_is_said(
        live_window: Any, make_window: Any, qtbot: Any, tmp_path: Path) -> None:
    """A PSF of another sensor size replaced the working one and was remembered: every frame
    failed, after a restart too; an earlier refusal stayed in the banner after a good load;
    a remembered PSF that no longer loads left the preview on "PSF: none" without a word."""
    import numpy as np

    from app.gui.settings import AppSettings

    w = live_window
    good = w.bench.sim_psf
    before = w.engine.psf.copy()
    np.save(tmp_path / "other.npy", np.ones((64, 80), np.float32))
    assert not w._load_psf(str(tmp_path / "other.npy"))
    text = w.banner.text()
    assert "belongs to another camera" in text and "not loaded" in text, text
    np.testing.assert_array_equal(w.engine.psf, before)  # the preview keeps its PSF
    assert w.settings.psf_path != str(tmp_path / "other.npy")
    np.save(tmp_path / "good.npy", good)
    assert w._load_psf(str(tmp_path / "good.npy"))
    assert not w.banner.isVisible()  # the refusal was of the other file
    # with the camera disconnected there is no sensor to hold it to (its last frame was
    # kept, and refused the PSF of the camera about to be connected)
    w.disconnect_camera()
    qtbot.waitUntil(lambda: w.camera_state != "live", timeout=10_000)
    assert w._load_psf(str(tmp_path / "other.npy"))
    assert w._load_psf(str(tmp_path / "good.npy"))
    # the last session's PSF is gone: said, and the bench's PSF is used
    w2 = make_window(AppSettings(frame_rate_hz=10.0, connect_light=False,
                                 psf_path=str(tmp_path / "moved-away.npy")))
    assert "moved-away.npy of the last session" in w2.banner.text()
    assert w2.settings.psf_path == ""
    qtbot.waitUntil(lambda: w2.camera_state == "live", timeout=20_000)
    qtbot.waitUntil(lambda: w2.engine.has_psf, timeout=10_000)
    assert "simulated bench" in w2.psf_source


def test_two_quick_roi_changes_keep_the_camera_live(live_window: Any, qtbot: Any) -> None:
    """(GUI review) Set camera ROI clicked twice (or ROI then Full sensor) while the first
    change ran read the camera as not live: it stayed stopped under a green status line."""
    w = live_window
    cc = w.camera_controls
    cc.show_roi.setChecked(True)
    qtbot.wait(200)
    w.raw_panel.roi.setPos((10, 8))
    w.raw_panel.roi.setSize((40, 32))
    cc.roi_apply.click()
    cc.roi_apply.click()
    qtbot.waitUntil(lambda: w.camera_state == "live" and not w.camera_queue.busy,
                    timeout=15_000)
    cc.roi_apply.click()
    cc.roi_reset.click()
    qtbot.waitUntil(lambda: w.camera_state == "live" and not w.camera_queue.busy,
                    timeout=15_000)
    n = w.frames_shown
    qtbot.waitUntil(lambda: w.frames_shown > n + 2, timeout=10_000)  # frames flow again
    assert cc.live.isChecked()
