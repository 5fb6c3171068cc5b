"""Camera protocol, frames, errors and the shared streaming helper.

A :class:`Camera` is any object with the members of the :class:`Camera` protocol; the
backends in this package derive from :class:`CameraBase`, which implements the parts that do
not depend on the hardware: the context manager, the feature-not-available defaults, frame
metadata and the two streaming paths.

Streaming has two paths that are never mixed:

- **newest frame** (live view): :meth:`Camera.start_live`, then poll
  :meth:`Camera.latest_frame` at the display rate. A background thread keeps only the newest
  frame; every frame replaced before anybody took it counts as a drop.
- **lossless** (acquisition): :meth:`Camera.start_acquisition`, then :meth:`Camera.pop_frame`
  every frame. Frames wait in a bounded queue; when it is full the acquisition stops and
  :class:`AcquisitionOverflow` is raised at the next pop (science data never silently loses a
  frame).

Starting one path while the other runs raises :class:`CameraError`; so does :meth:`Camera.snap`
while either runs. :meth:`Camera.stop` ends whichever runs (and is a no-op when none does).

Errors: a :class:`FrameError` is one bad frame (a corrupt compressed frame, a failed read, an
undecodable file, a frame of another size or pixel type); the source may still deliver the
next. Live view skips it (counted in :attr:`StreamStats.bad`, logged) and ends only after
:attr:`CameraBase.stream_max_bad_frames` bad frames in a row, or when no *good* frame came for
:attr:`CameraBase.stream_timeout_s` plus two frame times (:meth:`CameraBase.expected_frame_s`,
which follows the exposure and frame rate set while streaming). An acquisition ends at the
first error of any kind (its data must be whole). Any other :class:`CameraError` ends either
stream at once.

Feature names (:class:`Feature`) are shared by :class:`Capabilities` and
:class:`FeatureNotAvailable`, so a caller can ask first or try and catch.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import numbers
import os
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from enum import Enum, StrEnum
from types import TracebackType
from typing import Any, Protocol, Self

import numpy as np

from drivers.timing import ReadoutPattern, SensorTiming, ShutterMode

__all__ = [
    "AcquisitionFinished",
    "AcquisitionOverflow",
    "Camera",
    "CameraBase",
    "CameraError",
    "CameraTimeout",
    "Capabilities",
    "Feature",
    "FeatureNotAvailable",
    "Frame",
    "FrameError",
    "FrameStreamer",
    "Roi",
    "SourceEnded",
    "StreamMode",
    "StreamStats",
    "TriggerMode",
    "bit_depth_of",
    "check_black_level",
    "protocol_members",
    "read_frame_metadata",
]

_log = logging.getLogger(__name__)

#: Frame metadata format name and version (bumped on incompatible changes; an added key that
#: readers may lack, such as ``sensor``, is not one).
FRAME_FORMAT = "lenslesscam-frame"
FRAME_FORMAT_VERSION = 1


def read_frame_metadata(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The metadata of a saved frame (a TIFF whose description is :meth:`Frame.metadata`).

    ``sensor`` is checked ([rows, columns] of positive integers) and None where a frame saved
    before the sensor size was recorded has none; ``black_level`` likewise (a number >= 0, or
    None). Raises ValueError naming the file when it is not such a frame.
    """
    import json

    import tifffile

    try:
        with tifffile.TiffFile(path) as tf:
            meta = json.loads(tf.pages[0].description or "")
    except Exception as exc:
        raise ValueError(f"{path}: not a saved frame with its metadata ({exc})") from None
    if not isinstance(meta, dict) or meta.get("format") != FRAME_FORMAT:
        raise ValueError(f"{path}: not a saved frame with its metadata (format "
                         f"{FRAME_FORMAT})")
    if meta.get("sensor") is None:
        meta["sensor"] = None
    else:
        try:
            meta["sensor"] = list(_check_sensor(meta["sensor"]))
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None
    if meta.get("black_level") is None:  # unknown, or saved before it was recorded
        meta["black_level"] = None
    else:
        try:
            meta["black_level"] = check_black_level(meta["black_level"])
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None
    return meta


def check_black_level(value: Any) -> float:
    """A black level as a float: a finite number >= 0 (ValueError naming the value otherwise)."""
    try:
        level = float(value)
    except (TypeError, ValueError):
        level = math.nan
    if isinstance(value, bool) or not (math.isfinite(level) and level >= 0):
        raise ValueError(f"black level must be a finite number >= 0 (camera codes), got "
                         f"{value!r}")
    return level


def _check_sensor(value: Any) -> tuple[int, int]:
    try:
        rows, cols = value
        if int(rows) != rows or int(cols) != cols or rows < 1 or cols < 1:
            raise ValueError
    except (TypeError, ValueError):
        raise ValueError(
            f"sensor size must be (rows, columns) of positive integers, got {value!r}"
        ) from None
    return int(rows), int(cols)


# --------------------------------------------------------------------------------------------
# errors


class CameraError(RuntimeError):
    """A camera could not do what was asked (the message names the device)."""


class CameraTimeout(CameraError, TimeoutError):
    """No frame arrived within the timeout."""


class FrameError(CameraError):
    """One bad frame: the source may still deliver the next one.

    A corrupt or undecodable frame, a read or dequeue that returned no frame, a frame whose
    size or pixel type differs from the stream's. The message names the frame's problem (and
    its file, for recorded frames). A live stream skips such frames (see
    :class:`FrameStreamer`); :meth:`Camera.snap` and an acquisition raise them.
    """


class FeatureNotAvailable(CameraError):
    """The device has no such feature (or not in this mode).

    ``feature`` is a :class:`Feature` value (or a device feature name), ``device`` describes
    the camera.
    """

    def __init__(self, feature: str, device: str, detail: str = "") -> None:
        self.feature = str(feature.value if isinstance(feature, Enum) else feature)
        self.device = device
        self.detail = detail
        msg = f"{device}: feature '{self.feature}' is not available"
        super().__init__(f"{msg} ({detail})" if detail else msg)


class AcquisitionOverflow(CameraError):
    """The lossless acquisition queue was full: the consumer did not keep up."""


class AcquisitionFinished(CameraError):
    """A finite acquisition delivered all its frames; there is nothing more to pop."""


class SourceEnded(CameraError):
    """A file source (an image sequence, a video) opened without looping reached its end."""


# --------------------------------------------------------------------------------------------
# enums and small value types


class Feature(StrEnum):
    """Names of the optional camera features (see :meth:`Capabilities.supports`)."""

    EXPOSURE = "exposure"
    GAIN = "gain"
    ROI = "roi"
    BINNING = "binning"
    PIXEL_FORMAT = "pixel_format"
    SHUTTER_MODE = "shutter_mode"
    READOUT_PATTERN = "readout_pattern"
    LINE_TIME = "line_time"
    TRIGGER_DELAY = "trigger_delay"
    TRIGGER_SOFTWARE = "trigger_software"
    FRAME_RATE = "frame_rate"


class TriggerMode(StrEnum):
    """How frames are started."""

    FREE_RUN = "free-run"
    SOFTWARE = "software"


class StreamMode(StrEnum):
    """Which streaming path runs."""

    IDLE = "idle"
    LIVE = "live"
    ACQUISITION = "acquisition"


_BIT_DEPTHS = {
    "Mono8": 8,
    "Mono10": 10,
    "Mono12": 12,
    "Mono14": 14,
    "Mono16": 16,
}


def bit_depth_of(pixel_format: str) -> int:
    """Bits per pixel of a mono pixel format name (``Mono8`` .. ``Mono16``)."""
    try:
        return _BIT_DEPTHS[pixel_format]
    except KeyError:
        raise ValueError(
            f"unknown pixel format {pixel_format!r}; expected one of {sorted(_BIT_DEPTHS)}"
        ) from None


@dataclass(frozen=True)
class Roi:
    """Region of interest in *unbinned sensor pixels* (x = column, y = row of the corner)."""

    x: int
    y: int
    width: int
    height: int

    def __post_init__(self) -> None:
        for name in ("x", "y", "width", "height"):
            v = getattr(self, name)
            if int(v) != v:
                raise ValueError(f"Roi.{name} must be an integer, got {v!r}")
            object.__setattr__(self, name, int(v))
        if self.x < 0 or self.y < 0 or self.width < 1 or self.height < 1:
            raise ValueError(f"invalid ROI {self}")

    def to_dict(self) -> dict[str, int]:
        """Plain-JSON form."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Roi:
        """Inverse of :meth:`to_dict`."""
        return cls(int(d["x"]), int(d["y"]), int(d["width"]), int(d["height"]))


@dataclass(frozen=True)
class Capabilities:
    """What a camera can do. ``features`` holds :class:`Feature` values it supports."""

    backend: str
    camera_id: str
    model: str
    sensor_width: int
    sensor_height: int
    features: frozenset[Feature]
    pixel_formats: tuple[str, ...]
    trigger_modes: tuple[TriggerMode, ...] = (TriggerMode.FREE_RUN,)
    shutter_modes: tuple[ShutterMode, ...] = ()
    readout_patterns: tuple[ReadoutPattern, ...] = ()
    exposure_range_us: tuple[float, float] | None = None
    gain_range: tuple[float, float] | None = None
    frame_rate_range_hz: tuple[float, float] | None = None
    binning_factors: tuple[int, ...] = (1,)
    roi_min_size: tuple[int, int] = (1, 1)  # (width, height)
    roi_step: tuple[int, int] = (1, 1)  # (width, height) increments

    def supports(self, feature: Feature | str) -> bool:
        """Whether ``feature`` is available."""
        return Feature(feature) in self.features

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form."""
        return {
            "backend": self.backend,
            "camera_id": self.camera_id,
            "model": self.model,
            "sensor_width": self.sensor_width,
            "sensor_height": self.sensor_height,
            "features": sorted(f.value for f in self.features),
            "pixel_formats": list(self.pixel_formats),
            "trigger_modes": [m.value for m in self.trigger_modes],
            "shutter_modes": [m.value for m in self.shutter_modes],
            "readout_patterns": [p.value for p in self.readout_patterns],
            "exposure_range_us": _opt_list(self.exposure_range_us),
            "gain_range": _opt_list(self.gain_range),
            "frame_rate_range_hz": _opt_list(self.frame_rate_range_hz),
            "binning_factors": list(self.binning_factors),
            "roi_min_size": list(self.roi_min_size),
            "roi_step": list(self.roi_step),
        }


def _opt_list(t: tuple[float, float] | None) -> list[float] | None:
    return None if t is None else [float(t[0]), float(t[1])]


# --------------------------------------------------------------------------------------------
# frames


@dataclass(frozen=True)
class Frame:
    """One image and everything needed to interpret it later.

    ``pixels`` is owned by the frame and read-only: an array that does not own its memory
    (a view, a device buffer) is copied; an array that does is taken over (and made
    read-only). Shape is ``(roi.height // binning, roi.width // binning)``.

    ``timing`` describes the *full sensor* (all rows); the shutter function of this frame is
    ``recon.preprocess.downsample_rows(shutter_function(timing, w)[:, roi.y : roi.y +
    roi.height], binning)``.
    ``timestamp`` is host time (``time.time()``) when the frame reached the driver;
    device timestamps, when there are any, go into ``extra``. ``exposure_us`` and ``gain``
    are ``None`` when the device cannot report them.
    ``sensor`` is (rows, columns) of the whole sensor the frame came from, in unbinned pixels
    (the backends fill it from :meth:`Camera.capabilities`); ``None`` when unknown. It tells
    a region of interest from a frame of another, smaller sensor; ``roi`` must lie inside it.
    ``black_level`` is the code a pixel reads with no light (the readout's offset, in the
    frame's codes) where the backend knows it (the simulated camera's ``dark_offset_adu``),
    else ``None``: the app's automatic dark level takes it before estimating one.
    """

    pixels: np.ndarray
    frame_id: int
    timestamp: float
    exposure_us: float | None
    gain: float | None
    roi: Roi
    binning: int
    pixel_format: str
    bit_depth: int
    timing: SensorTiming | None
    backend: str
    camera_id: str
    extra: Mapping[str, Any] = field(default_factory=dict)
    sensor: tuple[int, int] | None = None
    black_level: float | None = None

    def __post_init__(self) -> None:
        arr = self.pixels
        if self.black_level is not None:
            object.__setattr__(self, "black_level", check_black_level(self.black_level))
        if not isinstance(arr, np.ndarray):
            raise TypeError(f"Frame.pixels must be a numpy array, got {type(arr).__name__}")
        if self.sensor is not None:
            sensor = _check_sensor(self.sensor)
            r = self.roi
            if r.y + r.height > sensor[0] or r.x + r.width > sensor[1]:
                raise ValueError(
                    f"frame ROI {r} lies outside its {sensor[0]}x{sensor[1]} (rows x columns) "
                    "sensor")
            object.__setattr__(self, "sensor", sensor)
        if not (arr.flags.owndata and arr.flags.c_contiguous):
            arr = np.array(arr, copy=True, order="C")
        arr.flags.writeable = False
        object.__setattr__(self, "pixels", arr)
        object.__setattr__(self, "frame_id", int(self.frame_id))
        object.__setattr__(self, "extra", dict(self.extra))

    @property
    def shape(self) -> tuple[int, ...]:
        """Shape of the pixel array."""
        return tuple(self.pixels.shape)

    def metadata(self) -> dict[str, Any]:
        """Everything but the pixels, as plain JSON types (format-versioned)."""
        return {
            "format": FRAME_FORMAT,
            "format_version": FRAME_FORMAT_VERSION,
            "frame_id": self.frame_id,
            "timestamp": float(self.timestamp),
            "exposure_us": None if self.exposure_us is None else float(self.exposure_us),
            "gain": None if self.gain is None else float(self.gain),
            "roi": self.roi.to_dict(),
            "sensor": None if self.sensor is None else list(self.sensor),
            "binning": int(self.binning),
            "pixel_format": self.pixel_format,
            "bit_depth": int(self.bit_depth),
            "dtype": str(self.pixels.dtype),
            "shape": list(self.pixels.shape),
            "timing": None if self.timing is None else self.timing.to_dict(),
            "backend": self.backend,
            "camera_id": self.camera_id,
            "black_level": self.black_level,
            "extra": _jsonable(self.extra),
        }


def _jsonable(obj: Any) -> Any:
    """Convert numpy scalars/arrays, enums and tuples to plain JSON types."""
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, Enum):
        return obj.value
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if obj is None or isinstance(obj, str | int | float | bool):
        return obj
    return str(obj)


# --------------------------------------------------------------------------------------------
# the protocol


class Camera(Protocol):
    """What every camera backend offers.

    (Not ``runtime_checkable``: Python 3.11's ``isinstance`` would read every property, and a
    missing feature raises. Check conformance with :func:`protocol_members` on the type.)

    Units: exposure in microseconds, line time and trigger delay in microseconds, frame rate
    in hertz; gain in the device's unit (dB for GenICam SFNC, a linear factor for the
    simulated camera). A feature the device lacks raises :class:`FeatureNotAvailable` on both
    get and set; :meth:`capabilities` says which exist.
    """

    @property
    def backend(self) -> str:
        """Backend name (``sim``, ``genicam``, ``v4l2``)."""
        ...

    @property
    def camera_id(self) -> str:
        """Identifier of this device within its backend."""
        ...

    @property
    def is_open(self) -> bool:
        """Whether the device is open."""
        ...

    def open(self) -> None:
        """Open the device (idempotent)."""
        ...

    def close(self) -> None:
        """Stop streaming and release the device (idempotent)."""
        ...

    def __enter__(self) -> Self:
        """Open and return self."""
        ...

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        """Close."""
        ...

    def capabilities(self) -> Capabilities:
        """Features, formats, ranges."""
        ...

    @property
    def exposure_us(self) -> float:
        """Exposure time in microseconds."""
        ...

    @exposure_us.setter
    def exposure_us(self, value: float) -> None: ...

    @property
    def gain(self) -> float:
        """Gain (device units)."""
        ...

    @gain.setter
    def gain(self, value: float) -> None: ...

    @property
    def roi(self) -> Roi:
        """Region of interest in unbinned sensor pixels."""
        ...

    @roi.setter
    def roi(self, value: Roi) -> None: ...

    @property
    def binning(self) -> int:
        """Symmetric binning factor."""
        ...

    @binning.setter
    def binning(self, value: int) -> None: ...

    @property
    def pixel_format(self) -> str:
        """Pixel format name (``Mono8`` .. ``Mono16``)."""
        ...

    @pixel_format.setter
    def pixel_format(self, value: str) -> None: ...

    @property
    def bit_depth(self) -> int:
        """Significant bits per pixel."""
        ...

    @property
    def shutter_mode(self) -> ShutterMode:
        """Global, rolling or dual rolling."""
        ...

    @shutter_mode.setter
    def shutter_mode(self, value: ShutterMode) -> None: ...

    @property
    def readout_pattern(self) -> ReadoutPattern:
        """Row order of the rolling shutter."""
        ...

    @readout_pattern.setter
    def readout_pattern(self, value: ReadoutPattern) -> None: ...

    @property
    def line_time_us(self) -> float:
        """Delay between the starts of successive rows, in microseconds."""
        ...

    @line_time_us.setter
    def line_time_us(self, value: float) -> None: ...

    @property
    def trigger_delay_us(self) -> float:
        """Delay from trigger to the first row's start, in microseconds."""
        ...

    @trigger_delay_us.setter
    def trigger_delay_us(self, value: float) -> None: ...

    @property
    def trigger_mode(self) -> TriggerMode:
        """Free-run or software trigger."""
        ...

    @trigger_mode.setter
    def trigger_mode(self, value: TriggerMode) -> None: ...

    @property
    def frame_rate_hz(self) -> float:
        """Frame rate of free-running acquisition."""
        ...

    @frame_rate_hz.setter
    def frame_rate_hz(self, value: float) -> None: ...

    @property
    def timing(self) -> SensorTiming | None:
        """Sensor timing of the next frame, or None when the device cannot say."""
        ...

    @property
    def resulting_frame_rate_hz(self) -> float | None:
        """The frame rate the present settings give, or None when the device cannot say.

        The exposure can make it lower than :attr:`frame_rate_hz`.
        """
        ...

    def snap(self, timeout_s: float = 5.0) -> Frame:
        """Acquire one frame (raises :class:`CameraTimeout` after ``timeout_s``)."""
        ...

    def start_live(self, n_frames: int | None = None) -> None:
        """Start the newest-frame path."""
        ...

    def latest_frame(self, timeout_s: float = 0.0) -> Frame | None:
        """Newest frame not yet returned (waiting up to ``timeout_s``), else None."""
        ...

    def start_acquisition(self, n_frames: int | None = None, queue_size: int = 64) -> None:
        """Start the lossless path (``n_frames`` None: until :meth:`stop`)."""
        ...

    def pop_frame(self, timeout_s: float = 5.0) -> Frame:
        """Next frame of the lossless path, in order."""
        ...

    def stop(self) -> None:
        """Stop whichever streaming path runs."""
        ...

    @property
    def stream_mode(self) -> StreamMode:
        """Which path runs now."""
        ...

    def stream_stats(self) -> StreamStats:
        """Counters of the running (or the last) stream."""
        ...


def protocol_members(protocol: type) -> frozenset[str]:
    """Public names (plus ``__enter__``/``__exit__``) a class must have to follow ``protocol``."""
    names = {n for n in vars(protocol) if not n.startswith("_")}
    return frozenset(names | {"__enter__", "__exit__"})


# --------------------------------------------------------------------------------------------
# streaming helper


@dataclass(frozen=True)
class StreamStats:
    """Counters of one stream.

    ``acquired`` frames came from the device; ``delivered`` reached the consumer;
    ``dropped`` were replaced before anybody took them (newest-frame path only);
    ``pending`` wait to be taken. ``acquired == delivered + dropped + pending``.
    ``bad`` frames raised :class:`FrameError` (skipped by the newest-frame path, not counted in
    ``acquired``); ``last_bad`` is the last one's message (None when there was none).
    """

    mode: StreamMode
    running: bool
    acquired: int = 0
    delivered: int = 0
    dropped: int = 0
    pending: int = 0
    max_pending: int = 0
    queue_size: int = 0
    error: str | None = None
    bad: int = 0
    last_bad: str | None = None


GrabFunction = Callable[[float], "Frame | None"]


class FrameStreamer:
    """A background thread that pulls frames from ``grab`` into one of the two sinks.

    ``grab(poll_s)`` returns a frame, or None when none arrived within about ``poll_s``
    (so the thread can notice a stop request). ``on_exit`` runs in the thread when it ends
    (the backend stops the device there). Errors end the stream and are raised to the consumer
    by :meth:`latest` / :meth:`pop` once the frames before them are taken
    (:class:`AcquisitionOverflow` is raised at once).

    Which errors end it:

    - No *good* frame for ``stall_timeout_s`` ends it with :class:`CameraTimeout` (bad frames
      do not keep a dead device alive).
    - LIVE: a :class:`FrameError` from ``grab`` skips that frame: it is counted
      (:attr:`StreamStats.bad`, message in ``last_bad``) and logged as a warning (the first,
      then at most one per ``bad_log_interval_s`` seconds with the count since), and the
      stream goes on. ``max_bad_frames`` bad frames in a row (default 10; a good frame resets
      the count) end it with a :class:`CameraError` naming the count and the last message
      (caused by that :class:`FrameError`): one bad read among good ones is noise, a run of
      them is a device that is gone or a source that delivers nothing usable.
    - ACQUISITION: the first error of any kind, a :class:`FrameError` included, ends it (the
      recorded data must have no holes).
    - Any other exception ends either stream at once.
    """

    #: Seconds between two warnings about skipped bad frames (the first is logged at once).
    bad_log_interval_s: float = 5.0

    def __init__(
        self,
        grab: GrabFunction,
        *,
        mode: StreamMode,
        device: str,
        n_frames: int | None = None,
        queue_size: int = 64,
        stall_timeout_s: float = 5.0,
        poll_s: float = 0.05,
        on_exit: Callable[[], None] | None = None,
        max_bad_frames: int = 10,
    ) -> None:
        if mode is StreamMode.IDLE:
            raise ValueError("a stream needs mode LIVE or ACQUISITION")
        if isinstance(max_bad_frames, bool) or int(max_bad_frames) != max_bad_frames or (
                max_bad_frames < 1):
            raise ValueError(f"max_bad_frames must be a positive integer, got {max_bad_frames!r}")
        if n_frames is not None and (int(n_frames) != n_frames or n_frames < 1):
            raise ValueError(f"n_frames must be a positive integer or None, got {n_frames!r}")
        if int(queue_size) != queue_size or queue_size < 1:
            raise ValueError(f"queue_size must be a positive integer, got {queue_size!r}")
        self.mode = mode
        self._grab = grab
        self._device = device
        self._n = None if n_frames is None else int(n_frames)
        self._queue_size = 1 if mode is StreamMode.LIVE else int(queue_size)
        self._stall = float(stall_timeout_s)
        self._frame_s = 0.0  # one frame's time: the stall allows it twice more (expect_frame_s)
        self._frame_s_next = 0.0  # the new frame time, in force from the next good frame
        self._poll = float(poll_s)
        self._on_exit = on_exit
        self._max_bad = int(max_bad_frames)
        self._bad = 0  # FrameErrors, all of them
        self._bad_run = 0  # FrameErrors since the last good frame
        self._last_bad: str | None = None
        self._bad_logged_at: float | None = None  # monotonic time of the last warning
        self._bad_unlogged = 0  # bad frames since that warning
        self._cond = threading.Condition()
        self._frames: collections.deque[Frame] = collections.deque()
        self._stop_evt = threading.Event()
        self._done = False
        self._error: BaseException | None = None
        self._acquired = 0
        self._delivered = 0
        self._dropped = 0
        self._max_pending = 0
        self._thread = threading.Thread(
            target=self._run, name=f"stream-{mode.value}-{device}", daemon=True
        )

    # -- thread side ---------------------------------------------------------------------------

    def expect_frame_s(self, seconds: float) -> None:
        """One frame now takes ``seconds`` (exposure and readout, or the frame period).

        The stream ends as stalled only after the stall timeout plus two such frames: a long
        exposure the camera accepts (3 s at a 2 s timeout) is not a lost camera. A shorter
        frame time takes effect at the next good frame: the frame under way when a 6 s
        exposure became 10 ms still takes its 6 s (the stream was declared lost 2 s in).
        """
        new = max(0.0, float(seconds)) if math.isfinite(seconds) else 0.0
        self._frame_s_next = new
        self._frame_s = max(self._frame_s, new)

    @property
    def stall_s(self) -> float:
        """Seconds without a good frame after which the stream ends."""
        return self._stall + 2.0 * self._frame_s

    def start(self) -> None:
        """Start the thread."""
        self._thread.start()

    def _run(self) -> None:
        try:
            last_good = time.monotonic()
            while not self._stop_evt.is_set() and (self._n is None or self._acquired < self._n):
                try:
                    frame = self._grab(self._poll)
                except FrameError as exc:
                    self._bad_frame(exc, last_good)  # raises when the stream must end
                    continue
                if frame is None:
                    if time.monotonic() - last_good > self.stall_s:
                        raise self._stalled(None)
                    continue
                last_good = time.monotonic()
                self._frame_s = self._frame_s_next  # a frame came: the new time holds now
                with self._cond:
                    self._bad_run = 0
                self._put(frame)
        except BaseException as exc:  # stored and raised to the consumer
            with self._cond:
                self._error = exc
        finally:
            if self._on_exit is not None:
                try:
                    self._on_exit()
                except Exception as exc:
                    _log.error("%s: stopping the stream failed: %s", self._device, exc)
                    with self._cond:
                        if self._error is None:
                            self._error = exc
            with self._cond:
                self._done = True
                self._cond.notify_all()

    def _stalled(self, cause: FrameError | None) -> CameraTimeout:
        if not self._bad_run:
            return CameraTimeout(
                f"{self._device}: no frame for {self.stall_s:.3g} s while streaming")
        return CameraTimeout(
            f"{self._device}: no good frame for {self.stall_s:.3g} s while streaming: "
            f"{self._bad_run} bad frame(s) in a row, the last: {cause or self._last_bad}")

    def _bad_frame(self, exc: FrameError, last_good: float) -> None:
        """Count a bad frame; raise when the stream must end (see the class docstring)."""
        with self._cond:
            self._bad += 1
            self._bad_run += 1
            self._last_bad = str(exc)
            run = self._bad_run
        if self.mode is not StreamMode.LIVE:
            raise exc
        if run >= self._max_bad:
            raise CameraError(
                f"{self._device}: {run} bad frames in a row, the last: {exc}") from exc
        if time.monotonic() - last_good > self.stall_s:
            raise self._stalled(exc) from exc
        now = time.monotonic()
        if self._bad_logged_at is None:
            _log.warning("%s: bad frame skipped, live view goes on: %s", self._device, exc)
        elif now - self._bad_logged_at >= self.bad_log_interval_s:
            _log.warning("%s: %d bad frames skipped in the last %.3g s (%d in all), the last: "
                         "%s", self._device, self._bad_unlogged + 1, now - self._bad_logged_at,
                         self._bad, exc)
        else:
            self._bad_unlogged += 1
            return
        self._bad_logged_at = now
        self._bad_unlogged = 0

    def _put(self, frame: Frame) -> None:
        with self._cond:
            self._acquired += 1
            if self.mode is StreamMode.LIVE:
                if self._frames:
                    self._frames.clear()
                    self._dropped += 1
                self._frames.append(frame)
            else:
                if len(self._frames) >= self._queue_size:
                    self._acquired -= 1  # the frame that did not fit is not part of the data
                    raise AcquisitionOverflow(
                        f"{self._device}: acquisition queue of {self._queue_size} frames "
                        f"overflowed after {self._acquired} frames (consumer too slow); "
                        "acquisition stopped"
                    )
                self._frames.append(frame)
            self._max_pending = max(self._max_pending, len(self._frames))
            self._cond.notify_all()

    # -- consumer side -------------------------------------------------------------------------

    @property
    def running(self) -> bool:
        """Whether the thread still runs."""
        with self._cond:
            return not self._done

    def stop(self, timeout_s: float = 15.0) -> None:
        """Ask the thread to stop and wait for it.

        A KeyboardInterrupt (Ctrl-C) that lands just after a ``with self._cond`` of the
        consumer acquired the lock, before its block began, leaves the consumer's thread
        holding it for good (CPython runs the signal handler between the two; bpo-29988): the
        stream thread then waits for the lock forever and this join timed out ("streaming
        thread did not stop", seen in CI). No method here calls ``stop`` while it holds the
        lock, so a lock this thread holds now is such a leak: it is released first.
        """
        self._stop_evt.set()
        if self._thread is not threading.current_thread():
            while self._cond._is_owned():  # type: ignore[attr-defined]  # RLock: a leak, above
                self._cond.release()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                raise CameraError(f"{self._device}: streaming thread did not stop")

    def latest(self, timeout_s: float = 0.0) -> Frame | None:
        """Newest untaken frame, waiting up to ``timeout_s``; None if none came."""
        deadline = time.monotonic() + max(0.0, timeout_s)
        with self._cond:
            while True:
                if self._frames:
                    self._delivered += 1
                    return self._frames.popleft()
                if self._error is not None:
                    raise self._error
                remaining = deadline - time.monotonic()
                if self._done or remaining <= 0:
                    return None
                self._cond.wait(remaining)

    def pop(self, timeout_s: float = 5.0) -> Frame:
        """Oldest queued frame, waiting up to ``timeout_s``."""
        deadline = time.monotonic() + max(0.0, timeout_s)
        with self._cond:
            while True:
                if isinstance(self._error, AcquisitionOverflow):
                    raise self._error
                if self._frames:
                    self._delivered += 1
                    return self._frames.popleft()
                if self._error is not None:
                    raise self._error
                if self._done:
                    raise AcquisitionFinished(
                        f"{self._device}: acquisition finished after {self._acquired} frames"
                    )
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise CameraTimeout(
                        f"{self._device}: no frame within {timeout_s:.3g} s "
                        f"({self._acquired} acquired so far)"
                    )
                self._cond.wait(remaining)

    def stats(self) -> StreamStats:
        """Current counters."""
        with self._cond:
            return StreamStats(
                mode=self.mode,
                running=not self._done,
                acquired=self._acquired,
                delivered=self._delivered,
                dropped=self._dropped,
                pending=len(self._frames),
                max_pending=self._max_pending,
                queue_size=self._queue_size,
                error=None
                if self._error is None
                else f"{type(self._error).__name__}: {self._error}",
                bad=self._bad,
                last_bad=self._last_bad,
            )


# --------------------------------------------------------------------------------------------
# base class


# --------------------------------------------------------------------------------------------
# settings: one validation for every backend


def _real(value: Any, name: str, device: str) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{device}: {name} must be a real number, got {type(value).__name__}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{device}: {name} must be finite, got {value!r}")
    return v


def _in_range(v: float, rng: tuple[float, float] | None, name: str, unit: str, dev: str) -> None:
    if rng is not None and not (rng[0] <= v <= rng[1]):
        raise ValueError(f"{dev}: {name} {v:g}{unit} outside [{rng[0]:g}, {rng[1]:g}]{unit}")


def _validate_setting(cam: CameraBase, name: str, value: Any) -> Any:
    """Check ``value`` for setting ``name`` against the camera's declared capabilities."""
    dev = cam.describe()
    if name in ("exposure_us", "frame_rate_hz", "line_time_us"):
        v = _real(value, name, dev)
        if v <= 0:
            raise ValueError(f"{dev}: {name} must be > 0, got {value!r}")
        if name == "exposure_us":
            _in_range(v, cam.capabilities().exposure_range_us, "exposure", " us", dev)
        elif name == "frame_rate_hz":
            _in_range(v, cam.capabilities().frame_rate_range_hz, "frame rate", " Hz", dev)
        return v
    if name == "gain":
        v = _real(value, name, dev)
        _in_range(v, cam.capabilities().gain_range, "gain", "", dev)
        return v
    if name == "trigger_delay_us":
        v = _real(value, name, dev)
        if v < 0:
            raise ValueError(f"{dev}: trigger_delay_us must be >= 0, got {value!r}")
        return v
    if name == "binning":
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
            raise ValueError(f"{dev}: binning must be an integer >= 1, got {value!r}")
        caps = cam.capabilities()  # an unsupported feature is the backend's FeatureNotAvailable
        factors = caps.binning_factors
        if caps.supports(Feature.BINNING) and int(value) not in factors:
            raise ValueError(f"{dev}: binning {value!r} not in {factors}")
        return int(value)
    if name == "roi":
        if not isinstance(value, Roi):
            raise TypeError(f"{dev}: roi must be a Roi, got {type(value).__name__}")
        caps = cam.capabilities()
        if value.x + value.width > caps.sensor_width or value.y + value.height > caps.sensor_height:
            raise ValueError(
                f"{dev}: ROI {value} outside the {caps.sensor_width}x{caps.sensor_height} sensor"
            )
        return value
    if name == "pixel_format":
        if not isinstance(value, str):
            raise TypeError(f"{dev}: pixel format must be a string, got {type(value).__name__}")
        return value
    if name == "shutter_mode":
        return ShutterMode(value)
    if name == "readout_pattern":
        return ReadoutPattern(value)
    if name == "trigger_mode":
        return TriggerMode(value)
    raise AssertionError(f"no validation rule for {name}")  # a new setting needs a rule


#: settings that change how long one frame takes (a running stream's stall timeout follows)
_TIMING_SETTINGS = frozenset({"exposure_us", "frame_rate_hz", "line_time_us", "readout_pattern",
                              "trigger_delay_us", "roi", "binning", "shutter_mode"})


def _setting(name: str, doc: str) -> Any:
    """Public camera property: ``_get_<name>`` reads; a set validates, then ``_do_set_<name>``."""

    def fget(self: CameraBase) -> Any:
        return getattr(self, f"_get_{name}")()

    def fset(self: CameraBase, value: Any) -> None:
        getattr(self, f"_do_set_{name}")(_validate_setting(self, name, value))
        if name in _TIMING_SETTINGS:
            self._frame_time_changed()

    return property(fget, fset, doc=doc)


class CameraBase:
    """Hardware-independent part of every backend.

    Subclasses set ``backend``, implement ``_open``, ``_close``, ``_snap(timeout_s)``,
    ``_stream_begin()``, ``_stream_grab(poll_s)``, ``_stream_end()`` and
    :meth:`capabilities`, and override the feature properties they support (the defaults
    raise :class:`FeatureNotAvailable`). Device access from the streaming thread and from
    setters is serialised by ``self._lock``.
    """

    backend: str = "base"

    #: Seconds without a good frame after which a stream ends with :class:`CameraTimeout`, on
    #: top of two frame times (:meth:`expected_frame_s`: a long exposure is not a stall).
    stream_timeout_s: float = 5.0
    #: Bad frames (:class:`FrameError`) in a row after which live view ends with an error.
    stream_max_bad_frames: int = 10

    def __init__(self, camera_id: str) -> None:
        self._camera_id = camera_id
        self._lock = threading.RLock()
        self._is_open = False
        self._streamer: FrameStreamer | None = None
        self._last_stats = StreamStats(mode=StreamMode.IDLE, running=False)
        #: the sensor's size for Frame.sensor, once a backend could say it (it does not change)
        self._sensor_known: tuple[int, int] | None = None

    # -- identity and lifetime -----------------------------------------------------------------

    @property
    def camera_id(self) -> str:
        """Identifier of this device within its backend."""
        return self._camera_id

    def describe(self) -> str:
        """Short device description used in error messages."""
        return f"{self.backend} camera '{self._camera_id}'"

    def __repr__(self) -> str:
        state = "open" if self._is_open else "closed"
        return f"<{type(self).__name__} {self._camera_id!r} {state}>"

    @property
    def is_open(self) -> bool:
        """Whether the device is open."""
        return self._is_open

    def open(self) -> None:
        """Open the device (idempotent)."""
        if self._is_open:
            return
        with self._lock:
            self._open()
            self._is_open = True

    def close(self) -> None:
        """Stop streaming and release the device (idempotent)."""
        if not self._is_open:
            return
        try:
            self.stop()
        finally:
            with self._lock:
                try:
                    self._close()
                finally:
                    self._is_open = False

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def _require_open(self) -> None:
        if not self._is_open:
            raise CameraError(f"{self.describe()} is not open")

    def _require_idle(self, what: str) -> None:
        if self._streamer is not None and self._streamer.running:
            raise CameraError(
                f"{self.describe()}: cannot {what} while the {self._streamer.mode.value} "
                "stream runs; call stop() first"
            )

    def _unavailable(self, feature: Feature | str, detail: str = "") -> FeatureNotAvailable:
        return FeatureNotAvailable(feature, self.describe(), detail)

    # -- backend hooks -------------------------------------------------------------------------

    def _open(self) -> None:
        raise NotImplementedError  # abstract: every backend implements it

    def _close(self) -> None:
        raise NotImplementedError  # abstract: every backend implements it

    def _snap(self, timeout_s: float) -> Frame:
        raise NotImplementedError  # abstract: every backend implements it

    def _stream_begin(self) -> None:
        """Prepare the device for streaming (caller's thread; errors raise at start)."""

    def _stream_grab(self, poll_s: float) -> Frame | None:
        raise NotImplementedError  # abstract: every backend implements it

    def _stream_end(self) -> None:
        """Undo :meth:`_stream_begin` (runs in the streaming thread when it ends)."""

    def capabilities(self) -> Capabilities:
        """Features, formats, ranges."""
        raise NotImplementedError  # abstract: every backend implements it

    def _sensor_shape(self) -> tuple[int, int] | None:
        """(rows, columns) of the whole sensor in unbinned pixels, for :attr:`Frame.sensor`.

        Asked for frames until it gives a size, which is then kept (a sensor does not change
        size); a backend overrides it where :meth:`capabilities` cannot say reliably (None).
        """
        caps = self.capabilities()
        return int(caps.sensor_height), int(caps.sensor_width)

    # -- features ------------------------------------------------------------------------------
    # Every public setter validates once here, for all backends (type, finite, sign, and the
    # ranges and choices that ``capabilities()`` declares), then calls the backend's
    # ``_do_set_<name>``; the getter calls ``_get_<name>``. The defaults say "not available".

    exposure_us = _setting("exposure_us", "Exposure time in microseconds.")
    gain = _setting("gain", "Gain (device units).")
    roi = _setting("roi", "Region of interest in unbinned sensor pixels.")
    binning = _setting("binning", "Symmetric binning factor (1 where the device cannot bin).")
    pixel_format = _setting("pixel_format", "Pixel format name.")
    shutter_mode = _setting("shutter_mode", "Global, rolling or dual rolling.")
    readout_pattern = _setting("readout_pattern", "Row order of the rolling shutter.")
    line_time_us = _setting("line_time_us", "Row-to-row delay in microseconds.")
    trigger_delay_us = _setting(
        "trigger_delay_us", "Delay from trigger to first row start, in microseconds."
    )
    trigger_mode = _setting("trigger_mode", "Free-run unless the backend has a software trigger.")
    frame_rate_hz = _setting("frame_rate_hz", "Free-run frame rate in hertz.")

    def _get_exposure_us(self) -> float:
        raise self._unavailable(Feature.EXPOSURE)

    def _do_set_exposure_us(self, value: float) -> None:
        raise self._unavailable(Feature.EXPOSURE)

    def _get_gain(self) -> float:
        raise self._unavailable(Feature.GAIN)

    def _do_set_gain(self, value: float) -> None:
        raise self._unavailable(Feature.GAIN)

    def _black_level(self) -> float | None:
        """The code a pixel reads with no light, for :attr:`Frame.black_level` (None: unknown).

        A backend overrides it only where the value is known in the frame's codes (GenICam's
        ``BlackLevel`` is in device units, not necessarily codes: not used).
        """
        return None

    def _get_roi(self) -> Roi:
        raise self._unavailable(Feature.ROI)

    def _do_set_roi(self, value: Roi) -> None:
        raise self._unavailable(Feature.ROI)

    def _get_binning(self) -> int:
        return 1

    def _do_set_binning(self, value: int) -> None:
        if value != 1:
            raise self._unavailable(Feature.BINNING)

    def _get_pixel_format(self) -> str:
        raise self._unavailable(Feature.PIXEL_FORMAT)

    def _do_set_pixel_format(self, value: str) -> None:
        raise self._unavailable(Feature.PIXEL_FORMAT)

    @property
    def bit_depth(self) -> int:
        """Significant bits per pixel."""
        return bit_depth_of(self.pixel_format)

    def _get_shutter_mode(self) -> ShutterMode:
        raise self._unavailable(Feature.SHUTTER_MODE)

    def _do_set_shutter_mode(self, value: ShutterMode) -> None:
        raise self._unavailable(Feature.SHUTTER_MODE)

    def _get_readout_pattern(self) -> ReadoutPattern:
        raise self._unavailable(Feature.READOUT_PATTERN)

    def _do_set_readout_pattern(self, value: ReadoutPattern) -> None:
        raise self._unavailable(Feature.READOUT_PATTERN)

    def _get_line_time_us(self) -> float:
        raise self._unavailable(Feature.LINE_TIME)

    def _do_set_line_time_us(self, value: float) -> None:
        raise self._unavailable(Feature.LINE_TIME)

    def _get_trigger_delay_us(self) -> float:
        raise self._unavailable(Feature.TRIGGER_DELAY)

    def _do_set_trigger_delay_us(self, value: float) -> None:
        raise self._unavailable(Feature.TRIGGER_DELAY)

    def _get_trigger_mode(self) -> TriggerMode:
        return TriggerMode.FREE_RUN

    def _do_set_trigger_mode(self, value: TriggerMode) -> None:
        if value is not TriggerMode.FREE_RUN:
            raise self._unavailable(Feature.TRIGGER_SOFTWARE)

    def _get_frame_rate_hz(self) -> float:
        raise self._unavailable(Feature.FRAME_RATE)

    def _do_set_frame_rate_hz(self, value: float) -> None:
        raise self._unavailable(Feature.FRAME_RATE)

    @property
    def timing(self) -> SensorTiming | None:
        """Sensor timing when line time, pattern and exposure are all known, else None."""
        try:
            return SensorTiming.from_exposure_us(
                rows=self.capabilities().sensor_height,
                line_time_us=self.line_time_us,
                exposure_us=self.exposure_us,
                pattern=self.readout_pattern,
                trigger_delay_us=self.trigger_delay_us,
            )
        except (FeatureNotAvailable, ValueError):
            return None

    @property
    def resulting_frame_rate_hz(self) -> float | None:
        """The rate frames come at with the present settings, or None when unknown.

        The set frame rate, or less where one frame (exposure and readout, :attr:`timing`)
        takes longer than its period; None when the device has no frame rate or no timing.
        """
        rate = self._optional(lambda: self.frame_rate_hz)
        t = self.timing
        if rate is None or t is None or not t.frame_time_us > 0:
            return None
        return min(float(rate), 1e6 / t.frame_time_us)

    def expected_frame_s(self) -> float:
        """Seconds one frame takes with the present settings (0 when the device cannot say).

        The period of :attr:`resulting_frame_rate_hz`, else the exposure.

        Stalls and checks wait this long on top of their own timeouts.
        """
        try:
            rate = self.resulting_frame_rate_hz
            if rate is not None and rate > 0:
                return 1.0 / float(rate)
            exposure = self._optional(lambda: self.exposure_us)
        except Exception as exc:  # a device error: no allowance, as before
            _log.debug("%s: frame time unknown: %s", self.describe(), exc)
            return 0.0
        return float(exposure) * 1e-6 if exposure is not None and exposure > 0 else 0.0

    def _frame_time_changed(self) -> None:
        s = self._streamer
        if s is not None:
            s.expect_frame_s(self.expected_frame_s())

    def _optional(self, getter: Callable[[], Any]) -> Any:
        try:
            return getter()
        except FeatureNotAvailable:
            return None

    # -- acquisition ---------------------------------------------------------------------------

    def snap(self, timeout_s: float = 5.0) -> Frame:
        """Acquire one frame (raises :class:`CameraTimeout` after ``timeout_s``)."""
        self._require_open()
        self._require_idle("snap")
        if not (timeout_s > 0 and math.isfinite(timeout_s)):
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        return self._snap(float(timeout_s))

    @property
    def stream_mode(self) -> StreamMode:
        """Which path was started (kept after it ends by itself, until :meth:`stop`)."""
        s = self._streamer
        return s.mode if s is not None else StreamMode.IDLE

    def _start_stream(self, mode: StreamMode, n_frames: int | None, queue_size: int) -> None:
        self._require_open()
        s = self._streamer
        if s is not None:
            if s.running:
                other = s.mode.value
                raise CameraError(
                    f"{self.describe()}: cannot start the {mode.value} stream while the "
                    f"{other} stream runs; call stop() first"
                )
            self._retire_streamer()
        streamer = FrameStreamer(
            self._stream_grab,
            mode=mode,
            device=self.describe(),
            n_frames=n_frames,
            queue_size=queue_size,
            stall_timeout_s=self.stream_timeout_s,
            on_exit=self._stream_end_locked,
            max_bad_frames=self.stream_max_bad_frames,
        )
        streamer.expect_frame_s(self.expected_frame_s())
        with self._lock:
            self._stream_begin()
        self._streamer = streamer
        streamer.start()

    def _stream_end_locked(self) -> None:
        with self._lock:
            self._stream_end()

    def _retire_streamer(self) -> None:
        s = self._streamer
        if s is None:
            return
        try:
            s.stop()
        finally:
            self._last_stats = s.stats()
            self._streamer = None

    def start_live(self, n_frames: int | None = None) -> None:
        """Start the newest-frame path (until :meth:`stop`, or ``n_frames`` frames)."""
        self._start_stream(StreamMode.LIVE, n_frames, 1)

    def latest_frame(self, timeout_s: float = 0.0) -> Frame | None:
        """Newest frame not yet returned, waiting up to ``timeout_s``; None if none came."""
        s = self._streamer
        if s is None or s.mode is not StreamMode.LIVE:
            raise CameraError(f"{self.describe()}: no live stream (call start_live())")
        return s.latest(timeout_s)

    def start_acquisition(self, n_frames: int | None = None, queue_size: int = 64) -> None:
        """Start the lossless path: every frame is queued (at most ``queue_size``)."""
        self._start_stream(StreamMode.ACQUISITION, n_frames, queue_size)

    def pop_frame(self, timeout_s: float = 5.0) -> Frame:
        """Next frame of the lossless path, in order.

        Raises :class:`AcquisitionOverflow` if the queue overflowed,
        :class:`AcquisitionFinished` when a finite acquisition is exhausted,
        :class:`CameraTimeout` when nothing came within ``timeout_s``.
        """
        s = self._streamer
        if s is None or s.mode is not StreamMode.ACQUISITION:
            raise CameraError(f"{self.describe()}: no acquisition (call start_acquisition())")
        return s.pop(timeout_s)

    def stop(self) -> None:
        """Stop whichever streaming path runs (no-op when idle)."""
        self._retire_streamer()

    def stream_stats(self) -> StreamStats:
        """Counters of the running stream, or of the last one."""
        s = self._streamer
        return s.stats() if s is not None else self._last_stats

    # -- frames --------------------------------------------------------------------------------

    def _make_frame(
        self,
        pixels: np.ndarray,
        frame_id: int,
        *,
        timestamp: float | None = None,
        pixel_format: str | None = None,
        extra: Mapping[str, Any] | None = None,
    ) -> Frame:
        """Wrap pixels with the current settings as metadata.

        ``pixel_format`` overrides the setting (for the format the device really delivered).
        """
        roi = self._optional(lambda: self.roi)
        if roi is None:
            roi = Roi(0, 0, int(pixels.shape[1]), int(pixels.shape[0]))
        pf = pixel_format or self._optional(lambda: self.pixel_format)
        if pf is None:
            pf = "Mono16" if pixels.dtype == np.uint16 else "Mono8"
        sensor = self._sensor_known
        if sensor is None:
            sensor = self._sensor_known = self._optional(self._sensor_shape)
        if sensor is not None and (
            roi.y + roi.height > sensor[0] or roi.x + roi.width > sensor[1]
        ):  # a device whose size nodes disagree with its ROI: say "unknown", not a wrong size
            _log.warning("%s: ROI %s outside the reported %dx%d sensor; frame sensor size "
                         "unknown", self.describe(), roi, sensor[0], sensor[1])
            sensor = None
        return Frame(
            pixels=pixels,
            frame_id=frame_id,
            timestamp=time.time() if timestamp is None else timestamp,
            exposure_us=self._optional(lambda: self.exposure_us),
            gain=self._optional(lambda: self.gain),
            roi=roi,
            binning=self.binning,
            pixel_format=pf,
            bit_depth=bit_depth_of(pf),
            timing=self.timing,
            backend=self.backend,
            camera_id=self.camera_id,
            extra=dict(extra or {}),
            sensor=sensor,
            black_level=self._optional(self._black_level),
        )
