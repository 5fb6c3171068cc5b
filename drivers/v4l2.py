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
A file source loops by default and is paced at ``frame_rate_hz`` when one is given. It has
no exposure, gain, ROI, binning, shutter or trigger: those raise
:class:`~drivers.camera.FeatureNotAvailable`.
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
)

__all__ = ["SettingResult", "V4L2Camera", "V4L2DeviceInfo", "list_v4l2_devices"]

_log = logging.getLogger(__name__)

_FOURCCS = ("Y16 ", "GREY", "YUYV", "MJPG")
_FOURCC_ALIASES = {"Y16": "Y16 ", "Y16 ": "Y16 ", "GREY": "GREY", "YUYV": "YUYV", "MJPG": "MJPG"}


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
    if re.fullmatch(r"/dev/video\d+", s) or s.isdigit():
        return False
    return True


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
            self._source = int(s[len("/dev/video") :]) if s.startswith("/dev/video") else int(s)
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
        self._pace_hz: float | None = frame_rate_hz if self._is_file else None
        self._next_due = 0.0
        self._shape: tuple[int, int] = (0, 0)
        self._dtype: np.dtype[Any] = np.dtype(np.uint8)
        self._broken = False

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
        if self._is_file:
            src = str(self._source)
            if "%" in src:
                first = src % 0 if os.path.exists(src % 0) else src % 1
                if not os.path.exists(first):
                    raise FileNotFoundError(f"no image sequence at {src} (tried {first})")
                api = cv2.CAP_IMAGES
            else:
                if not os.path.exists(src):
                    raise FileNotFoundError(f"no video file at {src}")
                api = cv2.CAP_FFMPEG
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
            self._configure()
            self._probe()
        except BaseException:
            self._close()
            raise

    def _configure(self) -> None:
        import cv2

        if self._is_file:
            if self._cap.getBackendName() == "FFMPEG":
                self._checked_set("convert_rgb", cv2.CAP_PROP_CONVERT_RGB, 0)
            n = self._cap.get(cv2.CAP_PROP_FRAME_COUNT)
            self._n_file_frames = int(n) if n and n > 0 else 0
            self._file_pos = 0
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
        import cv2

        ok, img = self._cap.read()
        if not ok or img is None:
            raise CameraError(f"{self.describe()}: opened but no frame could be read")
        arr = self._to_mono(img)
        self._shape = (int(arr.shape[0]), int(arr.shape[1]))
        self._dtype = arr.dtype
        if self._is_file:
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
            self._file_pos = 0

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

    def _to_mono(self, img: np.ndarray) -> np.ndarray:
        import cv2

        if img.ndim == 2:
            if self._fourcc == "MJPG" and img.shape[0] == 1:
                decoded = cv2.imdecode(img.reshape(-1), cv2.IMREAD_UNCHANGED)
                if decoded is None:
                    raise CameraError(f"{self.describe()}: cannot decode a compressed frame")
                return self._to_mono(decoded)
            return img
        if img.ndim == 3 and self._fourcc == "YUYV" and img.shape[2] == 2:
            return np.ascontiguousarray(img[:, :, 0])  # luma of YUYV
        if img.ndim == 3 and img.shape[2] in (3, 4):
            code = cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
            return np.asarray(cv2.cvtColor(img, code))
        if img.ndim == 3 and img.shape[2] == 1:
            return img[:, :, 0]
        raise CameraError(f"{self.describe()}: unexpected frame shape {img.shape}")

    def _read_one(self) -> np.ndarray:
        """One frame (files loop at the end); raises CameraError at a real end or failure."""
        import cv2

        if self._is_file and self._n_file_frames and self._file_pos >= self._n_file_frames:
            if not self._loop:
                raise CameraError(f"{self.describe()}: end of file after {self._file_pos} frames")
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
            self._file_pos = 0
        ok, img = self._cap.read()
        if (not ok or img is None) and self._is_file and self._loop and self._file_pos > 0:
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
            self._file_pos = 0
            ok, img = self._cap.read()
        if not ok or img is None:
            raise CameraError(f"{self.describe()}: no frame (device gone or end of data)")
        self._file_pos += 1
        return self._to_mono(img)

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
                    raise CameraError(f"{self.describe()}: grab failed")
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
        pixels = box["img"]
        frame_id = self._frame_id
        self._frame_id += 1
        extra: dict[str, Any] = {"source": str(self._source)}
        if self._is_file:
            extra["file_frame_index"] = self._file_pos - 1
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
