"""The V4L2/OpenCV backend through the same VideoCapture interface, on recorded files."""

from __future__ import annotations

import logging
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from drivers.camera import CameraError, Feature, FeatureNotAvailable
from drivers.v4l2 import V4L2Camera, _is_file_source, list_v4l2_devices

pytestmark = pytest.mark.timeout(60)


@pytest.mark.parametrize("source", ["png_sequence", "ffv1_video"])
def test_recorded_16_bit_frames_come_back_exactly(
    source: str, request: pytest.FixtureRequest, recorded_frames: np.ndarray
) -> None:
    path = request.getfixturevalue(source)
    n = len(recorded_frames)
    with V4L2Camera(path) as cam:
        frames = [cam.snap() for _ in range(n + 2)]
        assert cam.pixel_format == "Mono16"
    for i, f in enumerate(frames):
        assert f.pixels.dtype == np.uint16 and f.bit_depth == 16
        np.testing.assert_array_equal(f.pixels, recorded_frames[i % n])  # loops at the end
        assert f.extra["file_frame_index"] == i % n


def test_end_of_file_without_loop(png_sequence: str) -> None:
    with V4L2Camera(png_sequence, loop=False) as cam:
        for _ in range(6):
            cam.snap()
        with pytest.raises(CameraError, match="end of file after 6 frames"):
            cam.snap()


def test_every_set_is_checked_and_reported(
    ffv1_video: str, caplog: pytest.LogCaptureFixture
) -> None:
    import cv2

    with V4L2Camera(ffv1_video) as cam:
        report = cam.settings_report()
        assert [r.name for r in report] == ["convert_rgb"]
        assert report[0].accepted and report[0].matches and report[0].readback == 0.0
        with caplog.at_level(logging.INFO, logger="drivers.v4l2"), warnings.catch_warnings():
            warnings.simplefilter("error")
            result = cam._checked_set("buffer_size", cv2.CAP_PROP_BUFFERSIZE, 1)
        assert not result.matches
        assert cam.mismatches() == [result]
        assert "buffer_size" in caplog.text and "requested 1.0" in result.line()


def test_files_have_no_exposure_gain_or_roi(png_sequence: str) -> None:
    with V4L2Camera(png_sequence) as cam:
        caps = cam.capabilities()
        assert caps.features == frozenset({Feature.FRAME_RATE})
        for attr, value in (("exposure_us", 1000.0), ("gain", 2.0)):
            with pytest.raises(FeatureNotAvailable, match="recorded file"):
                setattr(cam, attr, value)
            with pytest.raises(FeatureNotAvailable):
                getattr(cam, attr)
        with pytest.raises(FeatureNotAvailable, match="FOURCC"):
            cam.pixel_format = "Mono8"


def test_file_source_is_paced_at_the_set_rate(png_sequence: str) -> None:
    with V4L2Camera(png_sequence, frame_rate_hz=50.0) as cam:
        t0 = time.monotonic()
        cam.start_acquisition(n_frames=6)
        for _ in range(6):
            cam.pop_frame(timeout_s=2.0)
        elapsed = time.monotonic() - t0
        cam.stop()
    assert elapsed >= 5 / 50 * 0.9


def test_missing_sources_are_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="image sequence"):
        V4L2Camera(str(tmp_path / "%04d.png")).open()
    with pytest.raises(FileNotFoundError, match="video file"):
        V4L2Camera(str(tmp_path / "none.mkv")).open()
    with pytest.raises(ValueError, match="fourcc"):
        V4L2Camera(0, fourcc="RGB3")


def test_source_kinds_and_device_listing() -> None:
    assert not _is_file_source(0) and not _is_file_source("/dev/video2")
    assert _is_file_source("frames/%04d.png") and _is_file_source("x.mkv")
    assert V4L2Camera("/dev/video3").camera_id == "/dev/video3"
    for d in list_v4l2_devices():  # whatever this machine has (often nothing)
        assert d.path.startswith("/dev/video") and d.spec == f"v4l2:{d.index}"
