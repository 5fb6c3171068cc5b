"""GenICam backend against the real GenTL producers from PyPI (viky.cti, TLSimu.cti)."""

from __future__ import annotations

import logging
import shutil
import signal
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.camera import (
    AcquisitionFinished,
    CameraError,
    CameraTimeout,
    FrameError,
    Roi,
    TriggerMode,
)
from drivers.genicam import GenICamCamera, find_producers, list_genicam_devices

pytestmark = pytest.mark.timeout(90)


def test_find_producers_searches_env_config_cache_and_package(
    tlsimu_cti: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "empty-cache"))
    monkeypatch.delenv("LENSLESSCAM_GENTL_PATH", raising=False)
    monkeypatch.setenv("GENICAM_GENTL64_PATH", str(tlsimu_cti.parent))
    found = find_producers()
    names = [p.name for p in found]
    assert names[0] == "TLSimu.cti" and "viky.cti" in names
    monkeypatch.delenv("GENICAM_GENTL64_PATH")
    monkeypatch.setenv("LENSLESSCAM_GENTL_PATH", str(tlsimu_cti))
    assert next(p.name for p in find_producers()) == "TLSimu.cti"
    assert [p.name for p in find_producers(use_environment=False)] == ["viky.cti"]
    assert find_producers([tlsimu_cti, tlsimu_cti], include_package=False) == [tlsimu_cti]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="ELF platform")
def test_producer_problem_accepts_only_shared_libraries(
    tlsimu_cti: Path, viky_cti: Path, tmp_path: Path,
) -> None:
    from drivers.genicam import producer_problem

    assert producer_problem(tlsimu_cti) is None and producer_problem(viky_cti) is None
    for name, head, kind in (("pe.cti", b"MZ\x90\x00", "Windows (PE)"),
                             ("macho.cti", b"\xcf\xfa\xed\xfe", "macOS (Mach-O)")):
        (tmp_path / name).write_bytes(head + bytes(60))  # libraries, but not for Linux
        assert producer_problem(tmp_path / name) == (
            f"is a library for {kind}, not for this platform (ELF)")
    (tmp_path / "empty.cti").write_bytes(b"")
    (tmp_path / "text.cti").write_text("#!/bin/sh\n")
    assert "empty" in (producer_problem(tmp_path / "empty.cti") or "")
    assert "not a shared library" in (producer_problem(tmp_path / "text.cti") or "")
    assert "cannot be read" in (producer_problem(tmp_path / "missing.cti") or "")
    shutil.copy(viky_cti, tmp_path / "viky.cti")  # the one usable producer in the folder
    skipped: list[str] = []
    found = find_producers([tmp_path, tlsimu_cti], use_environment=False,
                           include_cache=False, include_package=False, skipped=skipped)
    assert [p.name for p in found] == ["viky.cti", "TLSimu.cti"]
    assert [line.split(" skipped: ")[0].rsplit("/", 1)[1] for line in skipped] == [
        "empty.cti", "macho.cti", "pe.cti", "text.cti"]


def test_list_devices_of_both_producers(viky_cti: Path, tlsimu_cti: Path) -> None:
    devices = list_genicam_devices([viky_cti, tlsimu_cti])
    assert [d.index for d in devices] == list(range(7))
    assert [d.model for d in devices[:3]] == ["Viky"] * 3
    assert {d.model for d in devices[3:]} == {"TLSimuMono", "TLSimuColor"}
    assert devices[3].producer == str(tlsimu_cti) and devices[3].spec == "genicam:3"


def test_device_index_counts_over_all_producers(viky_cti: Path, tlsimu_cti: Path) -> None:
    with GenICamCamera(3, producers=[viky_cti, tlsimu_cti]) as cam:
        assert cam.capabilities().model == "TLSimuMono"
    with pytest.raises(CameraError, match="no GenICam device 9"):
        GenICamCamera(9, producers=[viky_cti, tlsimu_cti]).open()
    with pytest.raises(CameraError, match="no GenTL producer"):
        GenICamCamera(0, producers=[]).open()


def test_opening_keeps_the_sigint_handler(viky_cti: Path) -> None:
    before = signal.getsignal(signal.SIGINT)
    with GenICamCamera(0, producer=viky_cti):
        assert signal.getsignal(signal.SIGINT) is before


def test_missing_sfnc_nodes_are_reported_by_name(viky_cti: Path, tlsimu_cti: Path) -> None:
    with GenICamCamera(0, producer=viky_cti) as viky:
        with pytest.raises(CameraError, match="'TriggerSoftware'"):
            viky.trigger_mode = TriggerMode.SOFTWARE
        with pytest.raises(CameraError, match="'ExposureTime'"):
            viky.exposure_us = 1000.0
        with pytest.raises(CameraError, match="OffsetX"):
            viky.roi = Roi(8, 0, 100, 100)
    with GenICamCamera(0, producer=tlsimu_cti) as tlsimu:
        with pytest.raises(CameraError, match="'AcquisitionFrameRate'"):
            tlsimu.frame_rate_hz = 10.0
        with pytest.raises(ValueError, match="Width"):
            tlsimu.roi = Roi(0, 0, 66, 48)  # Width increment is 4


def test_the_resulting_frame_rate_is_the_devices_own_node_where_it_has_one(
        viky_cti: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """viky has no sensor timing and no ResultingFrameRate: the rate it gives is unknown
    (None, not its set 20 Hz); a device with the SFNC node is read."""
    with GenICamCamera(0, producer=viky_cti) as viky:
        assert viky.frame_rate_hz > 0 and viky.timing is None
        assert viky.resulting_frame_rate_hz is None

        class Node:
            value = 12.5

        has, node = viky._has, viky._node
        monkeypatch.setattr(viky, "_has", lambda name, write=True: (
            name == "AcquisitionResultingFrameRate" or has(name, write)))
        monkeypatch.setattr(viky, "_node", lambda name: (
            Node() if name == "AcquisitionResultingFrameRate" else node(name)))
        assert viky.resulting_frame_rate_hz == 12.5


def test_fetch_timeout_becomes_camera_timeout(tlsimu_cti: Path) -> None:
    with GenICamCamera(0, producer=tlsimu_cti) as cam:
        cam.roi = Roi(0, 0, 32, 32)
        cam.trigger_mode = TriggerMode.SOFTWARE
        t0 = time.monotonic()
        with pytest.raises(CameraTimeout, match="no frame within"):
            cam._fetch_untriggered(0.2)  # armed, waiting for a trigger that never comes
        assert time.monotonic() - t0 < 2.0
        assert cam.snap().shape == (32, 32)  # recovers


def test_frames_report_the_format_actually_delivered(
    tlsimu_cti: Path, caplog: pytest.LogCaptureFixture,
) -> None:
    with GenICamCamera(0, producer=tlsimu_cti) as cam:
        cam.roi = Roi(0, 0, 32, 32)
        cam.trigger_mode = TriggerMode.SOFTWARE
        cam.pixel_format = "Mono16"  # TLSimu accepts the setting but keeps sending Mono8
        assert cam.pixel_format == "Mono16"  # what the device reads back, until a frame shows
        with caplog.at_level(logging.WARNING, logger="drivers.genicam"):
            frame = cam.snap()
            cam.snap()  # said once, not per frame
        caps = cam.capabilities()
        # the camera is not taken as delivering 16 bits any more
        assert cam.pixel_format == "Mono8" and cam.bit_depth == 8
        lines = [r.getMessage() for r in caplog.records if "PixelFormat" in r.getMessage()]
        assert len(lines) == 1 and "\n" not in lines[0]
        assert "PixelFormat is Mono16 but the device delivers Mono8 frames" in lines[0]
        cam.pixel_format = "Mono8"  # the device follows this one: nothing to say
        assert cam.snap().extra.get("requested_pixel_format") is None
        assert len([r for r in caplog.records if "PixelFormat" in r.getMessage()]) == 1
    assert frame.pixel_format == "Mono8" and frame.pixels.dtype == np.uint8
    assert frame.bit_depth == 8 and frame.extra["requested_pixel_format"] == "Mono16"
    # a ROI, and the whole sensor it is on (TLSimu's Width/Height maxima: 4096)
    assert frame.shape == (32, 32) and frame.sensor == (caps.sensor_height, caps.sensor_width)
    assert frame.sensor == (4096, 4096)


def test_free_run_snaps_have_increasing_ids(viky_cti: Path) -> None:
    with GenICamCamera(0, producer=viky_cti) as cam:
        cam.roi = Roi(0, 0, 100, 100)
        cam.frame_rate_hz = 200.0
        ids = [cam.snap().frame_id for _ in range(3)]
    assert ids == sorted(set(ids))  # viky restarts its counter per acquisition; ours does not


# --------------------------------------------------------------------------------------------
# 3. stream 200 frames from TLSimu


@pytest.fixture
def tlsimu(tlsimu_cti: Path) -> Iterator[GenICamCamera]:
    cam = GenICamCamera(0, producer=tlsimu_cti)
    cam.open()
    try:
        cam.roi = Roi(0, 0, 64, 64)
        yield cam
    finally:
        cam.close()


def test_newest_frame_path_with_a_slow_consumer(tlsimu: GenICamCamera) -> None:
    t0 = time.monotonic()
    tlsimu.start_live(n_frames=200)
    seen = []
    while True:
        frame = tlsimu.latest_frame(timeout_s=1.0)
        if frame is None:
            if not tlsimu.stream_stats().running:
                break
            continue
        seen.append(frame.frame_id)
        time.sleep(0.02)  # the display takes 20 ms per frame
    stream_time = time.monotonic() - t0
    stats = tlsimu.stream_stats()
    tlsimu.stop()
    assert stats.acquired == 200
    assert stats.dropped > 0 and stats.pending == 0
    assert stats.delivered == len(seen)
    assert stats.delivered + stats.dropped == 200
    assert seen == sorted(seen) and len(set(seen)) == len(seen)
    # nothing blocked: the camera did not wait for the consumer (200 x 20 ms = 4 s)
    assert stream_time < 200 * 0.02 * 0.75
    assert stats.error is None


def test_lossless_path_delivers_all_200_frames(tlsimu: GenICamCamera) -> None:
    tlsimu.start_acquisition(n_frames=200, queue_size=256)
    frames = [tlsimu.pop_frame(timeout_s=5.0) for _ in range(200)]
    with pytest.raises(AcquisitionFinished):
        tlsimu.pop_frame(timeout_s=2.0)
    stats = tlsimu.stream_stats()
    tlsimu.stop()
    ids = [f.frame_id for f in frames]
    device_ids = [f.extra["device_frame_id"] for f in frames]
    assert ids == list(range(ids[0], ids[0] + 200))
    assert np.all(np.diff(device_ids) == 1)  # the device lost nothing either
    assert stats.acquired == stats.delivered == 200 and stats.dropped == 0
    assert all(f.shape == (64, 64) for f in frames)


@pytest.fixture
def one_incomplete_buffer(monkeypatch: pytest.MonkeyPatch) -> dict[str, int]:
    """The producer reports the next buffer incomplete (GenTL's BUFFER_INFO_IS_INCOMPLETE), as
    a dropped packet would; harvesters then discards it and emits INCOMPLETE_BUFFER."""
    from genicam import gentl

    real = gentl.Buffer.is_complete
    left = {"n": 0}

    def is_complete(self: Any) -> bool:
        if left["n"] > 0:
            left["n"] -= 1
            return False
        return bool(real(self))

    monkeypatch.setattr(gentl.Buffer, "is_complete", is_complete)
    return left


def test_an_incomplete_buffer_is_a_bad_frame_not_a_silent_gap(
    tlsimu: GenICamCamera, one_incomplete_buffer: dict[str, int],
) -> None:
    """harvesters' fetch discarded an incomplete buffer and waited for the next one: a snap
    came late, live view never counted the loss, and an acquisition got a gap."""
    one_incomplete_buffer["n"] = 1
    with pytest.raises(FrameError, match="incomplete buffer"):
        tlsimu.snap()
    assert tlsimu.snap().shape == (64, 64)  # the next buffer is whole
    tlsimu.start_live()
    deadline = time.monotonic() + 10.0
    while tlsimu.stream_stats().acquired < 5 and time.monotonic() < deadline:
        time.sleep(0.02)
    one_incomplete_buffer["n"] = 2
    while tlsimu.stream_stats().bad < 2 and time.monotonic() < deadline:
        time.sleep(0.02)
    acquired = tlsimu.stream_stats().acquired
    while tlsimu.stream_stats().acquired < acquired + 5 and time.monotonic() < deadline:
        time.sleep(0.02)
    stats = tlsimu.stream_stats()
    tlsimu.stop()
    assert stats.bad == 2 and "incomplete buffer" in (stats.last_bad or "")
    assert stats.running and stats.error is None  # live view went on
