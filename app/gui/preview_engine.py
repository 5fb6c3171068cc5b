"""Live reconstruction preview, without Qt: newest frame in, a few warm-started FISTA steps out.

:class:`PreviewEngine` turns one camera frame into a quick FISTA-TV estimate:

1. the frame's pixels minus a dark level (a number, or ``auto``: the camera's black level
   where the frame carries one, else its 1st percentile, as ``--dark auto`` on a
   measurement), clipped at 0;
2. when the frame is a region of the sensor (``frame.roi`` smaller than the PSF), it is placed
   into a sensor-sized array and the pixels outside the ROI are masked out of the data term, so
   the model stays exact (a ROI is an erasure mask, not a smaller PSF); when the frame says
   which sensor it came from (``frame.sensor``), a PSF of another sensor size is refused, so a
   whole small sensor is never taken for a region of a PSF's bigger one;
3. box-downsampled by ``downsample`` (the PSF too, renormalised to unit sum), scaled to max 1;
4. ``iters_per_frame`` FISTA-TV iterations warm-started from the previous frame's solver.

The forward model, its Lipschitz constant and the FISTA state (iterate, momentum, the TV
prox's dual) are kept between frames of the same geometry (shape, ROI, downsampling, model):
the new frame only replaces the measurement, so on a still scene the preview converges like one
long run, and the solver's gradient restart (``recon.fista``: POGM momentum) resets the
momentum when a new frame turns the step against it (a moving scene). Changing the geometry or
the PSF starts over from zero; changing tau or the prox iterations keeps the iterate but
restarts the momentum.

A frame can be cancelled from another thread (:meth:`PreviewEngine.cancel`): it stops at the
next stage of a model build or FISTA step and raises :class:`PreviewCancelled`.

Models: ``2d`` (one PSF, one image) and ``video`` (dual rolling shutter: ``video_bins`` time
bins from the frame's :class:`~drivers.timing.SensorTiming`, shown side by side).

:class:`PreviewLoop` runs an engine on a background thread and keeps only the newest submitted
frame (stale frames are dropped and counted); the GUI wraps it in a Qt worker, the benchmark
drives it directly. Nothing here imports Qt.
"""

from __future__ import annotations

import atexit
import math
import numbers
import os
import threading
import time
import weakref
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import torch

from recon.fista import Fista

__all__ = [
    "MODELS",
    "RANGES",
    "SATURATED_SKIP_FRACTION",
    "FrameSlot",
    "PreviewCancelled",
    "PreviewEngine",
    "PreviewError",
    "PreviewLoop",
    "PreviewResult",
    "PreviewSettings",
    "PreviewStats",
    "clamp_setting",
    "frame_dark_level",
    "frame_keywords",
    "psf_sensor_problem",
    "run_one",
    "saturation_verdict",
]

F32 = npt.NDArray[np.float32]

#: tau auto re-estimates when the measurement changes by more than this (relative L2)
AUTO_RETUNE = 0.25
#: iteration limit of the preview's tau search (a few seconds at 256^2 on one core)
AUTO_ITERS = 100

#: Engines whose tau auto estimate may still run: stopped at interpreter exit, since a daemon
#: thread still inside torch when Python finalises aborts the process.
_LIVE_ENGINES: weakref.WeakSet[Any] = weakref.WeakSet()


@atexit.register
def _stop_auto_estimates() -> None:
    for engine in list(_LIVE_ENGINES):
        engine.stop_auto(timeout_s=30.0)

#: Preview models the engine knows.
MODELS: tuple[str, ...] = ("2d", "video")

#: The one allowed range (inclusive) of each numeric preview setting. The preview controls'
#: spin boxes use these ranges (app/gui/panels.py), :class:`PreviewSettings` refuses a value
#: outside them and :meth:`PreviewSettings.from_dict_lenient` (the settings file) clamps one
#: into them, so the controls always show what the engine runs. ``threads``, ``target_fps`` and
#: ``prox_iters`` have no control; their ranges still bound a hand-edited settings file (a
#: ``video_bins`` of 1000000 once made a 2.6 GB, 16 s preview frame). ``dark`` is a level in
#: camera codes (None: auto).
RANGES: dict[str, tuple[float, float]] = {
    "tau": (0.0, 1.0),
    "iters_per_frame": (1, 200),
    "downsample": (1, 16),
    "prox_iters": (1, 100),
    "dark": (0.0, 65535.0),
    "video_bins": (2, 32),
    "threads": (0, 256),
    "target_fps": (0.0, 1e6),  # an unreachable rate: one iteration per frame
}
_INT_SETTINGS = ("iters_per_frame", "downsample", "prox_iters", "video_bins", "threads")


def _lower_priority(nice: int = 5) -> None:
    """Lower the calling thread's CPU priority.

    On Linux nice is per thread and the worker threads torch starts from this thread inherit
    it, so a background estimate gives way to the live preview (nice 5: about a third of a
    core's share against it, so on a busy machine it still finishes); a no-op where the
    platform does not allow it.
    """
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, max(os.getpriority(os.PRIO_PROCESS, tid), nice))
    except (AttributeError, OSError):  # not Linux, or not permitted: run at normal priority
        pass


#: A frame with at least this fraction of its pixels at the top code is not reconstructed.
SATURATED_SKIP_FRACTION = 0.5


def saturation_verdict(saturated: int, n_pixels: int) -> tuple[str | None, str]:
    """``(refusal, warning)`` for a frame with ``saturated`` of ``n_pixels`` at full scale.

    The one rule of the live preview and the trade panel: at least
    :data:`SATURATED_SKIP_FRACTION` of the pixels refuses the frame (the text says why and what
    to change); fewer, but some, is a warning; none, ``(None, "")``.
    """
    if n_pixels and saturated >= SATURATED_SKIP_FRACTION * n_pixels:
        return (f"frame saturated ({100.0 * saturated / n_pixels:.0f} % of the pixels at full "
                "scale): not reconstructed – lower the exposure, gain or source intensity", "")
    return None, (f"warning: {saturated} saturated pixel(s) in the frame" if saturated else "")

def psf_sensor_problem(psf_shape: tuple[int, ...], *, sensor: tuple[int, int],
                       roi: tuple[int, int, int, int] | None = None, binning: int = 1
                       ) -> str | None:
    """Why a PSF of ``psf_shape`` (rows, columns, unbinned) cannot serve frames of ``sensor``.

    The PSF must be the sensor's, or the frame's region's (a PSF calibrated at the ROI); at
    ``binning`` both are box-downsampled. None when it fits. The one rule of the preview's
    frames and of loading a PSF while a camera runs.
    """
    b = int(binning)
    ph, pw = int(psf_shape[-2]) // b, int(psf_shape[-1]) // b
    sh, sw = (int(v) for v in sensor)
    region = (ph, pw) if roi is None else (int(roi[3]) // b, int(roi[2]) // b)
    if (ph, pw) in ((sh // b, sw // b), region):
        return None
    return (f"the PSF is {psf_shape[-2]}x{psf_shape[-1]} but this camera's sensor is {sh}x{sw} "
            f"and the frame's region {region[0] * b}x{region[1] * b} (binning {b}): it "
            "belongs to another camera; calibrate a PSF for this one")


def frame_dark_level(pixels: npt.ArrayLike, dark: float | None,
                     black_level: float | None = None) -> float:
    """The dark level of a frame for the app: ``dark``, else (None: auto) the camera's.

    Auto is ``--dark auto``'s rule for a measurement (:func:`recon.readers.load_measurement`):
    the frame's ``black_level`` (:attr:`drivers.camera.Frame.black_level`, the code an unlit
    pixel reads, where the camera reports it), else the frame's 1st percentile
    (:func:`recon.preprocess.measurement_dark_level`). An estimate from the frame errs high on
    a lensless frame, whose every pixel sees scene light: on the simulated bench (black level
    100) the percentile reads 152, which cost the preview 1.1 dB at a fixed tau and 2.5 dB
    with the automatic tau (``tests/test_camera_black_level.py``), and the corner patch 330.
    The one rule of the preview, the jobs launched from it and the trade panel.
    """
    if dark is not None:
        return float(dark)
    if black_level is not None:
        return float(black_level)
    from recon.preprocess import measurement_dark_level

    return float(np.asarray(measurement_dark_level(np.asarray(pixels))).reshape(-1)[0])


class PreviewError(ValueError):
    """The frame cannot be previewed with this PSF and these settings (message says why)."""


class PreviewCancelled(PreviewError):
    """:meth:`PreviewEngine.cancel` stopped the frame in progress (no result)."""


@dataclass(frozen=True)
class PreviewSettings:
    """What the preview computes.

    Every numeric setting has one allowed range, :data:`RANGES` (the preview controls'
    ranges); a value outside it is refused here and clamped by :meth:`from_dict_lenient`.

    Attributes:
        model: ``2d`` or ``video``.
        tau: TV weight (on the measurement scaled to max 1).
        iters_per_frame: FISTA iterations per frame (warm-started); the most per frame when
            ``target_fps`` is set.
        downsample: box-downsampling factor of frame and PSF.
        prox_iters: inner TV-prox iterations per FISTA step.
        dark: dark level in camera codes, or ``None`` for auto (:func:`frame_dark_level`).
        video_bins: number of time bins of the ``video`` model.
        threads: torch intra-op threads (process-wide); 0 (the default) lets the thread
            policy (:mod:`recon.threads`) choose from the free cores, once when the preview
            starts or this setting changes: on a busy machine more threads only fight the
            camera and GUI threads.
        target_fps: the display rate to hold: a frame stops iterating (after at least one
            iteration) when one more would make its preview take longer than
            1 / ``target_fps``; the result says how many it ran. 0 always runs
            ``iters_per_frame``.
        tau_auto: choose tau from the frame itself (:mod:`recon.autotau`, held-out pixels)
            on a background thread, again only when the geometry or PSF changes or the
            scene changes (the measurement moves by more than ``AUTO_RETUNE`` relative to
            the one the estimate was made on), never every frame; ``tau`` serves until the
            first estimate arrives.

    """

    model: str = "2d"
    tau: float = 3e-4
    iters_per_frame: int = 3
    downsample: int = 1
    prox_iters: int = 2
    dark: float | None = None
    video_bins: int = 4
    threads: int = 0
    target_fps: float = 15.0
    tau_auto: bool = True

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise ValueError(f"preview model must be one of {MODELS}, got {self.model!r}")
        for name in ("tau", "target_fps", "dark", *_INT_SETTINGS):
            v = getattr(self, name)
            if name == "dark" and v is None:
                continue
            integer = name in _INT_SETTINGS
            kind = "an integer" if integer else "a finite number"
            if isinstance(v, bool) or not isinstance(v, numbers.Real):
                raise ValueError(f"{name} must be {kind}, got {v!r}")
            if not math.isfinite(v) or (integer and int(v) != v):
                raise ValueError(f"{name} must be {kind}, got {v!r}")
            lo, hi = RANGES[name]
            if not lo <= v <= hi:
                raise ValueError(f"{name} must be {kind} from {lo:g} to {hi:g}, got {v!r}")
            # one type per field: 4.0 bins are 4, a tau of 1 is 1.0 (the saved file says so)
            object.__setattr__(self, name, int(v) if integer else float(v))
        if not isinstance(self.tau_auto, bool):
            raise ValueError(f"tau_auto must be true or false, got {self.tau_auto!r}")

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PreviewSettings:
        """Inverse of :meth:`to_dict`; unknown keys are ignored, bad values raise ValueError."""
        known = {f for f in cls.__dataclass_fields__}
        return cls(**{k: v for k, v in d.items() if k in known})

    @classmethod
    def from_dict_lenient(cls, d: dict[str, Any]) -> tuple[PreviewSettings, list[str]]:
        """Like :meth:`from_dict`, but only a key with a bad value (or type) keeps its default.

        A number outside its range (:data:`RANGES`) is clamped into it. Every other key is
        kept. Returns the settings and one ``"key=value (why); using X"`` line per key that was
        replaced or clamped (empty when all were good).
        """
        defaults = cls()
        good: dict[str, Any] = {}
        problems: list[str] = []
        for k, v in d.items():
            if k not in cls.__dataclass_fields__:
                continue
            try:  # the checks are per field, so each key can be tried on its own
                cls(**{k: v})
            except (TypeError, ValueError, OverflowError) as exc:
                clamped = _clamped(k, v)
                if clamped is not None:
                    problems.append(f"{k}={v!r} ({exc}); using {clamped!r}")
                    good[k] = clamped
                    continue
                problems.append(f"{k}={v!r} ({exc}); using the default {getattr(defaults, k)!r}")
                continue
            good[k] = v
        try:
            return cls(**good), problems
        except (TypeError, ValueError, OverflowError) as exc:  # not expected: keys interact
            return defaults, [*problems, f"{good!r} ({exc}); using the defaults"]


def _clamped(name: str, v: Any) -> int | float | None:
    """``v`` moved into the range of setting ``name``.

    None when ``v`` is not a number of the right kind (a string, NaN, 2.5 iterations) or
    ``name`` has no range.
    """
    if name not in RANGES or isinstance(v, bool) or not isinstance(v, numbers.Real):
        return None
    if not math.isfinite(v) or (name in _INT_SETTINGS and int(v) != v):
        return None
    lo, hi = RANGES[name]
    out = min(max(v, lo), hi)
    return int(out) if name in _INT_SETTINGS else float(out)


def clamp_setting(name: str, value: float) -> float:
    """``value`` moved into the range of setting ``name`` (:data:`RANGES`)."""
    lo, hi = RANGES[name]
    return min(max(value, lo), hi)


@dataclass(frozen=True)
class PreviewResult:
    """One preview.

    ``image`` is (H, W) float32 (the ``video`` model: its bins side by side); ``levels`` are
    display levels (0 and the 99.5th percentile). ``latency_s`` runs from the frame's host
    timestamp to the end of the computation; ``compute_s`` is the engine's own time.
    ``iterations`` is what this frame ran: fewer than ``settings.iters_per_frame`` when the
    display rate (``settings.target_fps``) could not hold them; ``note`` then says so.
    ``dark`` is the dark level subtracted; ``dark_note`` says where an automatic one came from.
    ``model_note``: the video model's bins (how many, of how many lines; fewer than asked when
    the lines do not divide; identical under a global shutter).
    """

    image: F32
    levels: tuple[float, float]
    frame_id: int
    iterations: int
    total_iterations: int
    objective: float
    residual: float
    compute_s: float
    latency_s: float
    warm: bool
    settings: PreviewSettings
    shape: tuple[int, int]
    done_time: float = field(default=0.0)
    note: str = ""
    threads: str = ""
    tau: float = math.nan
    tau_note: str = ""
    dark: float = math.nan
    dark_note: str = ""
    model_note: str = ""


@dataclass(frozen=True)
class _Geometry:
    model: str
    frame_shape: tuple[int, int]
    roi: tuple[int, int, int, int] | None
    downsample: int
    video_bins: int
    timing_key: tuple[Any, ...] | None
    shutter_row0: int = 0  # the PSF's first sensor row (a PSF calibrated at a ROI: its y)


def _preview_tv(model: str) -> Any:
    """The preview's TV: the video model weighs differences in time by half."""
    from recon.tv import TV

    return TV(weight_k=0.5) if model == "video" else TV()


def _box(a: npt.NDArray[Any], f: int) -> F32:
    """Mean over f x f blocks of the last two axes (float32, remainder dropped)."""
    arr = np.asarray(a, dtype=np.float32)
    if f == 1:
        return np.ascontiguousarray(arr)
    h, w = arr.shape[-2] // f, arr.shape[-1] // f
    if h == 0 or w == 0:
        raise PreviewError(f"downsampling by {f} leaves nothing of a {arr.shape[-2:]} image")
    blocks = arr[..., : h * f, : w * f].reshape(*arr.shape[:-2], h, f, w, f)
    return np.ascontiguousarray(blocks.mean(axis=(-3, -1), dtype=np.float32))


class PreviewEngine:
    """Frame -> quick FISTA-TV estimate, warm-started across frames of the same geometry.

    ``psf`` is the full-sensor PSF (H, W) or (1, H, W) at the camera's unbinned resolution (a
    binned frame uses the PSF box-downsampled by the binning). Not thread-safe: one thread
    calls :meth:`process`; :meth:`set_settings` and :meth:`set_psf` may be called from any
    thread and take effect at the next frame.
    """

    def __init__(self, psf: npt.ArrayLike | None, settings: PreviewSettings | None = None) -> None:
        self._lock = threading.Lock()
        self._pending_psf: F32 | None = None
        self._psf: F32 | None = None
        self._settings = settings or PreviewSettings()
        self._pending_settings: PreviewSettings | None = None
        self._geometry: _Geometry | None = None
        self._model: Any = None
        self._lipschitz = 0.0
        self._mask: Any = None
        self._measured_share: Any = None  # per coarse pixel: the share of its pixels measured
        self._model_note = ""
        self._x: Any = None
        self._solver: Fista | None = None
        self._solver_key: tuple[float, int] | None = None
        self._total_iters = 0
        self._threads_set: int | None = None
        self._threads_reason = ""
        self._iter_s: float | None = None  # recent seconds per FISTA iteration
        # tau auto: model recipe for the estimating thread, its result and what it was for
        self._build_args: tuple[str, dict[str, Any]] | None = None
        self._auto_thread: threading.Thread | None = None
        _LIVE_ENGINES.add(self)
        self._auto_gen = 0
        self._auto_tau: float | None = None
        self._auto_ref: F32 | None = None
        self._auto_note = ""
        self._tail_s = 0.0  # recent seconds from the last iteration to the result
        self._cancel = threading.Event()
        if psf is not None:
            self._psf = self._check_psf(psf)

    # -- configuration -------------------------------------------------------------------------

    @staticmethod
    def _check_psf(psf: npt.ArrayLike) -> F32:
        arr = np.asarray(psf, dtype=np.float32)
        if arr.ndim == 3 and arr.shape[0] == 1:
            arr = arr[0]
        if arr.ndim != 2:
            raise PreviewError(f"the preview needs one 2D PSF (H, W), got shape {arr.shape}")
        if not np.all(np.isfinite(arr)) or float(arr.sum()) <= 0:
            raise PreviewError("the PSF must be finite with a positive sum")
        return np.ascontiguousarray(arr / arr.sum(dtype=np.float64), dtype=np.float32)

    @property
    def settings(self) -> PreviewSettings:
        """Settings in effect (or to take effect at the next frame)."""
        with self._lock:
            return self._pending_settings or self._settings

    def set_settings(self, settings: PreviewSettings) -> None:
        """Use ``settings`` from the next frame on."""
        with self._lock:
            self._pending_settings = settings

    def set_psf(self, psf: npt.ArrayLike | None) -> None:
        """Use ``psf`` from the next frame on (None: no preview possible)."""
        checked = None if psf is None else self._check_psf(psf)
        with self._lock:
            self._pending_psf = checked
            if checked is None:
                self._psf = None
            self._geometry = None

    @property
    def psf(self) -> F32 | None:
        """The PSF in use (or about to be), unit sum, at the camera's unbinned resolution."""
        with self._lock:
            return self._pending_psf if self._pending_psf is not None else self._psf

    @property
    def has_psf(self) -> bool:
        """Whether a PSF is set."""
        with self._lock:
            return self._psf is not None or self._pending_psf is not None

    def reset(self) -> None:
        """Forget the warm start (the next frame starts from zero)."""
        with self._lock:
            self._geometry = None

    def stop_auto(self, timeout_s: float = 10.0) -> None:
        """Cancel a running tau auto estimate and wait for its thread."""
        with self._lock:
            self._auto_gen += 1
            thread = self._auto_thread
        if thread is not None:
            thread.join(timeout_s)

    def cancel(self) -> None:
        """Stop the frame in progress at its next cancellation point, and refuse new frames.

        The cancellation points are the stages of a model build and every FISTA step (the
        stepwise contract of :mod:`recon.stepwise`); the frame then raises
        :class:`PreviewCancelled`, and so does every later one until :meth:`resume`. A running
        tau auto estimate is cancelled too (not waited for). Any thread may call it: the GUI
        calls it when the preview worker stops, so closing the window never waits for a long
        frame to finish.
        """
        self._cancel.set()
        with self._lock:
            self._auto_gen += 1

    def resume(self) -> None:
        """Accept frames again after :meth:`cancel` (tau auto estimates afresh)."""
        with self._lock:
            self._auto_ref = None
            self._auto_note = ""
        self._cancel.clear()

    @property
    def cancelled(self) -> bool:
        """Whether :meth:`cancel` was called (and not :meth:`resume`)."""
        return self._cancel.is_set()

    def _check_cancel(self) -> None:
        if self._cancel.is_set():
            raise PreviewCancelled("the preview was cancelled")

    @property
    def auto_pending(self) -> bool:
        """True while a tau auto estimate runs in the background."""
        with self._lock:
            return self._auto_thread is not None and self._auto_thread.is_alive()

    def wait_auto(self, timeout_s: float | None = None) -> bool:
        """Wait for a running tau auto estimate; True when none is running any more."""
        with self._lock:
            thread = self._auto_thread
        if thread is not None:
            thread.join(timeout_s)
        return not self.auto_pending

    # -- processing ----------------------------------------------------------------------------

    def _apply_pending(self) -> PreviewSettings:
        with self._lock:
            if self._pending_psf is not None:
                self._psf = self._pending_psf
                self._pending_psf = None
                self._geometry = None
            if self._pending_settings is not None:
                # model, downsampling and bins are part of the geometry: a change of those
                # rebuilds the model at the next frame; tau and iterations apply at once
                self._settings = self._pending_settings
                self._pending_settings = None
            return self._settings

    def process(
        self,
        pixels: npt.ArrayLike,
        *,
        frame_id: int = 0,
        timestamp: float | None = None,
        roi: tuple[int, int, int, int] | None = None,
        binning: int = 1,
        timing: Any = None,
        sensor: tuple[int, int] | None = None,
        black_level: float | None = None,
    ) -> PreviewResult:
        """Preview one frame.

        Args:
            pixels: (H, W) frame in camera codes.
            frame_id: carried into the result.
            timestamp: host time (``time.time()``) the frame arrived; latency is measured
                from it (default: now).
            roi: (x, y, width, height) of the frame on the sensor in unbinned pixels, or None
                for the full sensor.
            binning: the frame's binning factor.
            timing: the frame's :class:`~drivers.timing.SensorTiming` (``video`` model only).
            sensor: (rows, columns) of the camera's whole sensor in unbinned pixels, or None
                when unknown; the PSF (at ``binning``) must be that size.
            black_level: the camera's black level in codes (None: unknown), the automatic
                dark level when it is known (:func:`frame_dark_level`).

        """
        t0 = time.perf_counter()
        self._check_cancel()
        s = self._apply_pending()
        if self._threads_set != s.threads:
            from recon.threads import apply_threads

            self._threads_reason = apply_threads(s.threads).reason
            self._threads_set = s.threads
            if self._model is not None:
                self._fit_threads(self._model)
        if self._psf is None:
            raise PreviewError("no PSF: load or calibrate one to see a reconstruction")
        frame = np.asarray(pixels)
        if frame.ndim != 2:
            raise PreviewError(f"the preview takes 2D frames, got shape {frame.shape}")
        sensor_psf = self._psf_at_binning(binning)
        ph, pw = sensor_psf.shape
        if sensor is not None:
            problem = psf_sensor_problem(self._psf.shape, sensor=sensor, roi=roi,
                                         binning=binning)
            if problem is not None:
                raise PreviewError(problem)
        # roi is (x, y, width, height); the PSF (rows, columns)
        full_roi = roi is None or (roi[3] // binning, roi[2] // binning) == (ph, pw)
        row0 = 0
        if full_roi:
            if frame.shape != (ph, pw):
                raise PreviewError(
                    f"frame {frame.shape[0]}x{frame.shape[1]} does not match the PSF "
                    f"{ph}x{pw} (binning {binning}); calibrate a PSF for this sensor size"
                )
            if roi is not None:  # a PSF of this region: its rows are the region's rows
                row0 = int(roi[1])
            roi = None
        else:
            assert roi is not None
            x, y, w, h = (int(v) for v in roi)
            if (y + h) // binning > ph or (x + w) // binning > pw or x < 0 or y < 0:
                raise PreviewError(
                    f"the frame's region {w}x{h} at ({x}, {y}) lies outside the PSF's "
                    f"{ph}x{pw} sensor (binning {binning}); calibrate a PSF for this sensor")
        timing_key = None
        if s.model == "video":
            if timing is None:
                raise PreviewError("the video model needs the frame's sensor timing")
            timing_key = (timing.rows, timing.line_time_us, timing.exposure_lines,
                          str(timing.pattern), timing.trigger_delay_us)
        geo = _Geometry(s.model, (int(frame.shape[0]), int(frame.shape[1])), roi,
                        int(s.downsample), int(s.video_bins), timing_key,
                        row0 if s.model == "video" else 0)
        warm = geo == self._geometry and self._x is not None
        build_s = 0.0  # a one-off model build does not count against the display rate
        if geo != self._geometry:
            t_build = time.perf_counter()
            self._build(geo, sensor_psf, binning, timing)
            build_s = time.perf_counter() - t_build
            self._check_cancel()
        b, dark = self._measurement(frame, s, roi, binning, (ph, pw), black_level)
        bt = torch.from_numpy(b)[None]
        solver = self._solver
        # tau and its note read together: the estimate may finish while this frame runs
        tau, tau_note = self._auto_update(b, s) if s.tau_auto else (s.tau, "")
        key = (tau, s.prox_iters)
        if warm and solver is not None and self._solver_key == key:
            solver.set_measurement(bt)  # keep the iterate, the momentum and the TV dual
        else:
            tv = _preview_tv(s.model)
            # plain steps: a solver that never ends and is fed new frames would never leave
            # the preconditioned first phase (its end rules need one measurement), whose
            # fixed point is biased (recon/fista.py)
            solver = Fista(self._model.op, bt, tau=tau, tv=tv,
                                     x0=self._x if warm else None, max_iter=10**12, tol=0.0,
                                     prox_iters=s.prox_iters, lipschitz=self._lipschitz,
                                     precondition="off")
            self._solver, self._solver_key = solver, key
        step = None
        n = 0
        deadline = t0 + build_s + 1.0 / s.target_fps if s.target_fps > 0 else math.inf
        t_loop = time.perf_counter()
        while n < s.iters_per_frame and not solver.done:
            if n and self._iter_s is not None and (
                    time.perf_counter() + self._iter_s + self._tail_s > deadline):
                break  # one more would miss the display rate
            self._check_cancel()  # every step is a cancellation point
            t_it = time.perf_counter()
            step = solver.step()
            n += 1
            dt = time.perf_counter() - t_it
            self._iter_s = dt if self._iter_s is None else 0.7 * self._iter_s + 0.3 * dt
        t_tail = time.perf_counter()
        self._x = solver.x
        self._total_iters += n
        img = self._display(solver.x)
        lo = 0.0
        hi = float(np.percentile(img, 99.5)) if img.size else 1.0
        if not (hi > lo):
            hi = lo + 1.0
        done = time.time()
        t_end = time.perf_counter()
        compute = t_end - t0
        self._tail_s = 0.7 * self._tail_s + 0.3 * (t_end - t_tail)
        note = ""
        if n < s.iters_per_frame:
            note = (f"{n} of {s.iters_per_frame} iterations per frame to hold "
                    f"{s.target_fps:g} frames/s ({1e3 * (t_tail - t_loop) / max(n, 1):.0f} ms "
                    "per iteration)")
        return PreviewResult(
            image=img,
            levels=(lo, hi),
            frame_id=int(frame_id),
            iterations=n,
            total_iterations=self._total_iters,
            objective=float(solver.objective),
            residual=float(step.residual) if step is not None else float("nan"),
            compute_s=compute,
            latency_s=(done - timestamp) if timestamp is not None else compute,
            warm=warm,
            settings=s,
            shape=(int(img.shape[0]), int(img.shape[1])),
            done_time=done,
            note=note,
            threads=self._threads_reason,
            tau=tau,
            tau_note=tau_note,
            model_note=self._model_note,
            dark=dark,
            dark_note=("" if s.dark is not None else
                       f"dark {dark:g} (camera)" if black_level is not None else
                       f"dark {dark:g} (1st percentile)"),
        )

    # -- tau auto ------------------------------------------------------------------------------

    def _auto_update(self, b: F32, s: PreviewSettings) -> tuple[float, str]:
        """The tau to use now and its note; starts a background estimate on a scene change.

        Both are read together, under the lock: a note read later could name an estimate that
        finished after this tau was taken.
        """
        with self._lock:
            running = self._auto_thread is not None and self._auto_thread.is_alive()
            ref = self._auto_ref
            changed = ref is None or ref.shape != b.shape or float(
                np.linalg.norm(b - ref)) > AUTO_RETUNE * max(float(np.linalg.norm(ref)), 1e-30)
            if changed and not running and self._build_args is not None:
                self._auto_ref = b.copy()
                self._auto_note = "tau auto: estimating"
                gen = self._auto_gen
                self._auto_thread = threading.Thread(
                    target=self._estimate, args=(b.copy(), self._build_args, gen, s.prox_iters),
                    name="preview-tau-auto", daemon=True)
                self._auto_thread.start()
            return (self._auto_tau if self._auto_tau is not None else s.tau), self._auto_note

    def _estimate(self, b: F32, recipe: tuple[str, dict[str, Any]], gen: int,
                  prox_iters: int) -> None:
        """Background thread: choose tau on an independent copy of the model."""
        from recon.autotau import choose_tau
        from recon.models import build_model

        _lower_priority()  # the live preview comes first: this estimate gets the spare CPU
        try:
            model = build_model(recipe[0], **recipe[1])
            # the solver's TV (the video model's time weight): tau for the objective solved
            choice = choose_tau(model, torch.from_numpy(b)[None], max_iter=AUTO_ITERS,
                                min_iter=30, patience=30, prox_iters=prox_iters,
                                tv=_preview_tv(recipe[0]),
                                cancel=lambda: gen != self._auto_gen)
            tau, note = choice.tau, f"{choice.describe()} (re-estimated on a scene change)"
        except Exception as exc:  # too few pixels, memory refused, ...: keep the given tau
            # (a MemoryError left "tau auto: estimating" in the footer for good)
            tau, note = None, f"tau auto failed ({exc}); using the tau setting"
        with self._lock:
            if gen == self._auto_gen:  # not for an older geometry or PSF
                self._auto_tau, self._auto_note = tau, note

    def _fit_threads(self, model: Any) -> None:
        """One thread for a small preview grid (recon.threads.fit_threads), said in the stats."""
        from recon.threads import fit_threads

        fitted = fit_threads(model.scene_shape)
        if fitted is not None:
            self._threads_reason = fitted.reason

    def _psf_at_binning(self, binning: int) -> F32:
        assert self._psf is not None
        if binning == 1:
            return self._psf
        p = _box(self._psf, int(binning))
        return p / p.sum(dtype=np.float32)

    def _build(self, geo: _Geometry, psf: F32, binning: int, timing: Any) -> None:
        from recon.models import build_model

        d = geo.downsample
        psf_d = _box(psf, d)
        total = float(psf_d.sum())
        if total <= 0:
            raise PreviewError("the downsampled PSF is empty")
        psf_d = psf_d / np.float32(total)
        mask = sensor_mask = None
        if geo.roi is not None:
            from recon.preprocess import downsample_mask

            x, y, w, h = geo.roi
            sensor_mask = np.zeros(psf.shape, dtype=np.float32)
            b = binning
            sensor_mask[y // b : (y + h) // b, x // b : (x + w) // b] = 1.0
            # the mask rule of every command: a coarse pixel is measured when any of its
            # sensor pixels is (the preview kept only whole blocks: 5.9 % off the CLI)
            mask = downsample_mask(sensor_mask, d)
            if not mask.any():
                raise PreviewError(f"the ROI {geo.roi} is too small for downsampling by {d}")
        if geo.model == "video":
            from drivers.timing import shutter_function
            from recon.preprocess import downsample_rows

            # bins of `factor` lines directly (the mean of the one-line bins, as bin_time
            # makes them): the one-line function of a long exposure takes GBs
            factor = max(1, -(-int(timing.frame_lines) // geo.video_bins))
            m_k = shutter_function(timing, factor)
            self._check_cancel()
            # the rows the PSF covers (Frame: shutter_function(...)[:, roi.y : roi.y + h]):
            # a PSF calibrated at a ROI took the top rows' times, reversed on a lower half
            r0 = geo.shutter_row0
            m_k = m_k[:, r0 : r0 + psf.shape[0] * binning]
            if binning > 1:
                m_k = downsample_rows(m_k, binning)
            m_k = downsample_rows(m_k, d)[:, : psf_d.shape[0]]
            from recon.checks import check_shutter, check_shutter_frames

            try:  # the rules recon applies to a shutter file
                check_shutter_frames(m_k.shape[0], m_k.shape[1], "the video model",
                                     downsample=d)
                check_shutter(m_k, "the video model", rows_warning=False)
            except ValueError as exc:
                raise PreviewError(f"{exc} (the preview's video bins)") from None
            k = m_k.shape[0]
            asked = f" ({geo.video_bins} asked)" if k != geo.video_bins else ""
            model_note = f"{k} bins of {factor} lines{asked}"
            # every row integrates each bin alike (its times do not depend on the row)
            if m_k.shape[0] > 1 and np.allclose(m_k, m_k[:, :1]):
                model_note += (": every row sees the bins alike (a global shutter), so they "
                               "are not told apart; use the 2D model")
            recipe: tuple[str, dict[str, Any]] = (
                "video", {"psf": psf_d, "shutter": m_k.astype(np.float32), "mask": mask})
        else:
            recipe = ("2d", {"psf": psf_d, "mask": mask})
            model_note = ""
        self._check_cancel()
        model = build_model(recipe[0], **recipe[1])
        self._check_cancel()
        self._fit_threads(model)
        with self._lock:  # a new geometry or PSF: the next frame re-estimates tau
            self._build_args = recipe
            self._auto_gen += 1
            self._auto_tau = self._auto_ref = None
            self._auto_note = ""
        self._model = model
        self._mask = mask
        # downsample_masked's rule (the mean over the measured sensor pixels) with its
        # denominator made once: the function itself took 45 ms a frame at 960x1280
        self._measured_share = None if sensor_mask is None else _box(sensor_mask, d)
        self._model_note = model_note
        with torch.no_grad():  # every power iteration a cancellation point (17 s at 512x512
            # with 32 video bins, minutes at 1024x1024: a cancel waited for all of it)
            self._lipschitz = float(model.op.lipschitz(step=self._check_cancel))
        self._x = None
        self._solver = None
        self._geometry = geo

    def _measurement(
        self,
        frame: npt.NDArray[Any],
        s: PreviewSettings,
        roi: tuple[int, int, int, int] | None,
        binning: int,
        sensor: tuple[int, int],
        black_level: float | None,
    ) -> tuple[F32, float]:
        f = frame.astype(np.float32)
        dark = frame_dark_level(f, s.dark, black_level)
        f -= np.float32(dark)
        np.maximum(f, np.float32(0.0), out=f)
        if roi is not None:
            x, y, _, _ = roi
            full = np.zeros(sensor, dtype=np.float32)
            y0, x0 = y // binning, x // binning
            full[y0 : y0 + f.shape[0], x0 : x0 + f.shape[1]] = f[
                : sensor[0] - y0, : sensor[1] - x0
            ]
            f = full
        b = _box(f, s.downsample)  # 0 outside the region: its sums are the measured pixels
        share = self._measured_share
        if share is not None:  # their mean, as recon.preprocess.downsample_masked makes it
            np.divide(b, share, out=b, where=share > 0)
        peak = float(b.max())
        if not peak > 0:  # black, and a residual over a zero norm (1e27 in the footer)
            raise PreviewError(
                f"the frame is all at or below the dark level {dark:g} (its brightest pixel: "
                f"{float(frame.max()):g}): nothing to reconstruct; lower the dark level or "
                "set it to auto, or open the shutter / light the scene")
        b *= np.float32(1.0 / peak)
        return b, dark

    def _display(self, x: Any) -> F32:
        arr = x.detach().numpy()[0]  # (K, H, W)
        if arr.shape[0] == 1:
            return np.ascontiguousarray(arr[0], dtype=np.float32)
        k, h, w = arr.shape
        gap = 2
        out = np.zeros((h, k * w + (k - 1) * gap), dtype=np.float32)
        for i in range(k):
            out[:, i * (w + gap) : i * (w + gap) + w] = arr[i]
        return out


@dataclass(frozen=True)
class PreviewStats:
    """Counters of a :class:`FrameSlot`: frames submitted, previewed, dropped as stale."""

    submitted: int
    processed: int
    dropped: int
    errors: int
    last_error: str | None


def frame_keywords(frame: Any) -> dict[str, Any]:
    """:meth:`PreviewEngine.process` keywords of a :class:`drivers.camera.Frame`."""
    roi = frame.roi
    return {"frame_id": frame.frame_id, "timestamp": frame.timestamp,
            "roi": (roi.x, roi.y, roi.width, roi.height), "binning": frame.binning,
            "timing": frame.timing, "sensor": getattr(frame, "sensor", None),
            "black_level": getattr(frame, "black_level", None)}


class FrameSlot:
    """A one-frame mailbox: :meth:`put` replaces a frame nobody took yet (counted as dropped).

    Shared by :class:`PreviewLoop` (a Python thread) and the GUI's Qt worker, so both drop
    stale frames the same way.
    """

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._pending: tuple[Any, dict[str, Any]] | None = None
        self._closed = False
        self._submitted = self._processed = self._dropped = self._errors = 0
        self._last_error: str | None = None
        self._busy = False

    def put(self, pixels: npt.ArrayLike, **meta: Any) -> None:
        """Offer a frame (with :meth:`PreviewEngine.process` keywords)."""
        with self._cond:
            if self._pending is not None:
                self._dropped += 1
            self._pending = (pixels, meta)
            self._submitted += 1
            self._cond.notify_all()

    def take(self, timeout_s: float | None = 0.0) -> tuple[Any, dict[str, Any]] | None:
        """The waiting frame (waiting up to ``timeout_s``; None: until one comes or close)."""
        with self._cond:
            if timeout_s is None:
                while self._pending is None and not self._closed:
                    self._cond.wait()
            elif self._pending is None and timeout_s > 0:
                self._cond.wait(timeout_s)
            item, self._pending = self._pending, None
            if item is not None:
                self._busy = True
            return item

    def done(self, error: BaseException | None = None) -> None:
        """Report the end of the frame last taken."""
        with self._cond:
            self._busy = False
            if error is None:
                self._processed += 1
            else:
                self._errors += 1
                self._last_error = f"{type(error).__name__}: {error}"

    def close(self) -> None:
        """Wake a waiting :meth:`take` for good."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        with self._cond:
            return self._closed

    @property
    def busy(self) -> bool:
        """Whether a frame is being processed or waits."""
        with self._cond:
            return self._busy or self._pending is not None

    def stats(self) -> PreviewStats:
        """Current counters."""
        with self._cond:
            return PreviewStats(self._submitted, self._processed, self._dropped, self._errors,
                                self._last_error)


def run_one(engine: PreviewEngine, slot: FrameSlot) -> PreviewResult | BaseException | None:
    """Take the newest frame from ``slot`` and preview it (None: no frame waited).

    Errors are returned, not raised, after being counted in the slot.
    """
    item = slot.take()
    if item is None:
        return None
    pixels, meta = item
    try:
        result = engine.process(pixels, **meta)
    except Exception as exc:  # returned to the caller, who shows it
        slot.done(exc)
        return exc
    slot.done()
    return result


class PreviewLoop:
    """Runs a :class:`PreviewEngine` on its own thread, always on the newest submitted frame.

    ``on_result`` / ``on_error`` are called on the loop's thread.
    """

    def __init__(
        self,
        engine: PreviewEngine,
        on_result: Callable[[PreviewResult], None],
        on_error: Callable[[BaseException], None] | None = None,
        name: str = "preview",
    ) -> None:
        self.engine = engine
        self.slot = FrameSlot()
        self._on_result = on_result
        self._on_error = on_error
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, pixels: npt.ArrayLike, **meta: Any) -> None:
        """Queue ``pixels`` (with :meth:`PreviewEngine.process` keywords), replacing a stale one."""
        self.slot.put(pixels, **meta)

    def submit_frame(self, frame: Any) -> None:
        """Queue a :class:`drivers.camera.Frame`."""
        self.slot.put(frame.pixels, **frame_keywords(frame))

    @property
    def busy(self) -> bool:
        """Whether a frame is being processed or waits."""
        return self.slot.busy

    def stats(self) -> PreviewStats:
        """Current counters."""
        return self.slot.stats()

    def _run(self) -> None:
        while True:
            item = self.slot.take(None)
            if item is None:
                if self.slot.closed:
                    return
                continue
            pixels, meta = item
            try:
                result = self.engine.process(pixels, **meta)
            except Exception as exc:  # reported to the caller, the loop goes on
                self.slot.done(exc)
                if self._on_error is not None:
                    self._on_error(exc)
                continue
            self.slot.done()
            self._on_result(result)

    def stop(self, timeout_s: float = 10.0) -> None:
        """End the thread (after the frame in progress) and a running tau auto estimate."""
        self.slot.close()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout_s)
        self.engine.stop_auto(timeout_s)
