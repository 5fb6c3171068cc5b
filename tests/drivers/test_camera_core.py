"""Frames, errors, the streaming helper and the package surface, without any backend."""

from __future__ import annotations

import json
import logging
import math
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

import drivers
from drivers.camera import (
    AcquisitionOverflow,
    CameraError,
    CameraTimeout,
    FeatureNotAvailable,
    Frame,
    FrameError,
    FrameStreamer,
    Roi,
    StreamMode,
    bit_depth_of,
    read_frame_metadata,
)
from drivers.registry import list_cameras, open_camera
from drivers.simcam import SimulatedCamera
from drivers.timing import SensorTiming

pytestmark = pytest.mark.timeout(60)


def _frame(pixels: np.ndarray, **kw: object) -> Frame:
    args: dict[str, object] = dict(
        pixels=pixels, frame_id=3, timestamp=1.0, exposure_us=100.0, gain=None,
        roi=Roi(0, 0, pixels.shape[1], pixels.shape[0]), binning=1, pixel_format="Mono16",
        bit_depth=16, timing=SensorTiming(4, 10.0, 3), backend="test", camera_id="t0",
    )  # fmt: skip
    args.update(kw)
    return Frame(**args)  # type: ignore[arg-type]


def test_frame_copies_views_and_takes_owned_arrays() -> None:
    big = np.zeros((8, 8), dtype=np.uint16)
    f = _frame(big[2:6, 2:6])  # a view: copied
    big[3, 3] = 7
    assert f.pixels[1, 1] == 0 and f.pixels.flags.owndata and not f.pixels.flags.writeable
    own = np.ones((4, 4), dtype=np.uint16)
    g = _frame(own)  # owned: taken over, read-only from now on
    assert g.pixels is own and not own.flags.writeable


def test_frame_metadata_is_plain_json() -> None:
    f = _frame(np.zeros((4, 4), np.uint16), extra={"a": np.float32(1.5), "n": math.nan})
    meta = json.loads(json.dumps(f.metadata(), allow_nan=False))
    assert meta["extra"] == {"a": 1.5, "n": None}
    assert SensorTiming.from_dict(meta["timing"]) == f.timing
    assert Roi.from_dict(meta["roi"]) == f.roi
    assert f.sensor is None and meta["sensor"] is None  # built without it: unknown


def test_frame_sensor_size_is_checked_and_round_trips_through_a_saved_frame(
    tmp_path: Path,
) -> None:
    """A frame names the whole sensor it came from (rows, columns, unbinned), so a ROI is not
    confused with a smaller sensor; a saved frame keeps it and an older file without it reads."""
    import tifffile

    from app.gui.snapshots import save_frame

    f = _frame(np.zeros((6, 8), np.uint16), roi=Roi(4, 2, 8, 6), sensor=(np.int64(12), 16.0))
    assert f.sensor == (12, 16) and all(type(v) is int for v in f.sensor)
    with pytest.raises(ValueError, match="outside its 12x16"):
        _frame(np.zeros((6, 8), np.uint16), roi=Roi(10, 2, 8, 6), sensor=(12, 16))
    for bad in ((12,), (0, 16), (12.5, 16), "12x16"):
        with pytest.raises(ValueError, match="sensor size must be"):
            _frame(np.zeros((6, 8), np.uint16), roi=Roi(0, 0, 8, 6), sensor=bad)
    tif, _ = save_frame(f, tmp_path / "roi.tif")
    meta = read_frame_metadata(tif)
    assert meta["sensor"] == [12, 16]
    assert meta["format_version"] == 1  # an added key, not an incompatible change
    old = {k: v for k, v in f.metadata().items() if k != "sensor"}  # before the sensor size
    tifffile.imwrite(tmp_path / "old.tif", np.zeros((6, 8), np.uint16),
                     description=json.dumps(old), metadata=None)
    old_meta = read_frame_metadata(tmp_path / "old.tif")
    assert old_meta["sensor"] is None  # not recorded then: unknown
    assert Roi.from_dict(old_meta["roi"]) == f.roi
    tifffile.imwrite(tmp_path / "bad.tif", np.zeros((6, 8), np.uint16),
                     description=json.dumps({**old, "sensor": [12]}), metadata=None)
    with pytest.raises(ValueError, match=r"bad\.tif: sensor size must be"):
        read_frame_metadata(tmp_path / "bad.tif")


def test_errors_name_the_feature_and_the_device() -> None:
    e = FeatureNotAvailable("gain", "sim camera 'x'", "no node")
    assert (e.feature, e.device) == ("gain", "sim camera 'x'")
    assert str(e) == "sim camera 'x': feature 'gain' is not available (no node)"
    assert issubclass(CameraTimeout, TimeoutError) and issubclass(CameraTimeout, CameraError)
    with pytest.raises(ValueError):
        Roi(0, 0, 0, 4)
    with pytest.raises(ValueError, match="unknown pixel format"):
        bit_depth_of("RGB8")


def test_streamer_overflow_and_validation() -> None:
    counter = iter(range(10**6))

    def grab(poll_s: float) -> Frame:
        return _frame(np.zeros((2, 2), np.uint16), frame_id=next(counter))

    s = FrameStreamer(grab, mode=StreamMode.ACQUISITION, device="d", queue_size=2)
    s.start()
    # the grab thread needs a third frame to overflow: on a loaded machine a stop at once
    # could come first (the test then failed with no overflow)
    deadline = time.monotonic() + 10.0
    while s.stats().error is None and time.monotonic() < deadline:
        time.sleep(0.005)
    s.stop()
    with pytest.raises(AcquisitionOverflow, match="queue of 2 frames overflowed"):
        s.pop(1.0)
    with pytest.raises(ValueError):
        FrameStreamer(grab, mode=StreamMode.IDLE, device="d")
    with pytest.raises(ValueError):
        FrameStreamer(grab, mode=StreamMode.LIVE, device="d", n_frames=0)


def test_stop_frees_a_lock_a_ctrl_c_left_held() -> None:
    """Ctrl-C between a consumer's lock acquisition and its ``with`` block leaves the lock held
    by the consumer's thread (bpo-29988); the stream thread then blocked on it and ``stop``
    failed with "streaming thread did not stop" (a flaky CI run of the calibrate Ctrl-C test).
    ``stop`` now releases what the calling thread holds, and the thread ends."""
    counter = iter(range(10**6))

    def grab(poll_s: float) -> Frame:
        time.sleep(0.002)
        return _frame(np.zeros((2, 2), np.uint16), frame_id=next(counter))

    s = FrameStreamer(grab, mode=StreamMode.LIVE, device="d")
    s.start()
    assert s.latest(5.0) is not None
    s._cond.acquire()  # what the interrupted `with self._cond:` left behind
    time.sleep(0.05)  # the stream thread now waits for the lock
    s.stop(timeout_s=5.0)
    assert not s.running and not s._cond._is_owned()


def test_streamer_reports_a_stall() -> None:
    def grab(poll_s: float) -> None:
        threading.Event().wait(poll_s)

    s = FrameStreamer(grab, mode=StreamMode.LIVE, device="d", stall_timeout_s=0.1, poll_s=0.02)
    s.start()
    with pytest.raises(CameraTimeout, match=r"no frame for 0\.1 s"):
        while True:
            s.latest(0.5)
    assert not s.running


def test_open_camera_specs() -> None:
    with open_camera("sim", width=16, height=8) as cam:
        assert isinstance(cam, SimulatedCamera) and cam.is_open
    for bad in ("webcam", "sim:1", "genicam:x"):
        with pytest.raises(ValueError):
            open_camera(bad)
    assert list_cameras(genicam_producers=[])[0].spec == "sim"


def test_package_exports_lazily() -> None:
    assert drivers.SimulatedCamera is SimulatedCamera
    assert set(drivers.__all__) <= set(dir(drivers))
    with pytest.raises(AttributeError):
        _ = drivers.NoSuchThing  # type: ignore[attr-defined]
    code = (
        "import sys, drivers, drivers.pointsource_sim; "
        "bad = [m for m in ('numpy', 'serial', 'cv2', 'harvesters') if m in sys.modules]; "
        "print(bad)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"  # the firmware process starts without heavy imports


# -- bad frames: live view skips them, an acquisition stops at the first --------------------


def _scripted_grab(script: list[str], *, then: str = "good") -> Callable[[float], Frame | None]:
    """A grab that follows ``script`` ('good', 'bad', 'fail'), then repeats ``then``."""
    ids = iter(range(10**6))
    steps = iter(script)

    def grab(poll_s: float) -> Frame | None:
        step = next(steps, then)
        if step == "bad":
            raise FrameError("frame 7: corrupt MJPEG data")
        if step == "fail":
            raise CameraError("device unplugged")
        threading.Event().wait(0.002)
        return _frame(np.zeros((2, 2), np.uint16), frame_id=next(ids))

    return grab


def _drain_live(s: FrameStreamer, until: Callable[[], bool], timeout_s: float = 10.0) -> list[int]:
    ids: list[int] = []
    deadline = time.monotonic() + timeout_s
    while not until() and time.monotonic() < deadline:
        f = s.latest(0.05)
        if f is not None:
            ids.append(f.frame_id)
    return ids


def test_live_view_skips_a_bad_frame_counts_it_and_says_so(
    caplog: pytest.LogCaptureFixture,
) -> None:
    s = FrameStreamer(_scripted_grab(["good"] * 3 + ["bad"]), mode=StreamMode.LIVE,
                      device="cam d")
    with caplog.at_level(logging.WARNING, logger="drivers.camera"):
        s.start()
        try:
            _drain_live(s, lambda: s.stats().acquired >= 20)
            st = s.stats()
            assert s.running and st.error is None  # the stream went on
        finally:
            s.stop()
    assert st.bad == 1 and st.last_bad == "frame 7: corrupt MJPEG data"
    assert st.acquired == st.delivered + st.dropped + st.pending  # bad ones are not acquired
    said = [r.getMessage() for r in caplog.records if "bad frame" in r.getMessage()]
    assert len(said) == 1 and "cam d" in said[0] and "corrupt MJPEG" in said[0]


def test_bad_frame_warnings_are_rate_limited_and_count_the_ones_not_said(
    caplog: pytest.LogCaptureFixture,
) -> None:
    s = FrameStreamer(_scripted_grab(["good", "bad"] * 10**5), mode=StreamMode.LIVE,
                      device="d")
    s.bad_log_interval_s = 0.2
    with caplog.at_level(logging.WARNING, logger="drivers.camera"):
        s.start()
        try:
            _drain_live(s, lambda: False, timeout_s=0.7)
        finally:
            s.stop()
    said = [r.getMessage() for r in caplog.records if "bad frame" in r.getMessage()]
    assert s.stats().bad > 20 and 2 <= len(said) <= 5  # not one line per bad frame
    assert "skipped in the last" in said[1] and "corrupt MJPEG" in said[1]


def test_live_view_ends_after_max_bad_frames_in_a_row() -> None:
    # runs of 3 bad frames between good ones never end it; a run of 4 does
    script = ["good", "bad", "bad", "bad", "good", "bad", "bad", "bad", "good"]
    s = FrameStreamer(_scripted_grab(script, then="bad"), mode=StreamMode.LIVE, device="d",
                      max_bad_frames=4)
    s.start()
    with pytest.raises(CameraError, match="d: 4 bad frames in a row, the last: frame 7: "
                                          "corrupt MJPEG data") as info:
        _drain_live(s, lambda: False, timeout_s=5.0)
    assert isinstance(info.value.__cause__, FrameError)
    s.stop()
    st = s.stats()
    assert st.bad == 6 + 4 and st.acquired == 3


def test_bad_frames_do_not_keep_a_dead_device_alive_past_the_stall_timeout() -> None:
    def grab(poll_s: float) -> None:
        threading.Event().wait(0.01)
        raise FrameError("read returned no frame")

    s = FrameStreamer(grab, mode=StreamMode.LIVE, device="d", stall_timeout_s=0.3,
                      max_bad_frames=10**6)
    t0 = time.monotonic()
    s.start()
    with pytest.raises(CameraTimeout, match=r"no good frame for 0\.3 s.*bad frame\(s\) in a "
                                            r"row, the last: read returned no frame"):
        _drain_live(s, lambda: False, timeout_s=5.0)
    assert 0.3 <= time.monotonic() - t0 < 3.0 and s.stats().bad >= 10
    s.stop()


def test_live_view_ends_at_once_on_an_error_that_is_not_a_bad_frame() -> None:
    s = FrameStreamer(_scripted_grab(["good", "fail"]), mode=StreamMode.LIVE, device="d")
    s.start()
    with pytest.raises(CameraError, match="device unplugged") as info:
        _drain_live(s, lambda: False, timeout_s=5.0)
    assert not isinstance(info.value, FrameError) and s.stats().bad == 0
    s.stop()


def test_an_acquisition_ends_at_its_first_bad_frame() -> None:
    s = FrameStreamer(_scripted_grab(["good", "good", "bad"]), mode=StreamMode.ACQUISITION,
                      device="d", n_frames=10, queue_size=10)
    s.start()
    got = [s.pop(5.0).frame_id for _ in range(2)]
    with pytest.raises(FrameError, match="corrupt MJPEG"):
        s.pop(5.0)
    s.stop()
    assert got == [0, 1] and s.stats().acquired == 2 and s.stats().bad == 1


def test_streamer_validates_max_bad_frames() -> None:
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="max_bad_frames"):
            FrameStreamer(_scripted_grab([]), mode=StreamMode.LIVE, device="d",
                          max_bad_frames=bad)  # type: ignore[arg-type]
