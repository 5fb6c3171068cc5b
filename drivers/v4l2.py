"""V4L2 cameras through OpenCV, and recorded frames through the same ``VideoCapture`` path.

Devices (``/dev/videoN`` or an index) open with ``cv2.CAP_V4L2``. Settings are applied in
the order the driver needs them (FOURCC, size, fps, raw mode, buffer size, manual exposure,
gain) and every ``set()`` is checked by reading the property back: the results are kept as
:class:`SettingResult` rows (:meth:`V4L2Camera.settings_report`), mismatches are listed by
:meth:`V4L2Camera.mismatches` and logged at INFO (no warnings: a camera that rounds a value is
normal, the report says what it did).

- ``Y16``: raw 16-bit grey (``CAP_PROP_CONVERT_RGB`` 0 keeps it 16-bit),
- ``GREY``: 8-bit grey, ``YUYV``: the luma plane is kept, ``MJPG``: decoded to grey.
- Exposure: V4L2 ``exposure_absolute`` is in units of 100 us; ``CAP_PROP_AUTO_EXPOSURE`` 1
  is manual, 3 automatic (V4L2 menu values, passed through by OpenCV's V4L2 backend).

Files: a printf-style image sequence (``frames/%04d.png``, read by ``CAP_IMAGES``, 16-bit PNG
stays 16-bit) or a video file (``CAP_FFMPEG``; a lossless codec such as FFV1 in ``.mkv`` or
``.avi`` with ``CAP_PROP_CONVERT_RGB`` 0 gives the stored 16-bit grey frames back exactly).
A path that exists as a file is a video file, even with a ``%`` in its name; otherwise a path
with ``%`` must be a pattern with exactly one ``%d`` or ``%0Nd``. A single image file is
refused (give the pattern of its sequence). A sequence is the run of files from index 0 (or
1, as OpenCV reads them) up to the last file on disk: a missing or unreadable file before
the last one is an error that names it (OpenCV would stop there, and the loop would replay
the frames before the gap). A file source loops at its real end by default (for live
preview; ``loop=False`` raises there) and is paced at ``frame_rate_hz`` when one is given. It has
no exposure, gain, ROI, binning, shutter or trigger: those raise
:class:`~drivers.camera.FeatureNotAvailable`.

Every frame must have the size and the dtype (uint8 or uint16) of the first one: a frame
that differs raises :class:`FrameSourceError` naming the file (or the frame), instead of
arriving as a crop or with another frame's pixel format.

Bad frames: an undecodable file in a sequence, a video frame that cannot be decoded (told
from the video's end by reading one frame more: a frame there means it was not the end, and
that frame is the next one returned; two undecodable frames in a row read as the end), a
frame of another size or dtype, a corrupt MJPEG frame and a device read that returns no frame
raise a
:class:`~drivers.camera.FrameError` (a :class:`FrameSourceError` for the data's own faults),
and the source moves past that frame: :meth:`~V4L2Camera.snap` and an acquisition raise it,
live view skips it and goes on (until too many come in a row: a device whose every read
fails is gone). The real end of a file source with ``loop=False`` is not a frame error.

Colour frames (3 or 4 channels) are reduced to grey: 3 equal channels exactly (one is kept),
others by OpenCV's luma weights (``cv2.COLOR_BGR2GRAY``: 0.299 R + 0.587 G + 0.114 B); the
frame's ``extra["colour"]`` says which, and the first such frame after opening logs a warning
(the camera model is mono).
"""

from __future__ import annotations

import contextlib
import glob
import logging
import math
import os
import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drivers.camera import (
    CameraBase,
    CameraError,
    CameraTimeout,
    Capabilities,
    Feature,
    Frame,
    FrameError,
    SourceEnded,
)

__all__ = [
    "FrameSourceError",
    "SettingResult",
    "V4L2Camera",
    "V4L2DeviceInfo",
    "list_v4l2_devices",
]

_log = logging.getLogger(__name__)

_FOURCCS = ("Y16 ", "GREY", "YUYV", "MJPG")
_FOURCC_ALIASES = {"Y16": "Y16 ", "Y16 ": "Y16 ", "GREY": "GREY", "YUYV": "YUYV", "MJPG": "MJPG"}
_MAX_INDEX = 2**31 - 1  # OpenCV takes a device index as a C int
_SEQ_CONVERSION = re.compile(r"%(\d*)d")
_COLOUR_LUMA = "BGR to grey by OpenCV's luma weights (0.299 R + 0.587 G + 0.114 B); colour lost"
_COLOUR_EQUAL = "3 equal colour channels: one kept (exact)"


class FrameSourceError(FrameError, ValueError):
    """The frames of a source are not one consistent mono stream.

    An unreadable file, or a frame whose size or dtype differs from the first frame's. A
    :class:`~drivers.camera.FrameError` (live view skips that frame and goes on; the source has
    moved past it) and a :class:`ValueError`: the data, not the device, is at fault.
    """


@dataclass(frozen=True)
class SettingResult:
    """One checked ``VideoCapture.set``.

    What was asked, whether OpenCV accepted it, what the device reports afterwards, and
    whether that matches.
    """

    name: str
    requested: float | str
    accepted: bool
    readback: float | str | None
    matches: bool

    def line(self) -> str:
        """One-line human description."""
        status = "ok" if self.matches else ("MISMATCH" if self.accepted else "REJECTED")
        return f"{self.name}: requested {self.requested!r}, read back {self.readback!r} [{status}]"


@dataclass(frozen=True)
class V4L2DeviceInfo:
    """A V4L2 video node."""

    path: str
    index: int
    name: str

    @property
    def spec(self) -> str:
        """Camera spec for :func:`drivers.open_camera`."""
        return f"v4l2:{self.index}"


def list_v4l2_devices() -> list[V4L2DeviceInfo]:
    """Video nodes under /dev (without opening them)."""
    out = []
    for path in sorted(glob.glob("/dev/video*")):
        m = re.fullmatch(r"/dev/video(\d+)", path)
        if not m:
            continue
        idx = int(m.group(1))
        name = ""
        try:
            name = Path(f"/sys/class/video4linux/video{idx}/name").read_text().strip()
        except OSError:
            pass
        out.append(V4L2DeviceInfo(path, idx, name))
    return out


def _fourcc_str(code: float) -> str:
    c = int(code)
    if c <= 0:
        return ""
    return "".join(chr((c >> (8 * i)) & 0xFF) for i in range(4))


def _is_file_source(source: int | str | os.PathLike[str]) -> bool:
    if isinstance(source, int):
        return False
    s = str(source)
    if re.fullmatch(r"/dev/video\d+", s, re.ASCII) or re.fullmatch(r"\d+", s, re.ASCII):
        return False
    return True


def _check_pattern(pattern: str) -> re.Match[str]:
    """The one ``%d`` / ``%0Nd`` of a sequence pattern; ValueError for anything else."""
    convs = list(_SEQ_CONVERSION.finditer(pattern))
    if len(convs) != 1 or pattern.count("%") != 1:
        raise ValueError(
            f"{pattern}: no such file, and not an image-sequence pattern (one %d or %0Nd, "
            "like frames/%04d.png, and no other '%')"
        )
    return convs[0]


def _sequence_indices(pattern: str, conv: re.Match[str]) -> list[int]:
    """Sorted indices of the files on disk that ``pattern % index`` names exactly."""
    prefix, suffix = pattern[: conv.start()], pattern[conv.end() :]
    rx = re.compile(re.escape(prefix) + r"( *\d+)" + re.escape(suffix), re.ASCII)
    out = set()
    for path in glob.glob(glob.escape(prefix) + "*" + glob.escape(suffix)):
        m = rx.fullmatch(path)
        if m and pattern % int(m.group(1)) == path:
            out.add(int(m.group(1)))
    return sorted(out)


def sequence_name_of(pattern_name: str, name: str) -> bool:
    """Whether the file ``name`` is a frame of the sequence ``pattern_name`` (both file names).

    The rule the camera reads a sequence by (one ``%d`` or ``%0Nd``, ``pattern % index`` is
    the name exactly): the output checks of ``snap`` and ``calibrate`` use it too, so what
    the camera reads and what they protect are the same files. False for a name that is not
    a pattern.
    """
    try:
        conv = _check_pattern(pattern_name)
    except ValueError:
        return False
    prefix, suffix = pattern_name[: conv.start()], pattern_name[conv.end() :]
    m = re.fullmatch(re.escape(prefix) + r"( *\d+)" + re.escape(suffix), name, re.ASCII)
    return bool(m) and pattern_name % int(m.group(1)) == name


def _pattern_suggestion(path: str) -> str:
    """``frames/0007.png`` -> ``frames/%04d.png`` (the last run of digits in the name)."""
    head, name = os.path.split(path)
    runs = list(re.finditer(r"\d+", name, re.ASCII))
    if not runs:
        return os.path.join(head, "%04d" + os.path.splitext(name)[1])
    r = runs[-1]
    return os.path.join(head, f"{name[: r.start()]}%0{len(r.group())}d{name[r.end() :]}")


class V4L2Camera(CameraBase):
    """A V4L2 device, an image sequence or a video file, read through ``cv2.VideoCapture``.

    ``source``: a device index, ``/dev/videoN``, a sequence pattern (``frames/%04d.png``)
    or a video file path. Device options: ``fourcc`` (Y16, GREY, YUYV, MJPG), ``width``,
    ``height``, ``frame_rate_hz``, ``exposure_us``, ``gain``, all checked after setting.
    """

    backend = "v4l2"

    def __init__(
        self,
        source: int | str | os.PathLike[str] = 0,
        *,
        fourcc: str | None = None,
        width: int | None = None,
        height: int | None = None,
        frame_rate_hz: float | None = None,
        exposure_us: float | None = None,
        gain: float | None = None,
        loop: bool = True,
        bit_depth: int | None = None,
    ) -> None:
        self._is_file = _is_file_source(source)
        if self._is_file:
            self._source: int | str = str(source)
            cam_id = str(source)
        else:
            s = str(source)
            index = int(s[len("/dev/video") :]) if s.startswith("/dev/video") else int(s)
            if not 0 <= index <= _MAX_INDEX:
                raise ValueError(f"v4l2 device index {index} is out of range (0 to {_MAX_INDEX})")
            self._source = index
            cam_id = f"/dev/video{self._source}"
        super().__init__(cam_id)
        if fourcc is not None and fourcc.upper() not in _FOURCC_ALIASES:
            raise ValueError(f"fourcc {fourcc!r} not one of {sorted(_FOURCC_ALIASES)}")
        self._fourcc = None if fourcc is None else _FOURCC_ALIASES[fourcc.upper()]
        self._req_size = (width, height)
        self._req_fps = frame_rate_hz
        self._req_exposure = exposure_us
        self._req_gain = gain
        self._loop = bool(loop)
        self._declared_bits = bit_depth
        self._cap: Any = None
        self._settings: list[SettingResult] = []
        self._frame_id = 0
        self._n_file_frames = 0
        self._file_pos = 0
        self._ahead: Any = None  # a video's frame read past an undecodable one, next to return
        self._pace_hz: float | None = frame_rate_hz if self._is_file else None
        self._next_due = 0.0
        self._shape: tuple[int, int] = (0, 0)
        self._dtype: np.dtype[Any] = np.dtype(np.uint8)
        self._broken = False
        self._seq_first: int | None = None  # index of a sequence's first file; None: not one
        self._colour_said = False

    def describe(self) -> str:
        """Description for messages."""
        kind = "file" if self._is_file else "device"
        return f"v4l2 {kind} '{self.camera_id}'"

    # -- lifetime ------------------------------------------------------------------------------

    def _open(self) -> None:
        import cv2

        # OpenCV's own warnings go straight to stderr; this driver reports failures itself
        with contextlib.suppress(AttributeError):
            cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
        self._seq_first = None
        self._colour_said = False
        n_seq = 0
        if self._is_file:
            src = str(self._source)
            if os.path.isdir(src):
                raise FileNotFoundError(
                    f"{src} is a folder: give an image-sequence pattern like "
                    f"{os.path.join(src, '%04d.png')} or a video file"
                )
            if os.path.exists(src):  # a video file, '%' in its name or not
                if os.path.isfile(src) and cv2.haveImageReader(src):
                    raise ValueError(
                        f"{src} is a single image, not a sequence or a video: give the pattern "
                        f"of its sequence, like {_pattern_suggestion(src)}"
                    )
                api = cv2.CAP_FFMPEG
            elif "%" in src:
                self._seq_first, n_seq = self._find_sequence(src)
                api = cv2.CAP_IMAGES
            else:
                raise FileNotFoundError(f"no video file at {src}")
            cap = cv2.VideoCapture(src, api)
        else:
            cap = cv2.VideoCapture(int(self._source), cv2.CAP_V4L2)
        if not cap.isOpened():
            cap.release()
            raise CameraError(f"cannot open {self.describe()}")
        self._cap = cap
        self._settings = []
        self._broken = False
        try:
            if self._seq_first is not None:
                self._check_sequence_count(n_seq)
            self._configure()
            self._probe()
        except BaseException:
            self._close()
            raise

    @staticmethod
    def _find_sequence(pattern: str) -> tuple[int, int]:
        """First index and length of the sequence on disk; an error for a gap in it."""
        conv = _check_pattern(pattern)
        indices = _sequence_indices(pattern, conv)
        if not indices:
            raise FileNotFoundError(f"no image sequence at {pattern} (no file matches it)")
        present = set(indices)
        if 0 not in present and 1 not in present:
            raise FileNotFoundError(
                f"{pattern}: the sequence starts at {pattern % indices[0]}, but OpenCV reads "
                f"a sequence from index 0 or 1 (no {pattern % 0} or {pattern % 1}): renumber it"
            )
        first = 0 if 0 in present else 1
        n = 0
        while first + n in present:
            n += 1
        if indices[-1] >= first + n:
            raise FileNotFoundError(
                f"{pattern}: {pattern % (first + n)} is missing, but the sequence goes on to "
                f"{pattern % indices[-1]}: the frames after the gap would never be read "
                f"(fill the gap or renumber the files)"
            )
        return first, n

    def _check_sequence_count(self, n_on_disk: int) -> None:
        """OpenCV stops a sequence at a file it cannot read: name that file."""
        import cv2

        assert self._seq_first is not None
        n_cv = int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT))
        if n_cv < n_on_disk:
            raise FrameSourceError(
                f"cannot read {self._seq_path(max(n_cv, 0))}: not an image OpenCV can decode "
                f"(the sequence {self._source} goes on to {self._seq_path(n_on_disk - 1)})"
            )
        self._n_file_frames = n_on_disk

    def _seq_path(self, pos: int) -> str:
        assert self._seq_first is not None
        return str(self._source) % (self._seq_first + pos)

    def _frame_name(self, pos: int) -> str:
        """The file (sequence) or frame (video) at ``pos``, for messages."""
        if self._seq_first is not None:
            return self._seq_path(pos)
        return f"frame {pos} of {self.describe()}"

    def _configure(self) -> None:
        import cv2

        if self._is_file:
            self._file_pos = 0
            self._ahead = None
            if self._seq_first is not None:
                return  # its length was found on disk
            if self._cap.getBackendName() == "FFMPEG":
                self._checked_set("convert_rgb", cv2.CAP_PROP_CONVERT_RGB, 0)
            n = self._cap.get(cv2.CAP_PROP_FRAME_COUNT)
            self._n_file_frames = int(n) if n and n > 0 else 0
            return
        if self._fourcc is not None:
            code = cv2.VideoWriter.fourcc(*self._fourcc)
            self._checked_set("fourcc", cv2.CAP_PROP_FOURCC, code, as_fourcc=True)
        w, h = self._req_size
        if w is not None:
            self._checked_set("width", cv2.CAP_PROP_FRAME_WIDTH, float(w))
        if h is not None:
            self._checked_set("height", cv2.CAP_PROP_FRAME_HEIGHT, float(h))
        if self._req_fps is not None:
            self._checked_set("fps", cv2.CAP_PROP_FPS, float(self._req_fps))
        if self._fourcc in ("Y16 ", "GREY", "YUYV"):
            self._checked_set("convert_rgb", cv2.CAP_PROP_CONVERT_RGB, 0)
        self._checked_set("buffer_size", cv2.CAP_PROP_BUFFERSIZE, 1)
        if self._req_exposure is not None:
            self._set_exposure(float(self._req_exposure))
        if self._req_gain is not None:
            self._checked_set("gain", cv2.CAP_PROP_GAIN, float(self._req_gain))

    def _set_exposure(self, exposure_us: float) -> None:
        import cv2

        self._checked_set("auto_exposure", cv2.CAP_PROP_AUTO_EXPOSURE, 1)  # V4L2 manual
        self._checked_set("exposure", cv2.CAP_PROP_EXPOSURE, exposure_us / 100.0, tol=0.5)

    def _probe(self) -> None:
        """Read one frame to learn shape and dtype, then rewind a file source."""
        ok, img = self._cap.read()
        if not ok or img is None:
            if self._seq_first is not None:
                raise FrameSourceError(
                    f"cannot read {self._seq_path(0)}: not an image OpenCV can decode"
                )
            raise CameraError(f"{self.describe()}: opened but no frame could be read")
        arr, _ = self._to_mono(img)
        if arr.dtype not in (np.uint8, np.uint16):
            where = self._frame_name(0) if self._is_file else self.describe()
            raise FrameSourceError(
                f"{where}: {arr.dtype} pixels; this camera reads 8- or 16-bit unsigned grey "
                "(Mono8 or Mono16)"
            )
        self._shape = (int(arr.shape[0]), int(arr.shape[1]))
        self._dtype = arr.dtype
        if self._is_file:
            self._rewind()

    def _close(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()

    # -- checked settings ----------------------------------------------------------------------

    def _checked_set(
        self, name: str, prop: int, value: float, *, as_fourcc: bool = False, tol: float = 1e-6
    ) -> SettingResult:
        accepted = bool(self._cap.set(prop, value))
        raw = self._cap.get(prop)
        if as_fourcc:
            requested: float | str = _fourcc_str(value)
            readback: float | str | None = _fourcc_str(raw)
            matches = readback == requested
        else:
            requested = float(value)
            readback = None if raw == -1 else float(raw)
            matches = readback is not None and abs(readback - requested) <= tol * max(
                1.0, abs(requested)
            )
        result = SettingResult(name, requested, accepted, readback, matches)
        self._settings.append(result)
        if not matches:
            _log.info("%s: %s", self.describe(), result.line())
        return result

    def settings_report(self) -> list[SettingResult]:
        """Every checked ``set()`` since open, in order."""
        return list(self._settings)

    def mismatches(self) -> list[SettingResult]:
        """The checked settings the device did not take as asked."""
        return [r for r in self._settings if not r.matches]

    # -- capabilities and features -------------------------------------------------------------

    def capabilities(self) -> Capabilities:
        """Exposure, gain and frame rate on devices; frame rate (pacing) on files."""
        self._require_open()
        feats = {Feature.FRAME_RATE}
        if not self._is_file:
            feats |= {Feature.EXPOSURE, Feature.GAIN}
        return Capabilities(
            backend=self.backend,
            camera_id=self.camera_id,
            model="file" if self._is_file else "v4l2",
            sensor_width=self._shape[1],
            sensor_height=self._shape[0],
            features=frozenset(feats),
            pixel_formats=(self._pixel_format(),),
        )

    def _pixel_format(self) -> str:
        if self._declared_bits is not None:
            return f"Mono{self._declared_bits}"
        return "Mono16" if self._dtype == np.uint16 else "Mono8"

    def _get_pixel_format(self) -> str:
        """Mono8 or Mono16 (or Mono<bits> when ``bit_depth`` was declared)."""
        self._require_open()
        return self._pixel_format()

    def _do_set_pixel_format(self, value: str) -> None:
        if value == self.pixel_format:
            return
        raise self._unavailable(Feature.PIXEL_FORMAT, "fixed by the FOURCC chosen at construction")

    def _get_exposure_us(self) -> float:
        """Exposure (V4L2 exposure_absolute x 100 us)."""
        import cv2

        if self._is_file:
            raise self._unavailable(Feature.EXPOSURE, "a recorded file has no exposure control")
        self._require_open()
        with self._lock:
            return float(self._cap.get(cv2.CAP_PROP_EXPOSURE)) * 100.0

    def _do_set_exposure_us(self, value: float) -> None:
        if self._is_file:
            raise self._unavailable(Feature.EXPOSURE, "a recorded file has no exposure control")
        self._require_open()
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"exposure_us must be > 0, got {value!r}")
        with self._lock:
            self._set_exposure(float(value))

    def _get_gain(self) -> float:
        """CAP_PROP_GAIN (device units)."""
        import cv2

        if self._is_file:
            raise self._unavailable(Feature.GAIN, "a recorded file has no gain control")
        self._require_open()
        with self._lock:
            return float(self._cap.get(cv2.CAP_PROP_GAIN))

    def _do_set_gain(self, value: float) -> None:
        import cv2

        if self._is_file:
            raise self._unavailable(Feature.GAIN, "a recorded file has no gain control")
        self._require_open()
        with self._lock:
            self._checked_set("gain", cv2.CAP_PROP_GAIN, float(value))

    def _get_frame_rate_hz(self) -> float:
        """Device fps; for files the pacing rate (0: as fast as possible)."""
        import cv2

        self._require_open()
        if self._is_file:
            return float(self._pace_hz or 0.0)
        with self._lock:
            return float(self._cap.get(cv2.CAP_PROP_FPS))

    def _do_set_frame_rate_hz(self, value: float) -> None:
        import cv2

        self._require_open()
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"frame_rate_hz must be > 0, got {value!r}")
        if self._is_file:
            self._pace_hz = float(value)
            return
        with self._lock:
            self._checked_set("fps", cv2.CAP_PROP_FPS, float(value), tol=0.01)

    # -- frames --------------------------------------------------------------------------------

    def _to_mono(self, img: np.ndarray) -> tuple[np.ndarray, str | None]:
        """Grey pixels, and how colour was reduced to grey (None: the frame was grey)."""
        import cv2

        if img.ndim == 2:
            if self._fourcc == "MJPG" and img.shape[0] == 1:
                decoded = cv2.imdecode(img.reshape(-1), cv2.IMREAD_UNCHANGED)
                if decoded is None:
                    raise FrameError(f"{self.describe()}: cannot decode a compressed frame")
                return self._to_mono(decoded)
            return img, None
        if img.ndim == 3 and self._fourcc == "YUYV" and img.shape[2] == 2:
            return np.ascontiguousarray(img[:, :, 0]), None  # luma of YUYV
        if img.ndim == 3 and img.shape[2] in (3, 4):
            b, g, r = img[:, :, 0], img[:, :, 1], img[:, :, 2]
            alpha = "; alpha channel dropped" if img.shape[2] == 4 else ""
            if np.array_equal(b, g) and np.array_equal(b, r):
                return np.ascontiguousarray(b), _COLOUR_EQUAL + alpha
            code = cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
            return np.asarray(cv2.cvtColor(img, code)), _COLOUR_LUMA + alpha
        if img.ndim == 3 and img.shape[2] == 1:
            return img[:, :, 0], None
        raise CameraError(f"{self.describe()}: unexpected frame shape {img.shape}")

    def _read_one(self) -> tuple[np.ndarray, str | None]:
        """One frame and its colour note (files loop at the end).

        Raises CameraError at a real end or failure, FrameSourceError for a sequence file
        that cannot be read and for a frame of another size or dtype than the first, FrameError
        for a device read that returned no frame. After a frame error the source is past that
        frame (the next read is the next file; a sequence's loop goes on).
        """
        import cv2

        if self._is_file and self._n_file_frames and self._file_pos >= self._n_file_frames:
            if not self._loop:
                raise SourceEnded(f"{self.describe()}: end of file after {self._file_pos} "
                                  "frames")
            self._rewind()
        if self._ahead is not None:
            ok, img, self._ahead = True, self._ahead, None
        else:
            ok, img = self._cap.read()
        if (not ok or img is None) and self._seq_first is not None:
            # before the end found on disk (checked above): this file, not the end of data.
            # Move past it, whatever OpenCV's position did, so the loop goes on.
            bad = self._file_pos
            self._file_pos += 1
            if self._file_pos < self._n_file_frames:
                self._cap.set(cv2.CAP_PROP_POS_FRAMES, self._file_pos)
            raise FrameSourceError(
                f"cannot read {self._seq_path(bad)}: not an image OpenCV can decode"
            )
        if (not ok or img is None) and self._is_file and self._file_pos > 0:
            # A video: a frame that cannot be decoded, or the real end of one whose frame count
            # was missing or an estimate? OpenCV's reading moves past a bad frame, so one read
            # more tells: a frame there means this one was bad (kept for the next call).
            ok_next, img_next = self._cap.read()
            if ok_next and img_next is not None:
                bad = self._file_pos
                self._file_pos += 1
                self._ahead = img_next
                raise FrameSourceError(f"{self._frame_name(bad)}: cannot be decoded")
            if self._loop:  # the real end
                self._rewind()
                ok, img = self._cap.read()
        if not ok or img is None:
            if not self._is_file:  # one failed dequeue, or the device gone: the streamer's
                raise FrameError(  # limit of bad frames in a row tells which
                    f"{self.describe()}: the read returned no frame")
            raise CameraError(f"{self.describe()}: no frame (end of data)")
        pos = self._file_pos
        self._file_pos += 1
        arr, colour = self._to_mono(img)
        where = self._frame_name(pos) if self._is_file else self.describe()
        if arr.dtype != self._dtype:
            raise FrameSourceError(
                f"{where}: {arr.dtype} pixels, but the source was opened as {self._dtype} "
                f"({self._pixel_format()}): one source, one pixel format"
            )
        if arr.shape != self._shape:
            raise FrameSourceError(
                f"{where}: {arr.shape[0]}x{arr.shape[1]} pixels, but the source was opened "
                f"at {self._shape[0]}x{self._shape[1]} (rows x columns): one source, one size"
            )
        if colour is not None and not self._colour_said:
            self._colour_said = True
            _log.warning("%s: colour frames are reduced to grey: %s (each frame records it "
                         "in extra['colour'])", self.describe(), colour)
        return arr, colour

    def _rewind(self) -> None:
        import cv2

        self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
        self._file_pos = 0
        self._ahead = None

    def _grab_frame(self, timeout_s: float, *, discard_buffered: bool = False) -> Frame:
        """Read one frame in a helper thread so a stuck device cannot block past the timeout.

        ``discard_buffered``: first drop the frame waiting in the (one-buffer) queue, which
        may predate the call.
        """
        if self._broken:
            raise CameraError(f"{self.describe()}: an earlier read never returned; reopen")
        box: dict[str, Any] = {}

        def work() -> None:
            try:
                if discard_buffered and not self._cap.grab():
                    raise FrameError(f"{self.describe()}: grab failed")
                box["img"] = self._read_one()
            except BaseException as exc:
                box["exc"] = exc

        t = threading.Thread(target=work, name=f"v4l2-read-{self.camera_id}", daemon=True)
        t.start()
        t.join(timeout_s)
        if t.is_alive():
            self._broken = True
            raise CameraTimeout(f"{self.describe()}: no frame within {timeout_s:.3g} s")
        if "exc" in box:
            raise box["exc"]
        pixels, colour = box["img"]
        frame_id = self._frame_id
        self._frame_id += 1
        extra: dict[str, Any] = {"source": str(self._source)}
        if self._is_file:
            extra["file_frame_index"] = self._file_pos - 1
            if self._seq_first is not None:
                extra["file"] = self._seq_path(self._file_pos - 1)
        if colour is not None:
            extra["colour"] = colour
        return self._make_frame(pixels, frame_id, extra=extra)

    def _snap(self, timeout_s: float) -> Frame:
        with self._lock:
            return self._grab_frame(timeout_s, discard_buffered=not self._is_file)

    def _stream_begin(self) -> None:
        self._next_due = time.monotonic()

    def _stream_grab(self, poll_s: float) -> Frame | None:
        if self._pace_hz:
            wait = self._next_due - time.monotonic()
            if wait > poll_s:
                time.sleep(poll_s)
                return None
            if wait > 0:
                time.sleep(wait)
            self._next_due = max(self._next_due, time.monotonic() - 1.0) + 1.0 / self._pace_hz
        with self._lock:
            return self._grab_frame(max(poll_s, self.stream_timeout_s))
