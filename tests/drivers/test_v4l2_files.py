"""File sources of the V4L2/OpenCV backend that are not one clean stream.

Gaps and unreadable files in a sequence, frames of another dtype or size, colour files,
camera specs that are not a device, a sequence or a video, and a single image.
"""

from __future__ import annotations

import logging
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

import app.cli
from drivers.camera import CameraError
from drivers.registry import open_camera
from drivers.v4l2 import FrameSourceError, V4L2Camera

pytestmark = pytest.mark.timeout(60)

SHAPE = (48, 64)


def _frame(i: int, dtype: type = np.uint16, shape: tuple[int, ...] = SHAPE) -> np.ndarray:
    rng = np.random.default_rng(100 + i)
    a: np.ndarray = rng.integers(0, np.iinfo(dtype).max, shape, endpoint=True).astype(dtype)
    a.flat[0] = i  # frame index in a corner pixel
    return a


def _write(path: Path, a: np.ndarray) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), a)


@pytest.fixture
def seq(tmp_path: Path) -> Callable[..., str]:
    """Write a sequence ``name/%04d.png`` of frames 0..n-1 (with changes); return its pattern."""

    def make(name: str, n: int, *, skip: tuple[int, ...] = (),
             frames: dict[int, np.ndarray] | None = None) -> str:
        d = tmp_path / name
        for i in range(n):
            if i in skip:
                continue
            _write(d / f"{i:04d}.png", (frames or {}).get(i, _frame(i)))
        return str(d / "%04d.png")

    return make


# -- 1. gaps and unreadable files -----------------------------------------------------------


def test_a_missing_file_in_a_sequence_is_named_not_looped_over(seq: Callable[..., str]) -> None:
    pattern = seq("gap", 6, skip=(2,))
    missing = pattern % 2
    cam = V4L2Camera(pattern)
    with pytest.raises(FileNotFoundError, match=f"{missing} is missing.*goes on to .*0005.png"):
        cam.open()  # not frames 0, 1, 0, 1, ...
    assert not cam.is_open


def test_a_file_opencv_cannot_read_is_named(seq: Callable[..., str]) -> None:
    pattern = seq("junk", 3)
    Path(pattern % 1).write_text("not an image")
    with pytest.raises(FrameSourceError, match=r"cannot read .*junk/0001\.png"):
        V4L2Camera(pattern).open()  # not frame 0 forever


def test_a_truncated_file_is_named_at_every_read(seq: Callable[..., str]) -> None:
    pattern = seq("trunc", 3)
    whole = Path(pattern % 1).read_bytes()
    Path(pattern % 1).write_bytes(whole[: len(whole) // 3])  # a PNG header, then nothing
    with V4L2Camera(pattern) as cam:
        assert cam.snap().pixels.flat[0] == 0
        for _ in range(2):  # each time the loop reaches it; never a rewind to frame 0
            with pytest.raises(FrameSourceError, match=r"cannot read .*trunc/0001\.png"):
                cam.snap()
            assert [int(cam.snap().pixels.flat[0]) for _ in range(2)] == [2, 0]  # past it


def test_acquisition_from_a_broken_sequence_raises_instead_of_looping(
    seq: Callable[..., str],
) -> None:
    pattern = seq("trunc_acq", 4)
    Path(pattern % 2).write_bytes(Path(pattern % 2).read_bytes()[:100])
    with V4L2Camera(pattern) as cam:
        cam.start_acquisition(n_frames=8)
        got = [int(cam.pop_frame(timeout_s=5.0).pixels.flat[0]) for _ in range(2)]
        with pytest.raises(FrameSourceError, match=r"trunc_acq/0002\.png"):
            cam.pop_frame(timeout_s=5.0)
        cam.stop()
    assert got == [0, 1]


def _spoil_after_opening(path: str) -> None:
    Path(path).write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 20)  # a PNG that will not decode


def test_live_view_goes_on_past_a_file_that_cannot_be_decoded(
    seq: Callable[..., str], caplog: pytest.LogCaptureFixture
) -> None:
    pattern = seq("live_bad", 5)
    with caplog.at_level(logging.WARNING), V4L2Camera(pattern, frame_rate_hz=100) as cam:
        _spoil_after_opening(pattern % 2)  # the check at opening passed: it fails when read
        cam.start_live()
        seen: list[int] = []
        deadline = time.monotonic() + 20.0
        while (len(seen) < 12 or cam.stream_stats().bad < 2) and time.monotonic() < deadline:
            f = cam.latest_frame(0.5)  # raised here when the bad file ended live view
            if f is not None:
                seen.append(int(f.pixels.flat[0]))
        stats = cam.stream_stats()
        cam.stop()
    assert stats.running and stats.error is None
    assert stats.bad >= 2 and len(seen) >= 12  # past the bad file, round the loop, past again
    assert "live_bad/0002.png" in (stats.last_bad or "")
    assert 2 not in seen and {3, 4} & set(seen) and {0, 1} & set(seen)
    said = [r.getMessage() for r in caplog.records if "bad frame" in r.getMessage()]
    assert said and "live_bad/0002.png" in said[0]


def test_a_snap_or_an_acquisition_over_an_undecodable_file_names_it(
    seq: Callable[..., str],
) -> None:
    pattern = seq("snap_bad", 4)
    with V4L2Camera(pattern) as cam:
        _spoil_after_opening(pattern % 2)
        assert [int(cam.snap().pixels.flat[0]) for _ in range(2)] == [0, 1]
        with pytest.raises(FrameSourceError, match=r"cannot read .*snap_bad/0002\.png") as info:
            cam.snap()
        assert len(str(info.value).splitlines()) == 1
        assert int(cam.snap().pixels.flat[0]) == 3
        cam.start_acquisition(n_frames=8)  # from frame 0 again after the loop: 0, 1, then 2
        got = [int(cam.pop_frame(timeout_s=5.0).pixels.flat[0]) for _ in range(2)]
        with pytest.raises(FrameSourceError, match=r"snap_bad/0002\.png"):
            cam.pop_frame(timeout_s=5.0)  # the recording stops: no hole in its data
        cam.stop()
    assert got == [0, 1]


def test_a_sequence_that_starts_past_1_says_so(seq: Callable[..., str], tmp_path: Path) -> None:
    pattern = seq("late", 4, skip=(0, 1))
    with pytest.raises(FileNotFoundError, match=r"starts at .*late/0002\.png.*index 0 or 1"):
        V4L2Camera(pattern).open()


def test_a_complete_sequence_still_loops_and_names_its_files(seq: Callable[..., str]) -> None:
    pattern = seq("whole", 3)
    with V4L2Camera(pattern) as cam:
        frames = [cam.snap() for _ in range(4)]
    assert [int(f.pixels.flat[0]) for f in frames] == [0, 1, 2, 0]
    assert [f.extra["file"] for f in frames] == [pattern % i for i in (0, 1, 2, 0)]
    with V4L2Camera(pattern, loop=False) as cam:
        for _ in range(3):
            cam.snap()
        with pytest.raises(CameraError, match="end of file after 3 frames"):
            cam.snap()


# -- 2. one pixel format per source ---------------------------------------------------------


@pytest.mark.parametrize(("first", "rest", "label"), [
    (np.uint8, np.uint16, "Mono8"), (np.uint16, np.uint8, "Mono16"),
])
def test_a_frame_of_another_dtype_is_refused_naming_its_file(
    seq: Callable[..., str], first: type, rest: type, label: str
) -> None:
    pattern = seq("mix", 4, frames={0: _frame(0, first), **{i: _frame(i, rest) for i in (1, 2, 3)}})
    with V4L2Camera(pattern) as cam:
        f0 = cam.snap()
        assert f0.pixels.dtype == first and f0.pixel_format == label
        for i in (1, 2, 3):  # never a uint16 frame labelled Mono8 (or the reverse)
            with pytest.raises(FrameSourceError, match=rf"mix/000{i}\.png: {np.dtype(rest)}"):
                cam.snap()


def test_frames_that_are_not_8_or_16_bit_unsigned_are_refused(tmp_path: Path) -> None:
    import tifffile

    d = tmp_path / "float"
    d.mkdir()
    for i in range(2):
        tifffile.imwrite(d / f"{i:04d}.tif", _frame(i).astype(np.float32))
    with pytest.raises(FrameSourceError, match=r"float/0000\.tif: float32 pixels.*8- or 16-bit"):
        V4L2Camera(str(d / "%04d.tif")).open()  # was labelled Mono8


# -- 3. one size per source -----------------------------------------------------------------


def test_a_frame_of_another_size_is_refused_naming_its_file_and_sizes(
    seq: Callable[..., str],
) -> None:
    pattern = seq("odd", 5, frames={2: _frame(2, shape=(32, 40))})
    with V4L2Camera(pattern) as cam:
        assert [int(cam.snap().pixels.flat[0]) for _ in range(2)] == [0, 1]
        with pytest.raises(FrameSourceError, match=r"odd/0002\.png: 32x40 .* 48x64"):
            cam.snap()  # not a 32x40 "ROI" of a 48x64 sensor
        f3 = cam.snap()
    assert f3.pixels.flat[0] == 3 and f3.shape == SHAPE


# -- 4. colour files ------------------------------------------------------------------------


def test_colour_frames_are_reduced_to_grey_and_say_so(
    seq: Callable[..., str], caplog: pytest.LogCaptureFixture
) -> None:
    import cv2

    colour = {i: _frame(i, shape=(*SHAPE, 3)) for i in range(3)}
    pattern = seq("c16", 3, frames=colour)
    with caplog.at_level(logging.WARNING, logger="drivers.v4l2"), V4L2Camera(pattern) as cam:
        frames = [cam.snap() for _ in range(3)]
    for i, f in enumerate(frames):
        np.testing.assert_array_equal(f.pixels, cv2.cvtColor(colour[i], cv2.COLOR_BGR2GRAY))
        assert "luma weights" in f.extra["colour"] and "colour lost" in f.extra["colour"]
        assert f.metadata()["extra"]["colour"] == f.extra["colour"]  # saved with the frame
    said = [r for r in caplog.records if "grey" in r.getMessage()]
    assert len(said) == 1 and "c16" in said[0].getMessage()  # once per open


def test_grey_stored_as_colour_is_kept_exactly(seq: Callable[..., str]) -> None:
    grey = {i: _frame(i) for i in range(2)}
    pattern = seq("g3", 2, frames={i: np.dstack([g, g, g]) for i, g in grey.items()})
    with V4L2Camera(pattern) as cam:
        frames = [cam.snap() for _ in range(2)]
    for i, f in enumerate(frames):
        np.testing.assert_array_equal(f.pixels, grey[i])
        assert "equal" in f.extra["colour"] and "exact" in f.extra["colour"]


def test_grey_frames_carry_no_colour_note(seq: Callable[..., str]) -> None:
    with V4L2Camera(seq("grey", 2)) as cam:
        assert "colour" not in cam.snap().extra


# -- 5. camera specs ------------------------------------------------------------------------


def test_a_huge_device_index_is_a_value_error() -> None:
    for spec in ("v4l2:99999999999999999999", "v4l2:/dev/video99999999999999999999"):
        with pytest.raises(ValueError, match="index 99999999999999999999 is out of range"):
            open_camera(spec)


@pytest.mark.parametrize("pattern", ["%04d%04d.png", "%04s.png", "rec_50%.mkv", "%%04d.png"])
def test_a_bad_pattern_is_a_value_error(tmp_path: Path, pattern: str) -> None:
    with pytest.raises(ValueError, match=r"not an image-sequence pattern .*one %d or %0Nd"):
        V4L2Camera(str(tmp_path / pattern)).open()


@pytest.mark.parametrize("name", ["rec_50%.mkv", "rec_%04d.mkv"])
def test_a_video_file_with_percent_in_its_name_opens_as_a_file(
    ffv1_video: str, recorded_frames: np.ndarray, tmp_path: Path, name: str
) -> None:
    path = tmp_path / name
    shutil.copy(ffv1_video, path)
    with V4L2Camera(str(path)) as cam:
        f = cam.snap()
    np.testing.assert_array_equal(f.pixels, recorded_frames[0])


def test_cli_snap_spec_errors_are_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch,
    seq: Callable[..., str],
) -> None:
    monkeypatch.setattr(app.cli, "COMMAND_MODULES", ("app.commands.devices",))
    pattern = seq("m16", 2)
    specs = {
        "v4l2:99999999999999999999": "out of range",
        f"v4l2:{pattern.replace('%04d', '%04d%04d')}": "not an image-sequence pattern",
        f"v4l2:{pattern % 0}": "single image",
    }
    for i, (spec, text) in enumerate(specs.items()):
        rc = app.cli.main(["snap", "--camera", spec, "--out", str(tmp_path / f"{i}.tif")])
        err = capsys.readouterr().err
        assert rc == 2 and text in err and len(err.strip().splitlines()) == 1, err
        assert "Traceback" not in err


# -- 6. a single image ----------------------------------------------------------------------


def test_a_single_image_is_refused_with_the_pattern_to_give(seq: Callable[..., str]) -> None:
    pattern = seq("one", 3)
    with pytest.raises(ValueError, match=r"one/0001\.png is a single image.*one/%04d\.png"):
        V4L2Camera(pattern % 1).open()  # was: opens as Mono8, then every snap fails


def test_a_folder_is_refused_with_a_pattern(seq: Callable[..., str]) -> None:
    folder = str(Path(seq("dir", 2)).parent)
    with pytest.raises(FileNotFoundError, match=r"is a folder.*%04d\.png"):
        V4L2Camera(folder).open()


def test_the_output_check_protects_the_files_the_camera_reads(tmp_path):
    """The registry's own pattern rule missed a space-padded %4d frame ("   7.png"), which
    the camera reads: one rule now (drivers.v4l2.sequence_name_of)."""
    from drivers.registry import camera_source_match
    from drivers.v4l2 import sequence_name_of

    assert sequence_name_of("%4d.png", "   7.png") and sequence_name_of("%04d.png", "0007.png")
    assert not sequence_name_of("%04d.png", "7.png") and not sequence_name_of("x.png", "x.png")
    (tmp_path / "   7.png").write_bytes(b"")
    spec = f"v4l2:{tmp_path}/%4d.png"
    assert camera_source_match(spec, tmp_path / "   7.png") == tmp_path / "   7.png"
    assert camera_source_match(spec, tmp_path / "  12.png") is not None  # a frame to come
    assert camera_source_match(spec, tmp_path / "other.png") is None


def _mjpeg_video_with_a_bad_frame(path: Path, n: int, bad: int) -> None:
    """An MJPEG AVI of ``n`` grey frames (frame i all 20 i) whose frame ``bad`` is zeroed."""
    import struct

    import cv2

    w = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 10, (32, 24), isColor=False)
    assert w.isOpened(), "this OpenCV cannot write MJPEG AVI"
    for i in range(n):
        w.write(np.full((24, 32), 20 * i, np.uint8))
    w.release()
    data = bytearray(path.read_bytes())
    chunks = [i for i in range(len(data) - 4) if data[i:i + 4] == b"00dc"]
    k = chunks[1 + bad]  # the first '00dc' is the header's stream type, then one per frame
    size = struct.unpack("<I", data[k + 4:k + 8])[0]
    data[k + 8:k + 8 + size] = bytes(size)  # the frame's JPEG bytes, all zero
    path.write_bytes(bytes(data))


def _level(frame) -> int:  # type: ignore[no-untyped-def]
    return round(float(frame.pixels.mean()) / 20)


def test_a_video_frame_that_cannot_be_decoded_is_named_and_the_video_goes_on(
    tmp_path: Path,
) -> None:
    """A bad frame in the middle of a video was read as its end: a looping source went back
    to frame 0 (replaying the frames before it), and an acquisition ended as if the data had."""
    path = tmp_path / "rec.avi"
    _mjpeg_video_with_a_bad_frame(path, 6, bad=3)
    with V4L2Camera(str(path)) as cam:
        got = [_level(cam.snap()) for _ in range(3)]
        with pytest.raises(FrameSourceError, match=r"frame 3 of .*rec\.avi.*cannot be decoded"):
            cam.snap()
        got += [_level(cam.snap()) for _ in range(3)]  # 4, 5, then round the loop to 0
    assert got == [0, 1, 2, 4, 5, 0]
    with V4L2Camera(str(path), loop=False) as cam:
        cam.start_acquisition(n_frames=6)
        seen = [_level(cam.pop_frame(timeout_s=5.0)) for _ in range(3)]
        with pytest.raises(FrameSourceError, match="frame 3"):
            cam.pop_frame(timeout_s=5.0)  # the recording stops there: no hole in its data
        cam.stop()
    assert seen == [0, 1, 2]


def test_live_view_goes_on_past_a_video_frame_that_cannot_be_decoded(tmp_path: Path) -> None:
    path = tmp_path / "live.avi"
    _mjpeg_video_with_a_bad_frame(path, 5, bad=2)
    with V4L2Camera(str(path), frame_rate_hz=100) as cam:
        cam.start_live()
        seen: list[int] = []
        deadline = time.monotonic() + 20.0
        while (len(seen) < 10 or cam.stream_stats().bad < 2) and time.monotonic() < deadline:
            f = cam.latest_frame(0.5)
            if f is not None:
                seen.append(_level(f))
        stats = cam.stream_stats()
        cam.stop()
    assert stats.running and stats.error is None and stats.bad >= 2
    assert 2 not in seen and {3, 4} <= set(seen) and {0, 1} <= set(seen)
