"""Frames, errors, the streaming helper and the package surface, without any backend."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import threading
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
    s.stop()
    with pytest.raises(AcquisitionOverflow, match="queue of 2 frames overflowed"):
        s.pop(1.0)
    with pytest.raises(ValueError):
        FrameStreamer(grab, mode=StreamMode.IDLE, device="d")
    with pytest.raises(ValueError):
        FrameStreamer(grab, mode=StreamMode.LIVE, device="d", n_frames=0)


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
