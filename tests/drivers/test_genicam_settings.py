"""GenICam settings are all or nothing: a refused ROI or pixel format leaves the camera as it was.

Against the real TLSimu producer (Width/Height: minimum 8, increment 4; no offset nodes).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from drivers.camera import CameraError, Roi, TriggerMode
from drivers.genicam import GenICamCamera

pytestmark = pytest.mark.timeout(90)


@pytest.fixture
def cam(tlsimu_cti: Path) -> Iterator[GenICamCamera]:
    c = GenICamCamera(0, producer=tlsimu_cti)
    c.open()
    try:
        c.roi = Roi(0, 0, 64, 48)
        c.trigger_mode = TriggerMode.SOFTWARE
        yield c
    finally:
        c.close()


def _record_writes(cam: GenICamCamera, monkeypatch: pytest.MonkeyPatch,
                   refuse: tuple[str, Any] | None = None) -> list[tuple[str, Any]]:
    """Node writes from now on; ``refuse`` = (node, value) the device turns down."""
    writes: list[tuple[str, Any]] = []
    real_set = cam._set

    def spy(feature: Any, name: str, value: Any) -> None:
        writes.append((name, value))
        if refuse == (name, value):
            raise ValueError(f"{cam.describe()}: {name} = {value!r} rejected: (device said no)")
        real_set(feature, name, value)

    monkeypatch.setattr(cam, "_set", spy)
    return writes


def test_the_declared_roi_grid_matches_the_device(cam: GenICamCamera) -> None:
    caps = cam.capabilities()
    assert caps.roi_step == (4, 4) and caps.roi_min_size == (8, 8)


def test_an_roi_off_the_grid_is_refused_before_anything_is_written(
    cam: GenICamCamera, monkeypatch: pytest.MonkeyPatch,
) -> None:
    writes = _record_writes(cam, monkeypatch)
    with pytest.raises(ValueError) as off_grid:
        cam.roi = Roi(0, 0, 256, 130)
    with pytest.raises(ValueError) as too_small:
        cam.roi = Roi(0, 0, 4, 48)
    assert writes == []
    assert cam.roi == Roi(0, 0, 64, 48)
    assert cam.snap().shape == (48, 64)
    assert str(off_grid.value).endswith(
        "ROI height 130 rejected: Height takes 8 plus a multiple of 4 (e.g. 128 or 132); "
        "nothing was changed")
    assert str(too_small.value).endswith(
        "ROI width 4 is below the minimum 8 (Width); nothing was changed")


def test_a_write_the_device_refuses_restores_the_previous_roi(
    cam: GenICamCamera, monkeypatch: pytest.MonkeyPatch,
) -> None:
    writes = _record_writes(cam, monkeypatch, refuse=("Height", 32))
    with pytest.raises(ValueError, match="Height = 32 rejected"):
        cam.roi = Roi(0, 0, 32, 32)
    assert writes == [("Width", 32), ("Height", 32), ("Width", 64), ("Height", 48)]
    assert cam.roi == Roi(0, 0, 64, 48)
    assert cam.snap().shape == (48, 64)
    cam.roi = Roi(0, 0, 128, 96)  # the camera is fine afterwards
    assert cam.snap().shape == (96, 128)


def test_roi_and_format_change_while_the_software_trigger_is_armed(cam: GenICamCamera) -> None:
    assert cam.snap().shape == (48, 64)  # leaves the acquisition armed (fast next snap)
    cam.roi = Roi(0, 0, 32, 16)  # was: 'Width' is not writable now
    assert cam.snap().shape == (16, 32)
    cam.pixel_format = "Mono8"  # was: 'PixelFormat' is not writable now
    assert cam.snap().pixel_format == "Mono8"


def test_a_pixel_format_the_device_does_not_keep_is_an_error(
    cam: GenICamCamera, monkeypatch: pytest.MonkeyPatch,
) -> None:
    real_set = cam._set

    def ignores_pixel_format(feature: Any, name: str, value: Any) -> None:
        if name != "PixelFormat":  # a device that takes the write and keeps its format
            real_set(feature, name, value)

    monkeypatch.setattr(cam, "_set", ignores_pixel_format)
    with pytest.raises(CameraError, match=r"PixelFormat = 'Mono16' was accepted but the device "
                                          r"reads back 'Mono8'; it stays at Mono8"):
        cam.pixel_format = "Mono16"
    assert cam.pixel_format == "Mono8" and cam.bit_depth == 8


def test_a_buffer_of_the_wrong_size_is_a_bad_frame_not_a_crash(
    cam: GenICamCamera, monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A buffer with fewer values than its width x height (a producer that hands over an
    incomplete one) is a FrameError naming both, which live view skips; the next frame is
    whole again."""
    from drivers.camera import FrameError

    real_fetch = cam._ia.try_fetch
    spoiled = {"left": 1}

    class _Short:
        def __init__(self, buffer: Any) -> None:
            self._b = buffer

        def __getattr__(self, name: str) -> Any:
            return getattr(self._b, name)

        @property
        def data(self) -> Any:
            return self._b.data[:-7]

    class _Buffer:
        def __init__(self, cm: Any) -> None:
            self._cm = cm

        def __enter__(self) -> Any:
            b = self._cm.__enter__()
            if spoiled["left"]:
                spoiled["left"] -= 1
                comp = _Short(b.payload.components[0])
                return type("B", (), {"payload": type("P", (), {"components": [comp]})(),
                                      "frame_id": b.frame_id, "timestamp_ns": 0})()
            return b

        def __exit__(self, *exc: Any) -> Any:
            return self._cm.__exit__(*exc)

    def fetch(**kw: Any) -> Any:
        b = real_fetch(**kw)
        return None if b is None else _Buffer(b)

    monkeypatch.setattr(cam._ia, "try_fetch", fetch)
    with pytest.raises(FrameError, match=r"delivered 3065 pixel values for a 48x64 frame"):
        cam.snap(timeout_s=5.0)
    assert cam.snap(timeout_s=5.0).pixels.shape == (48, 64)
