"""Simulated camera: a scene rendered through an injected forward model, plus sensor physics.

The renderer is injected (``drivers`` never imports ``recon``); its contract is::

    render(frames, shutter) -> image
        frames:  (K, Hs, Ws) float32   scene radiance of each time bin (or spectral band)
        shutter: (K, rows)  float32    M_k: the shutter function of the frame
        image:   (rows, cols) float    sum_k M_k[:, None] * crop(h * v_k)

The camera computes ``M`` from its :class:`~drivers.timing.SensorTiming` with
:func:`~drivers.timing.shutter_function` (bins = the scene's frame period in lines) and hands
over the scene frames that cover the exposure. Without an injected renderer it uses
:class:`CropRenderer`, the same model with a delta PSF (``crop`` takes the centre
``rows x cols`` of the scene plane, zero-padding a smaller scene), so the drivers work alone.

Radiometry: scene values are photo-electrons per pixel per millisecond *as they reach the
sensor through the renderer* (a unit-sum PSF keeps that scale). A frame collects
``render(frames, M) * bin_ms`` electrons (``bin_ms`` = one time bin in milliseconds), then:
dead pixels lose their signal, hot pixels gain dark current, shot (Poisson) noise is drawn, the
full well clips the charge, read (Gaussian) noise is added (it may go below zero: the readout
sits on the dark offset), the ROI is cut and binned (summed), and electrons become
codes: ``round(e * adu_per_electron + dark_offset_adu)`` clipped to the bit depth, where
``adu_per_electron = gain * max_code / full_well_e``.

Scenes: :class:`StillScene`, :class:`MovingScene` (frame period in lines or microseconds),
:class:`SpectralScene` (bands passed straight to the renderer), and the simulated point source:
given ``light_state`` (a state-file path written by :mod:`drivers.pointsource_sim`, or an object
with ``light_state()``), each frame reads the source's state and, when it is lit, adds a point
(a bilinear delta at ``point_position``) rendered through the same renderer. In strobe mode only
the part of each row's exposure window that overlaps the pulse
``[trigger + strobe_delay_us, + strobe_duration_us)`` collects light.

Time: the camera keeps a simulated clock in line units (``scene_time_lines``); frame n's
trigger is at that clock, which then advances by the frame period. ``pacing`` sleeps so frames
arrive at the set frame rate in real time (off, or a high ``frame_rate_hz``, for fast tests).
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from drivers.camera import (
    CameraBase,
    CameraError,
    CameraTimeout,
    Capabilities,
    Feature,
    Frame,
    Roi,
    TriggerMode,
    bit_depth_of,
)
from drivers.lightstate import LightMode, LightState, LightStateFile, LightStateSource
from drivers.timing import (
    ReadoutPattern,
    SensorTiming,
    ShutterMode,
    row_start_lines,
    shutter_function,
)

__all__ = [
    "CropRenderer",
    "MovingScene",
    "Renderer",
    "Scene",
    "SimulatedCamera",
    "SpectralScene",
    "StillScene",
    "crop_center",
    "demo_pattern",
    "shutter_at",
]

Renderer = Callable[[np.ndarray, np.ndarray], np.ndarray]

_PIXEL_FORMATS = ("Mono8", "Mono12", "Mono16")
_BINNINGS = (1, 2, 4)


# --------------------------------------------------------------------------------------------
# helpers


def crop_center(img: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Centre ``shape`` of a 2D array; a smaller array is zero-padded around its centre."""
    rows, cols = shape
    out = np.zeros((rows, cols), dtype=img.dtype)
    h, w = img.shape
    # overlap of the two centred windows
    sy, sx = (h - rows) // 2, (w - cols) // 2  # source offset (negative: pad)
    y0, x0 = max(0, -sy), max(0, -sx)
    y1, x1 = min(rows, h - sy), min(cols, w - sx)
    if y1 > y0 and x1 > x0:
        out[y0:y1, x0:x1] = img[y0 + sy : y1 + sy, x0 + sx : x1 + sx]
    return out


class CropRenderer:
    """Default renderer: the forward model with a delta PSF, ``sum_k M_k . crop(v_k)``."""

    def __init__(self, cols: int) -> None:
        self.cols = int(cols)

    def __call__(self, frames: np.ndarray, shutter: np.ndarray) -> np.ndarray:
        """Render ``frames`` (K, Hs, Ws) with ``shutter`` (K, rows) to (rows, cols)."""
        rows = shutter.shape[1]
        out = np.zeros((rows, self.cols), dtype=np.float32)
        for k in range(frames.shape[0]):
            out += shutter[k][:, None] * crop_center(frames[k], (rows, self.cols))
        return out


def demo_pattern(height: int, width: int) -> np.ndarray:
    """A deterministic still scene (float32, electrons/ms): soft blobs on a faint ramp."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    img = 20.0 + 30.0 * x / max(1, width - 1)
    for cy, cx, s, a in (
        (0.3, 0.3, 0.08, 400.0),
        (0.6, 0.7, 0.05, 800.0),
        (0.75, 0.25, 0.1, 250.0),
    ):
        r2 = ((y - cy * height) / (s * height)) ** 2 + ((x - cx * width) / (s * width)) ** 2
        img = img + a * np.exp(-0.5 * r2)
    return np.asarray(img, dtype=np.float32)


def shutter_at(timing: SensorTiming, bin_lines: int, start_lines: int) -> tuple[int, np.ndarray]:
    """Shutter function of a frame whose trigger is at absolute time ``start_lines``.

    Time bins are ``[j * bin_lines, (j + 1) * bin_lines)`` on the absolute clock (the scene's
    frame grid). Returns ``(j0, M)``: the first bin index and M (K, rows) float64. When the
    row starts fall on the grid this is exactly :func:`~drivers.timing.shutter_function`.
    """
    if int(bin_lines) != bin_lines or bin_lines < 1:
        raise ValueError(f"bin_lines must be an integer >= 1, got {bin_lines!r}")
    start = int(start_lines)
    if start % bin_lines == 0:
        return start // bin_lines, shutter_function(timing, int(bin_lines))
    starts = row_start_lines(timing.rows, timing.pattern) + start
    ends = starts + timing.exposure_lines
    j0 = int(starts.min()) // bin_lines
    j1 = -(-int(ends.max()) // bin_lines)
    lo = (j0 + np.arange(j1 - j0, dtype=np.int64))[:, None] * bin_lines
    overlap = np.clip(
        np.minimum(lo + bin_lines, ends[None, :]) - np.maximum(lo, starts[None, :]), 0, None
    )
    return j0, overlap.astype(np.float64) / float(bin_lines)


# --------------------------------------------------------------------------------------------
# scenes


@dataclass(frozen=True)
class RenderInputs:
    """What one frame hands the renderer, plus how to turn its output into electrons."""

    frames: np.ndarray  # (K, Hs, Ws) float32
    shutter: np.ndarray  # (K, rows) float32
    bin_ms: float  # duration of one time bin in milliseconds
    info: dict[str, Any]


class Scene(Protocol):
    """A source of scene radiance for the simulated camera."""

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) of the scene plane."""
        ...

    @property
    def n_bands(self) -> int:
        """Number of spectral bands (1 unless spectral)."""
        ...

    def render_inputs(self, timing: SensorTiming, start_lines: int) -> RenderInputs:
        """Frames and shutter function for a frame triggered at ``start_lines``."""
        ...


def _as_stack(a: np.ndarray, ndim: int, name: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float32)
    if arr.ndim != ndim:
        raise ValueError(f"{name} must be {ndim}-D, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} has non-finite values")
    arr = arr.copy()
    arr.flags.writeable = False
    return arr


def _whole_exposure(timing: SensorTiming) -> tuple[np.ndarray, float]:
    """One bin covering the frame: M = E / frame_lines per row, bin = frame_lines lines."""
    m = shutter_function(timing, timing.frame_lines).astype(np.float32)
    return m, timing.frame_lines * timing.line_time_us / 1000.0


class StillScene:
    """A static image (H, W): time does not matter, one bin covers the exposure."""

    def __init__(self, image: np.ndarray) -> None:
        self.image = _as_stack(image, 2, "StillScene image")

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width)."""
        return (int(self.image.shape[0]), int(self.image.shape[1]))

    @property
    def n_bands(self) -> int:
        """1."""
        return 1

    def render_inputs(self, timing: SensorTiming, start_lines: int) -> RenderInputs:
        """The image and the whole-exposure shutter."""
        m, bin_ms = _whole_exposure(timing)
        return RenderInputs(self.image[None], m, bin_ms, {"scene": "still"})


class MovingScene:
    """A sequence (N, H, W); frame j shows during ``[j P, (j + 1) P)`` lines of scene time.

    Give the period in lines (exact) or microseconds (rounded to whole lines of the camera's
    current line time). ``loop``: after the last frame start again; else hold the last.
    """

    def __init__(
        self,
        frames: np.ndarray,
        *,
        frame_period_lines: int | None = None,
        frame_period_us: float | None = None,
        loop: bool = True,
    ) -> None:
        self.frames = _as_stack(frames, 3, "MovingScene frames")
        if (frame_period_lines is None) == (frame_period_us is None):
            raise ValueError("give exactly one of frame_period_lines or frame_period_us")
        if frame_period_lines is not None and (
            int(frame_period_lines) != frame_period_lines or frame_period_lines < 1
        ):
            raise ValueError(f"frame_period_lines must be an integer >= 1: {frame_period_lines!r}")
        if frame_period_us is not None and not (
            math.isfinite(frame_period_us) and frame_period_us > 0
        ):
            raise ValueError(f"frame_period_us must be > 0, got {frame_period_us!r}")
        self.frame_period_lines = None if frame_period_lines is None else int(frame_period_lines)
        self.frame_period_us = frame_period_us
        self.loop = bool(loop)

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width)."""
        return (int(self.frames.shape[1]), int(self.frames.shape[2]))

    @property
    def n_bands(self) -> int:
        """1."""
        return 1

    def period_lines(self, line_time_us: float) -> int:
        """Frame period in lines for a line time."""
        if self.frame_period_lines is not None:
            return self.frame_period_lines
        assert self.frame_period_us is not None  # checked in __init__
        return max(1, round(self.frame_period_us / line_time_us))

    def render_inputs(self, timing: SensorTiming, start_lines: int) -> RenderInputs:
        """The scene frames overlapping the exposure and the shutter on their time grid."""
        p = self.period_lines(timing.line_time_us)
        j0, m = shutter_at(timing, p, start_lines)
        idx = j0 + np.arange(m.shape[0])
        n = self.frames.shape[0]
        idx = idx % n if self.loop else np.clip(idx, 0, n - 1)
        return RenderInputs(
            self.frames[idx],
            m.astype(np.float32),
            p * timing.line_time_us / 1000.0,
            {"scene": "moving", "scene_frame_period_lines": p, "scene_first_frame": int(j0)},
        )


class SpectralScene:
    """A spectral cube (B, H, W), handed to the renderer as is (it applies the filters)."""

    def __init__(self, cube: np.ndarray) -> None:
        self.cube = _as_stack(cube, 3, "SpectralScene cube")

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width)."""
        return (int(self.cube.shape[1]), int(self.cube.shape[2]))

    @property
    def n_bands(self) -> int:
        """Number of bands."""
        return int(self.cube.shape[0])

    def render_inputs(self, timing: SensorTiming, start_lines: int) -> RenderInputs:
        """The cube; every band integrates over the whole exposure."""
        m, bin_ms = _whole_exposure(timing)
        return RenderInputs(
            self.cube, np.repeat(m, self.n_bands, axis=0), bin_ms, {"scene": "spectral"}
        )


# --------------------------------------------------------------------------------------------
# the camera


class SimulatedCamera(CameraBase):
    """A camera with no hardware: renders a scene, adds sensor physics, paces frames.

    Every feature of the :class:`~drivers.camera.Camera` protocol is available. Sensor size is
    ``width x height``; defaults are small so tests and demos are fast.
    """

    backend = "sim"
    stream_timeout_s = 2.0

    def __init__(
        self,
        width: int = 128,
        height: int = 96,
        *,
        renderer: Renderer | None = None,
        scene: Scene | np.ndarray | None = None,
        scene_shape: tuple[int, int] | None = None,
        light_state: str | os.PathLike[str] | LightStateSource | LightState | None = None,
        point_position: tuple[float, float] | None = None,
        point_flux_e_per_ms: float = 5000.0,
        exposure_us: float = 10_000.0,
        gain: float = 1.0,
        pixel_format: str = "Mono12",
        line_time_us: float = 10.0,
        readout_pattern: ReadoutPattern | str = ReadoutPattern.OUTSIDE_IN,
        trigger_delay_us: float = 0.0,
        frame_rate_hz: float = 30.0,
        pacing: bool = True,
        noise: bool = True,
        full_well_e: float = 30_000.0,
        read_noise_e: float = 2.0,
        dark_offset_adu: float = 100.0,
        dead_pixel_fraction: float = 0.0,
        hot_pixel_fraction: float = 0.0,
        hot_pixel_e_per_ms: float = 1000.0,
        seed: int = 0,
        camera_id: str = "sim0",
    ) -> None:
        super().__init__(camera_id)
        if int(width) != width or int(height) != height or width < 1 or height < 2:
            raise ValueError(f"sensor size (rows x columns) must be whole numbers of at least "
                             f"2x1, got {height}x{width}")
        self._width, self._height = int(width), int(height)
        self._renderer: Renderer = renderer if renderer is not None else CropRenderer(width)
        self._scene: Scene | None = StillScene(scene) if isinstance(scene, np.ndarray) else scene
        if scene_shape is not None:
            self._scene_shape = (int(scene_shape[0]), int(scene_shape[1]))
        elif self._scene is not None:
            self._scene_shape = self._scene.shape
        else:
            self._scene_shape = (self._height, self._width)
        self._light = _light_source_of(light_state)
        self._point_position = point_position
        self.point_flux_e_per_ms = float(point_flux_e_per_ms)
        for name, v in (
            ("full_well_e", full_well_e),
            ("read_noise_e", read_noise_e),
            ("dark_offset_adu", dark_offset_adu),
            ("hot_pixel_e_per_ms", hot_pixel_e_per_ms),
        ):
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be >= 0, got {v!r}")
        if full_well_e <= 0:
            raise ValueError("full_well_e must be > 0")
        self.full_well_e = float(full_well_e)
        self.read_noise_e = float(read_noise_e)
        self.dark_offset_adu = float(dark_offset_adu)
        self.hot_pixel_e_per_ms = float(hot_pixel_e_per_ms)
        self.noise = bool(noise)
        self.pacing = bool(pacing)
        defect_ss, noise_ss = np.random.SeedSequence(seed).spawn(2)
        defect_rng = np.random.default_rng(defect_ss)
        self._rng = np.random.default_rng(noise_ss)
        n_pix = self._width * self._height
        order = defect_rng.permutation(n_pix)
        n_dead = round(float(dead_pixel_fraction) * n_pix)
        n_hot = round(float(hot_pixel_fraction) * n_pix)
        if not (0 <= n_dead + n_hot <= n_pix):
            raise ValueError("dead + hot pixel fractions must be within [0, 1]")
        dead = np.zeros(n_pix, dtype=bool)
        dead[order[:n_dead]] = True
        hot = np.zeros(n_pix, dtype=bool)
        hot[order[n_dead : n_dead + n_hot]] = True
        self._dead: np.ndarray = dead.reshape(self._height, self._width)
        self._hot: np.ndarray = hot.reshape(self._height, self._width)

        self._line_time_us = _positive(line_time_us, "line_time_us")
        self._pattern = ReadoutPattern(readout_pattern)
        self._trigger_delay_us = _non_negative(trigger_delay_us, "trigger_delay_us")
        self._exposure_req_us = 0.0
        self._gain = 1.0
        self._pixel_format = "Mono12"
        self._roi = Roi(0, 0, self._width, self._height)
        self._binning = 1
        self._trigger_mode = TriggerMode.FREE_RUN
        self._frame_rate_hz = 30.0
        self.exposure_us = exposure_us
        self.gain = gain
        self.pixel_format = pixel_format
        self.frame_rate_hz = frame_rate_hz

        self._frame_id = 0
        self._clock_lines = 0
        self._next_ready = 0.0
        self._pending_ready: float | None = None
        self._unplugged = False

    # -- lifetime ------------------------------------------------------------------------------

    def _open(self) -> None:
        self._next_ready = time.monotonic()

    def _close(self) -> None:
        pass

    def capabilities(self) -> Capabilities:
        """All features; ranges of this simulated sensor."""
        return Capabilities(
            backend=self.backend,
            camera_id=self.camera_id,
            model="SimulatedCamera",
            sensor_width=self._width,
            sensor_height=self._height,
            features=frozenset(Feature),
            pixel_formats=_PIXEL_FORMATS,
            trigger_modes=(TriggerMode.FREE_RUN, TriggerMode.SOFTWARE),
            shutter_modes=tuple(ShutterMode),
            readout_patterns=tuple(ReadoutPattern),
            exposure_range_us=(self._line_time_us, 10_000_000.0),
            gain_range=(1.0, 64.0),
            frame_rate_range_hz=(0.1, 100_000.0),
            binning_factors=_BINNINGS,
        )

    # -- fault injection -----------------------------------------------------------------------

    def simulate_unplug(self) -> None:
        """From now on no frame arrives: snaps and streams end with :class:`CameraTimeout`."""
        self._unplugged = True

    def simulate_replug(self) -> None:
        """Undo :meth:`simulate_unplug`."""
        self._unplugged = False

    @property
    def unplugged(self) -> bool:
        """Whether :meth:`simulate_unplug` is in effect."""
        return self._unplugged

    # -- scene ---------------------------------------------------------------------------------

    @property
    def scene(self) -> Scene | None:
        """The scene (None: dark apart from the point source)."""
        return self._scene

    @scene.setter
    def scene(self, value: Scene | np.ndarray | None) -> None:
        with self._lock:
            self._scene = StillScene(value) if isinstance(value, np.ndarray) else value
            if self._scene is not None:
                self._scene_shape = self._scene.shape

    @property
    def scene_time_lines(self) -> int:
        """Simulated clock: the trigger time of the next frame, in line units."""
        return self._clock_lines

    @scene_time_lines.setter
    def scene_time_lines(self, value: int) -> None:
        if int(value) != value or value < 0:
            raise ValueError(f"scene_time_lines must be an integer >= 0, got {value!r}")
        with self._lock:
            self._clock_lines = int(value)

    @property
    def point_position(self) -> tuple[float, float]:
        """(row, col) of the simulated point source in scene pixels.

        Default: the on-axis pixel (H // 2, W // 2), the point that the forward model's crop
        convention maps onto the PSF as measured (a whole pixel, so no half-pixel blur).
        """
        if self._point_position is None:
            return (float(self._scene_shape[0] // 2), float(self._scene_shape[1] // 2))
        return self._point_position

    @point_position.setter
    def point_position(self, value: tuple[float, float]) -> None:
        r, c = float(value[0]), float(value[1])
        h, w = self._scene_shape
        if not (0 <= r <= h - 1 and 0 <= c <= w - 1):
            raise ValueError(f"point position {value} outside the scene plane {h}x{w}")
        self._point_position = (r, c)

    @property
    def defect_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """(dead, hot) boolean maps of the full sensor."""
        return self._dead.copy(), self._hot.copy()

    @property
    def adu_per_electron(self) -> float:
        """Conversion gain in codes per electron at the current gain and bit depth."""
        return self._gain * ((1 << self.bit_depth) - 1) / self.full_well_e

    # -- features ------------------------------------------------------------------------------

    def _check_settable(self, what: str) -> None:
        self._require_idle(f"change {what}")

    def _get_exposure_us(self) -> float:
        """Exposure in microseconds (whole line times)."""
        return self._timing().exposure_us

    def _do_set_exposure_us(self, value: float) -> None:
        with self._lock:  # validated against capabilities() by the base class
            self._exposure_req_us = value

    def _black_level(self) -> float | None:
        """The dark offset in codes (what an unlit pixel reads on average, before clipping)."""
        return float(min(self.dark_offset_adu, (1 << self.bit_depth) - 1))

    def _get_gain(self) -> float:
        """Linear gain factor (1 maps the full well to the top code)."""
        return self._gain

    def _do_set_gain(self, value: float) -> None:
        with self._lock:
            self._gain = value

    def _get_roi(self) -> Roi:
        """ROI in unbinned sensor pixels."""
        return self._roi

    def _do_set_roi(self, value: Roi) -> None:
        self._check_settable("the ROI")
        if value.width % self._binning or value.height % self._binning:
            raise ValueError(f"ROI {value} not divisible by binning {self._binning}")
        with self._lock:
            self._roi = value

    def _get_binning(self) -> int:
        """Symmetric binning (sums electrons)."""
        return self._binning

    def _do_set_binning(self, value: int) -> None:
        self._check_settable("binning")
        if value not in _BINNINGS:
            raise ValueError(f"binning {value!r} not in {_BINNINGS}")
        if self._roi.width % value or self._roi.height % value:
            raise ValueError(f"ROI {self._roi} not divisible by binning {value}")
        with self._lock:
            self._binning = int(value)

    def _get_pixel_format(self) -> str:
        """Mono8, Mono12 or Mono16."""
        return self._pixel_format

    def _do_set_pixel_format(self, value: str) -> None:
        self._check_settable("the pixel format")
        if value not in _PIXEL_FORMATS:
            raise ValueError(f"pixel format {value!r} not in {_PIXEL_FORMATS}")
        with self._lock:
            self._pixel_format = value

    @property
    def bit_depth(self) -> int:
        """Bits of the pixel format."""
        return bit_depth_of(self._pixel_format)

    def _get_shutter_mode(self) -> ShutterMode:
        """Implied by the readout pattern."""
        return self._timing().mode

    def _do_set_shutter_mode(self, value: ShutterMode) -> None:
        mode = ShutterMode(value)
        if mode is ShutterMode.GLOBAL:
            self.readout_pattern = ReadoutPattern.GLOBAL
        elif mode is ShutterMode.ROLLING:
            self.readout_pattern = ReadoutPattern.TOP_DOWN
        elif self._pattern not in (ReadoutPattern.OUTSIDE_IN, ReadoutPattern.CENTRE_OUT):
            self.readout_pattern = ReadoutPattern.OUTSIDE_IN

    def _get_readout_pattern(self) -> ReadoutPattern:
        """Row order."""
        return self._pattern

    def _do_set_readout_pattern(self, value: ReadoutPattern) -> None:
        p = ReadoutPattern(value)
        with self._lock:
            self._pattern = p

    def _get_line_time_us(self) -> float:
        """Row-to-row delay."""
        return self._line_time_us

    def _do_set_line_time_us(self, value: float) -> None:
        with self._lock:
            self._line_time_us = value
            self._exposure_req_us = max(self._exposure_req_us, value)

    def _get_trigger_delay_us(self) -> float:
        """Delay from trigger to the first row's start."""
        return self._trigger_delay_us

    def _do_set_trigger_delay_us(self, value: float) -> None:
        with self._lock:
            self._trigger_delay_us = value

    def _get_trigger_mode(self) -> TriggerMode:
        """Free-run or software (the simulation behaves the same: each frame is triggered)."""
        return self._trigger_mode

    def _do_set_trigger_mode(self, value: TriggerMode) -> None:
        with self._lock:
            self._trigger_mode = value

    def _get_frame_rate_hz(self) -> float:
        """Frame rate when paced (the exposure can make it slower)."""
        return self._frame_rate_hz

    def _do_set_frame_rate_hz(self, value: float) -> None:
        with self._lock:
            self._frame_rate_hz = value

    def _timing(self) -> SensorTiming:
        return SensorTiming.from_exposure_us(
            self._height,
            self._line_time_us,
            self._exposure_req_us,
            self._pattern,
            self._trigger_delay_us,
        )

    @property
    def timing(self) -> SensorTiming:
        """Timing of the full sensor for the next frame."""
        return self._timing()

    def frame_period_us(self) -> float:
        """Time between frame starts: 1 / frame rate, but never shorter than a frame."""
        return max(1e6 / self._frame_rate_hz, self._timing().frame_time_us)

    # -- acquisition ---------------------------------------------------------------------------

    def _snap(self, timeout_s: float) -> Frame:
        if self._unplugged:
            time.sleep(timeout_s)
            raise CameraTimeout(f"{self.describe()}: no frame within {timeout_s:.3g} s")
        if self.pacing:
            ready = max(self._next_ready, time.monotonic() + self._timing().frame_time_us * 1e-6)
            wait = ready - time.monotonic()
            if wait > timeout_s:
                time.sleep(timeout_s)
                raise CameraTimeout(f"{self.describe()}: no frame within {timeout_s:.3g} s")
            if wait > 0:
                time.sleep(wait)
            self._next_ready = ready + self.frame_period_us() * 1e-6
        with self._lock:
            return self._capture()

    def _stream_begin(self) -> None:
        self._pending_ready = None

    def _stream_grab(self, poll_s: float) -> Frame | None:
        if self._unplugged:
            time.sleep(poll_s)
            return None
        if self.pacing:
            if self._pending_ready is None:
                self._pending_ready = max(self._next_ready, time.monotonic())
            wait = self._pending_ready - time.monotonic()
            if wait > poll_s:
                time.sleep(poll_s)
                return None
            if wait > 0:
                time.sleep(wait)
            self._next_ready = self._pending_ready + self.frame_period_us() * 1e-6
            self._pending_ready = None
        with self._lock:
            return self._capture()

    def render_electrons(
        self, timing: SensorTiming | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Noise-free signal of the next frame on the full sensor, in electrons (float64).

        Does not advance the clock. Returns the image and metadata about what was rendered.
        """
        t = self._timing() if timing is None else timing
        start = self._clock_lines + round(self._trigger_delay_us / self._line_time_us)
        signal = np.zeros((self._height, self._width), dtype=np.float64)
        info: dict[str, Any] = {"scene_time_lines": self._clock_lines}
        if self._scene is not None:
            inputs = self._scene.render_inputs(t, start)
            signal += self._render(inputs.frames, inputs.shutter) * inputs.bin_ms
            info.update(inputs.info)
        if self._light is not None:
            state = self._light.light_state()
            info["light"] = {
                "mode": state.mode.value,
                "intensity": state.intensity,
                "counter": state.counter,
                "available": state.available,
            }
            if state.lit:
                weights = self._light_weights_ms(t, state)
                if np.any(weights > 0):
                    point = self._point_frames()
                    k = point.shape[0]
                    shutter = np.repeat(weights[None, :], k, axis=0).astype(np.float32)
                    scale = self.point_flux_e_per_ms * state.intensity
                    signal += self._render(point, shutter) * scale
        return signal, info

    def _render(self, frames: np.ndarray, shutter: np.ndarray) -> np.ndarray:
        out = np.asarray(self._renderer(frames, shutter), dtype=np.float64)
        if out.shape != (self._height, self._width):
            raise CameraError(
                f"{self.describe()}: renderer returned shape {out.shape}, "
                f"expected {(self._height, self._width)}"
            )
        return out

    def _light_weights_ms(self, t: SensorTiming, state: LightState) -> np.ndarray:
        """Milliseconds of each row's exposure that see the light."""
        if state.mode is LightMode.ON:
            return np.full(t.rows, t.exposure_us / 1000.0)
        starts = t.row_start_us()
        ends = starts + t.exposure_us
        p0 = state.strobe_delay_us
        p1 = p0 + state.strobe_duration_us
        overlap = np.clip(np.minimum(ends, p1) - np.maximum(starts, p0), 0.0, None)
        return np.asarray(overlap, dtype=np.float64) / 1000.0

    def _point_frames(self) -> np.ndarray:
        h, w = self._scene_shape
        img = np.zeros((h, w), dtype=np.float32)
        r, c = self.point_position
        r0, c0 = math.floor(r), math.floor(c)
        fr, fc = r - r0, c - c0
        for dr, wr in ((0, 1.0 - fr), (1, fr)):
            for dc, wc in ((0, 1.0 - fc), (1, fc)):
                rr, cc = r0 + dr, c0 + dc
                if wr * wc > 0 and 0 <= rr < h and 0 <= cc < w:
                    img[rr, cc] += wr * wc
        bands = self._scene.n_bands if self._scene is not None else 1
        return np.repeat(img[None], bands, axis=0)

    def _capture(self) -> Frame:
        t = self._timing()
        signal, info = self.render_electrons(t)
        exposure_ms = t.exposure_us / 1000.0
        signal[self._dead] = 0.0
        signal[self._hot] += self.hot_pixel_e_per_ms * exposure_ms
        read = None
        if self.noise:
            e = self._rng.poisson(np.clip(signal, 0.0, 1e12)).astype(np.float64)
            if self.read_noise_e > 0:
                read = self._rng.normal(0.0, self.read_noise_e, size=e.shape)
        else:
            e = signal
        # the well holds 0..full_well electrons; read noise is added by the readout chain,
        # on top of the dark offset, so it reaches codes below the offset too (clipping it
        # with the charge kept only its positive half: a biased dark level, 0.58x its std)
        e = np.clip(e, 0.0, self.full_well_e)
        if read is not None:
            e = e + read
        roi, b = self._roi, self._binning
        e = e[roi.y : roi.y + roi.height, roi.x : roi.x + roi.width]
        if b > 1:
            e = e.reshape(roi.height // b, b, roi.width // b, b).sum(axis=(1, 3))
        max_code = (1 << self.bit_depth) - 1
        adu = np.rint(e * self.adu_per_electron + self.dark_offset_adu)
        dtype = np.uint8 if self.bit_depth <= 8 else np.uint16
        pixels = np.clip(adu, 0, max_code).astype(dtype)
        frame_id = self._frame_id
        self._frame_id += 1
        self._clock_lines += max(1, round(self.frame_period_us() / self._line_time_us))
        info["trigger_mode"] = self._trigger_mode.value
        return self._make_frame(pixels, frame_id, extra=info)


def _light_source_of(
    value: str | os.PathLike[str] | LightStateSource | LightState | None,
) -> LightStateSource | None:
    if value is None:
        return None
    if isinstance(value, str | os.PathLike):
        return LightStateFile(value)
    if isinstance(value, LightState):
        fixed = value
        return _FixedLight(fixed)
    if isinstance(value, LightStateSource):
        return value
    raise TypeError(f"light_state must be a path, a LightState or have light_state(): {value!r}")


class _FixedLight:
    def __init__(self, state: LightState) -> None:
        self.state = state

    def light_state(self) -> LightState:
        return self.state


def _positive(v: float, name: str) -> float:
    x = float(v)
    if not (math.isfinite(x) and x > 0):
        raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
    return x


def _non_negative(v: float, name: str) -> float:
    x = float(v)
    if not (math.isfinite(x) and x >= 0):
        raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
    return x
