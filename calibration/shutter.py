"""Rolling-shutter functions: from the sensor timing, and measured with a strobed point source.

One path for every front end: :func:`calibrate_shutter` (the CLI's ``calibrate shutter`` and
the GUI wizard) snaps a frame, chooses the time bins with :func:`shutter_model` (the finest the
rows resolve unless a width is given; more bins than rows refused before anything is
captured or written), then returns the timing model's function or measures one, with the
camera (and source) in the metadata. :func:`strobe_time` is the point source's time rule.

From timing: :func:`shutter_from_timing` evaluates the drivers' timing model
(:func:`drivers.timing.shutter_function`) with time bins of ``bin_lines`` lines, cuts the ROI
rows, applies the camera's binning and an extra row downsampling (to match a measurement that
is box-downsampled before reconstruction), and keeps the timing it came from.

Measured: :func:`measure_shutter` is a workflow. The point source strobes (one pulse of
``pulse_us`` per frame, ``delay`` after the frame trigger) at a series of delays; in each frame
the rows whose exposure window overlaps the pulse are lit. Per row, the summed (dark
subtracted) signal against the delay is a trapezoid: it rises while the pulse enters the row's
window and falls while it leaves. Its half-level crossings give the row's window::

    start_r = rising half crossing + pulse / 2
    end_r   = falling half crossing + pulse / 2          (pulse <= exposure)

A least-squares fit of ``start_r = offset + line_time * L_r`` and
``end_r = offset + exposure + line_time * L_r`` (``L_r``: the row's start in lines for the
readout pattern) gives the line time, the offset (trigger delay) and the exposure; the result
is compared with the camera's timing model (the residual of the model against the measured
windows, and the relative line-time error).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from calibration.darks import capture_darks
from calibration.frames import acquire_frames
from calibration.sources import (
    camera_description,
    source_alive,
    source_call,
    source_identity,
    source_off,
    source_off_quietly,
    source_strobe,
)
from calibration.workflow import CalibrationError, Progress, Steps
from drivers.camera import Camera, CameraError, FeatureNotAvailable, Frame, Roi
from drivers.lightsource import MAX_TIME_US, LightSource
from drivers.timing import (
    ReadoutPattern,
    SensorTiming,
    row_start_lines,
    shutter_function,
)
from recon.preprocess import downsample_rows

__all__ = [
    "ShutterFunction",
    "ShutterMeasurement",
    "ShutterSettings",
    "analyse_strobe_scan",
    "calibrate_shutter",
    "measure_shutter",
    "shutter_for_frame",
    "shutter_from_timing",
    "shutter_model",
    "strobe_time",
]


@dataclass(frozen=True)
class ShutterFunction:
    """A shutter function M (K, rows) float32 and where it came from.

    ``bin_lines`` is the time-bin width in lines of ``timing``; ``roi_rows`` the (first row,
    row count) of the sensor it covers; ``binning`` the camera's row binning and
    ``row_factor`` the extra downsampling. ``method`` is ``'timing'`` or ``'measured'``.
    """

    shutter: np.ndarray
    timing: SensorTiming
    bin_lines: int
    row_factor: int = 1
    binning: int = 1
    roi_rows: tuple[int, int] | None = None
    method: str = "timing"
    measurement: ShutterMeasurement | None = None
    path: Path | None = None
    camera: dict[str, Any] | None = None
    source: str | None = None

    @property
    def bin_us(self) -> float:
        """Width of one time bin in microseconds."""
        return self.bin_lines * self.timing.line_time_us

    def metadata(self) -> dict[str, Any]:
        """Metadata of the saved file."""
        md: dict[str, Any] = {
            "timing": self.timing.to_dict(),
            "bin_lines": self.bin_lines,
            "bin_us": self.bin_us,
            "row_factor": self.row_factor,
            "binning": self.binning,
            "roi_rows": None if self.roi_rows is None else list(self.roi_rows),
            "method": self.method,
        }
        if self.measurement is not None:
            md["measurement"] = self.measurement.report()
        if self.camera is not None:
            md["camera"] = self.camera
        if self.source is not None:
            md["source"] = self.source
        return md

    def save(
        self, path: str | os.PathLike[str], extra_metadata: dict[str, Any] | None = None
    ) -> Path:
        """Write the ``.npz`` shutter calibration file (atomically), with the scan if any."""
        from recon.calibfile import save_shutter

        extra: dict[str, np.ndarray] = {}
        if self.measurement is not None:
            m = self.measurement
            extra = {
                "delays_us": m.delays_us,
                "row_response": m.row_response,
                "row_start_us": m.row_start_us,
                "row_end_us": m.row_end_us,
                "valid_rows": m.valid_rows,
            }
        md = self.metadata()
        md.update(extra_metadata or {})
        return save_shutter(path, self.shutter, md, extra)


def shutter_from_timing(
    timing: SensorTiming,
    *,
    bin_lines: int = 1,
    n_bins: int | None = None,
    roi_rows: tuple[int, int] | None = None,
    binning: int = 1,
    row_factor: int = 1,
) -> ShutterFunction:
    """The timing model's shutter function, cut to ``roi_rows`` and downsampled.

    Rows: ``shutter_function(timing, bin_lines)[:, y : y + h]``, then averaged over
    ``binning * row_factor`` rows (a binned camera row integrates like the mean of its rows).
    """
    m = shutter_function(timing, bin_lines, n_bins)
    if roi_rows is not None:
        y, h = int(roi_rows[0]), int(roi_rows[1])
        if y < 0 or h < 1 or y + h > timing.rows:
            raise ValueError(f"ROI rows {roi_rows} outside the sensor's {timing.rows} rows")
        m = m[:, y : y + h]
    factor = int(binning) * int(row_factor)
    if factor > 1:
        m = downsample_rows(m, factor)
    return ShutterFunction(
        shutter=m.astype(np.float32),
        timing=timing,
        bin_lines=int(bin_lines),
        row_factor=int(row_factor),
        binning=int(binning),
        roi_rows=None if roi_rows is None else (int(roi_rows[0]), int(roi_rows[1])),
    )


def shutter_for_frame(frame: Frame, *, bin_lines: int = 1, row_factor: int = 1) -> ShutterFunction:
    """Shutter function of a captured frame (its timing, ROI rows and binning)."""
    if frame.timing is None:
        raise ValueError(
            f"frame {frame.frame_id} from {frame.backend} camera '{frame.camera_id}' has no "
            "sensor timing: the shutter function cannot be computed from it"
        )
    return shutter_from_timing(
        frame.timing,
        bin_lines=bin_lines,
        roi_rows=(frame.roi.y, frame.roi.height),
        binning=frame.binning,
        row_factor=row_factor,
    )


# --------------------------------------------------------------------------------------------
# measurement


@dataclass(frozen=True)
class ShutterSettings:
    """Settings of a strobe scan (times in microseconds; None: derived from the model).

    ``pulse_us`` defaults to one model line time (at most half the exposure), ``step_us`` to
    half the pulse (or the span over ``max_delays`` when that is longer), ``span_us`` (the
    last delay) to 1.25 x the model's trigger delay + frame time. A row is used when its
    plateau exceeds ``min_snr`` times its dark noise and ``min_relative`` times the brightest
    row's plateau.
    """

    pulse_us: float | None = None
    step_us: float | None = None
    span_us: float | None = None
    frames_per_delay: int = 1
    n_darks: int = 8
    intensity: float | None = None
    min_snr: float = 10.0
    min_relative: float = 0.05
    pattern: ReadoutPattern | None = None
    max_delays: int = 2000
    frame_timeout_s: float = 5.0
    settle_frames: int = 1


@dataclass(frozen=True)
class ShutterMeasurement:
    """A strobe scan and the timing fitted to it.

    ``row_response`` (delays, rows) is the dark-subtracted row sum per delay;
    ``row_start_us`` / ``row_end_us`` the measured windows (NaN where an edge was not seen).
    ``model`` is the camera's timing model (None when it cannot say); ``model_residual_us``
    the RMS of the measured edges minus the model's, ``line_time_error`` the relative error
    of the model's line time against the fit.
    """

    delays_us: np.ndarray
    pulse_us: float
    row_response: np.ndarray
    row_start_us: np.ndarray
    row_end_us: np.ndarray
    valid_rows: np.ndarray
    row_lines: np.ndarray
    pattern: ReadoutPattern
    sensor_rows: int
    line_time_us: float
    offset_us: float
    exposure_us: float
    fit_residual_us: float
    model: SensorTiming | None = None
    model_residual_us: float | None = None
    line_time_error: float | None = None

    def timing(self) -> SensorTiming:
        """The measured timing (exposure rounded to whole measured lines)."""
        return SensorTiming(
            rows=self.sensor_rows,
            line_time_us=self.line_time_us,
            exposure_lines=max(1, round(self.exposure_us / self.line_time_us)),
            pattern=self.pattern,
            trigger_delay_us=max(0.0, self.offset_us),
        )

    def report(self) -> dict[str, Any]:
        """Plain-JSON summary: fit, residuals, comparison with the model."""

        def f(x: float | None) -> float | None:
            return None if x is None or not math.isfinite(x) else float(x)

        return {
            "line_time_us": f(self.line_time_us),
            "offset_us": f(self.offset_us),
            "exposure_us": f(self.exposure_us),
            "fit_residual_us": f(self.fit_residual_us),
            "pattern": self.pattern.value,
            "pulse_us": self.pulse_us,
            "delays": int(self.delays_us.size),
            "rows_used": int(self.valid_rows.sum()),
            "model_timing": None if self.model is None else self.model.to_dict(),
            "model_residual_us": f(self.model_residual_us),
            "line_time_error": f(self.line_time_error),
        }

    def summary(self) -> str:
        """One line for people."""
        s = (
            f"line time {self.line_time_us:.4g} us, offset {self.offset_us:.4g} us, exposure "
            f"{self.exposure_us:.4g} us (fit residual {self.fit_residual_us:.3g} us, "
            f"{int(self.valid_rows.sum())} rows)"
        )
        if self.model is not None and self.line_time_error is not None:
            s += (
                f"; model line time {self.model.line_time_us:.4g} us "
                f"({100 * self.line_time_error:+.2f}%), model residual "
                f"{self.model_residual_us:.3g} us"
            )
        return s


def _crossing(x0: float, x1: float, y0: float, y1: float, level: float) -> float:
    if y1 == y0:
        return (x0 + x1) / 2.0
    return x0 + (level - y0) * (x1 - x0) / (y1 - y0)


def _row_edges(d: np.ndarray, r: np.ndarray) -> tuple[float, float, float]:
    """(plateau, rising half crossing, falling half crossing) of one row's response."""
    if r.size >= 3:
        smooth = np.convolve(r, np.ones(3) / 3.0, mode="same")
        smooth[0], smooth[-1] = r[0], r[-1]
    else:
        smooth = r
    i_peak = int(np.argmax(smooth))
    top = float(smooth[i_peak])
    # the plateau level: median of the samples near the top (the maximum is biased by noise)
    plateau = float(np.median(r[r >= 0.8 * top])) if top > 0 else top
    half = plateau / 2.0
    rise = fall = math.nan
    i = i_peak
    while i > 0 and r[i] >= half:
        i -= 1
    if r[i] < half and i + 1 < r.size:
        rise = _crossing(d[i], d[i + 1], r[i], r[i + 1], half)
    j = i_peak
    while j < r.size - 1 and r[j] >= half:
        j += 1
    if r[j] < half and j > 0:
        fall = _crossing(d[j - 1], d[j], r[j - 1], r[j], half)
    return plateau, rise, fall


def analyse_strobe_scan(
    delays_us: np.ndarray,
    row_response: np.ndarray,
    row_lines: np.ndarray,
    row_noise: np.ndarray,
    *,
    pulse_us: float,
    pattern: ReadoutPattern,
    sensor_rows: int,
    model: SensorTiming | None = None,
    model_row_start_us: np.ndarray | None = None,
    min_snr: float = 10.0,
    min_relative: float = 0.05,
) -> ShutterMeasurement:
    """Fit line time, offset and exposure to a strobe scan (see the module docstring).

    ``row_lines`` is each frame row's start in lines for the readout pattern,
    ``row_noise`` its dark noise (same units as ``row_response``), ``model_row_start_us``
    the model's start of each frame row. Raises :class:`CalibrationError` when too few rows
    saw the pulses or the pattern leaves the line time undetermined.
    """
    d = np.asarray(delays_us, dtype=np.float64)
    resp = np.asarray(row_response, dtype=np.float64)
    if d.size < 4:
        raise CalibrationError(
            f"the scan has {d.size} delay(s): too few to find a row's rising and falling edge",
            "Use a longer span or a shorter step (the span must cover the exposure window)",
            stage="fit",
        )
    n_rows = resp.shape[1]
    plateaus = np.zeros(n_rows)
    starts = np.full(n_rows, np.nan)
    ends = np.full(n_rows, np.nan)
    for r in range(n_rows):
        plateau, rise, fall = _row_edges(d, resp[:, r])
        plateaus[r] = plateau
        starts[r] = rise + pulse_us / 2.0
        ends[r] = fall + pulse_us / 2.0
    best = float(plateaus.max()) if n_rows else 0.0
    valid = (plateaus > min_snr * np.asarray(row_noise)) & (plateaus > min_relative * best)
    starts[~valid] = np.nan
    ends[~valid] = np.nan
    lines = np.asarray(row_lines, dtype=np.float64)
    s_ok, e_ok = np.isfinite(starts), np.isfinite(ends)
    if int(valid.sum()) < 2:
        raise CalibrationError(
            f"only {int(valid.sum())} rows saw the strobe pulses clearly (need 2 or more)",
            "Raise the source intensity, the pulse length or the frames per delay; check "
            "that the source's trigger input is wired to the camera's trigger output",
            stage="fit",
        )
    edge_lines = np.concatenate([lines[s_ok], lines[e_ok]])
    if edge_lines.size < 3 or np.ptp(edge_lines) == 0:
        raise CalibrationError(
            "the measured rows all start together (a global shutter, or one row group): the "
            "line time is undetermined",
            "Measure a rolling-shutter mode, or use the shutter function from the timing",
            stage="fit",
        )
    # unknowns: offset a, end intercept b (= a + exposure), line time
    rows_a = np.column_stack([np.ones(s_ok.sum()), np.zeros(s_ok.sum()), lines[s_ok]])
    rows_b = np.column_stack([np.zeros(e_ok.sum()), np.ones(e_ok.sum()), lines[e_ok]])
    design = np.vstack([rows_a, rows_b])
    target = np.concatenate([starts[s_ok], ends[e_ok]])
    cols = [0, 1, 2] if s_ok.any() and e_ok.any() else ([0, 2] if s_ok.any() else [1, 2])
    coef, *_ = np.linalg.lstsq(design[:, cols], target, rcond=None)
    full = dict(zip(cols, coef, strict=True))
    line_time = float(full[2])
    resid = target - design[:, cols] @ coef
    fit_rms = float(np.sqrt(np.mean(resid**2)))
    if s_ok.any() and e_ok.any():
        offset, exposure = float(full[0]), float(full[1] - full[0])
    elif model is not None:
        exposure = model.exposure_us
        offset = float(full[0]) if s_ok.any() else float(full[1]) - exposure
    else:
        offset = exposure = math.nan
    if not (math.isfinite(line_time) and line_time > 0):
        raise CalibrationError(
            f"the fitted line time is {line_time:.3g} us",
            "Check the readout pattern setting and that the strobe delays cover the frame",
            stage="fit",
        )
    model_res = lt_err = None
    if model is not None and model_row_start_us is not None:
        ms = np.asarray(model_row_start_us, dtype=np.float64)
        diffs = np.concatenate(
            [starts[s_ok] - ms[s_ok], ends[e_ok] - (ms[e_ok] + model.exposure_us)]
        )
        model_res = float(np.sqrt(np.mean(diffs**2)))
        lt_err = (model.line_time_us - line_time) / line_time
    return ShutterMeasurement(
        delays_us=d,
        pulse_us=float(pulse_us),
        row_response=resp.astype(np.float32),
        row_start_us=starts,
        row_end_us=ends,
        valid_rows=valid,
        row_lines=lines,
        pattern=ReadoutPattern(pattern),
        sensor_rows=int(sensor_rows),
        line_time_us=line_time,
        offset_us=offset,
        exposure_us=exposure,
        fit_residual_us=fit_rms,
        model=model,
        model_residual_us=model_res,
        line_time_error=lt_err,
    )


def _frame_rows(roi: Roi, binning: int, n_rows: int) -> list[np.ndarray]:
    """Sensor rows making up each frame row."""
    return [roi.y + r * binning + np.arange(binning) for r in range(n_rows)]


def _on_source_grid(t_us: float, *, up: bool) -> float:
    """``t_us`` on the point source's time grid (the strobe times it sends), one step at least.

    Down for the pulse (it must stay within half the exposure), up for the delay step (the
    scan must stay within ``max_delays``). A default pulse or step (from the camera's line
    time) off that grid went out rounded while the analysis used the exact value.
    """
    from drivers.lightsource import TIME_RESOLUTION_US

    n = t_us / TIME_RESOLUTION_US
    steps = math.ceil(n - 1e-9) if up else math.floor(n + 1e-9)
    return max(steps, 1) * TIME_RESOLUTION_US


def measure_shutter(
    camera: Camera,
    source: LightSource,
    settings: ShutterSettings | None = None,
    *,
    bin_lines: int = 1,
    row_factor: int = 1,
    out: str | os.PathLike[str] | None = None,
) -> Steps[ShutterFunction]:
    """Strobe scan -> measured timing -> shutter function (saved to ``out``).

    The result's ``measurement`` holds the scan, the fit and the comparison with the camera's
    timing model; its ``shutter`` comes from the measured timing (same ROI rows, binning and
    ``row_factor`` as the frames); its ``camera`` and ``source`` say what measured it (saved
    or not). The camera's exposure and readout pattern are used as set. Front ends call
    :func:`calibrate_shutter`, which chooses ``bin_lines`` first.
    """
    s = settings or ShutterSettings()
    strobing = False
    try:
        yield Progress("setup", "checking the point source and the camera timing", 0.0)
        identity = source_identity(source, stage="setup")
        source_off(source, stage="setup")
        model = camera.timing
        pattern = s.pattern
        if pattern is None:
            try:
                pattern = camera.readout_pattern
            except FeatureNotAvailable:
                pattern = model.pattern if model is not None else None
        if pattern is None:
            raise CalibrationError(
                "the camera does not report its readout pattern",
                "Give the pattern (top-down, outside-in, centre-out) explicitly",
                stage="setup",
            )
        pattern = ReadoutPattern(pattern)
        try:
            sensor_rows = int(camera.capabilities().sensor_height)
        except CameraError:
            sensor_rows = model.rows if model is not None else 0
        if model is None and (s.pulse_us is None or s.span_us is None):
            raise CalibrationError(
                "the camera has no timing model to derive the scan from",
                "Give the pulse length and the scan span explicitly",
                stage="setup",
            )
        pulse = s.pulse_us
        if pulse is None:
            assert model is not None
            # on the source's time grid: the analysis must use the pulse that is sent
            pulse = _on_source_grid(min(model.line_time_us, model.exposure_us / 2.0), up=False)
        span = s.span_us
        if span is None:
            assert model is not None
            span = 1.25 * (model.trigger_delay_us + model.frame_time_us) + pulse
        step = s.step_us
        if step is None:  # half the pulse, coarser where the span needs more than max_delays
            step = _on_source_grid(max(pulse / 2.0, span / max(1, s.max_delays - 1)), up=True)
        if not (pulse > 0 and step > 0 and span > 0):
            raise ValueError(f"pulse, step and span must be > 0 (got {pulse}, {step}, {span})")
        if model is not None and pulse > model.exposure_us / 2.0:
            raise CalibrationError(
                f"a {pulse:g} us pulse is longer than half the {model.exposure_us:g} us "
                "exposure: the rows' edges cannot be told apart",
                "Use a shorter pulse (default: one line time) or a longer exposure",
                stage="setup",
            )
        if span + pulse > MAX_TIME_US:  # the source's longest strobe delay and pulse
            raise CalibrationError(
                f"a {span:g} us span ends beyond the point source's longest strobe delay "
                f"({MAX_TIME_US:g} us)",
                "Use a shorter span (--span; by default the frame time and trigger delay "
                "set it)",
                stage="setup",
            )
        if model is not None and s.step_us is None and step > model.exposure_us / 2.0:
            # the span forced the step up (at most max_delays delays): a row's exposure window
            # would fall between delays, and the scan would end in "no row saw the pulses"
            raise CalibrationError(
                f"a {span:g} us span in at most {s.max_delays} delays needs steps of {step:g} "
                f"us, more than half the {model.exposure_us:g} us exposure: the rows' "
                "windows would fall between the delays",
                (f"Use a shorter span (--span; the default, "
                 f"{1.25 * (model.trigger_delay_us + model.frame_time_us) + pulse:.4g} us, "
                 "covers the frame) or a longer exposure" if s.span_us is not None else
                 "Use a longer exposure, or a smaller ROI (fewer rows to scan): the frame is "
                 "too long for this exposure in the scan's delays"),
                stage="setup",
            )
        delays = np.arange(0.0, span + step / 2.0, step)
        if delays.size > s.max_delays:
            raise CalibrationError(
                f"the scan would need {delays.size} delays (span {span:g} us, step {step:g} us)",
                f"Use a longer step or a shorter span (at most {s.max_delays} delays)",
                stage="setup",
            )

        dark = yield from capture_darks(
            camera,
            s.n_darks,
            timeout_s=s.frame_timeout_s,
            settle=s.settle_frames,
            fractions=(0.01, 0.1),
        )
        if s.intensity is not None:
            value = float(s.intensity)
            source_call(
                source,
                f"set intensity {value:g}",
                lambda: source.set_intensity(value),
                stage="scan",
            )
        responses = np.zeros((delays.size, dark.shape[0]))
        for i, delay in enumerate(delays):
            source_strobe(source, float(delay), float(pulse), stage="scan")
            strobing = True
            frac = 0.1 + 0.85 * (i + 1) / delays.size
            stats = yield from acquire_frames(
                camera,
                s.frames_per_delay,
                stage="scan",
                what=f"frame at delay {delay:g} us",
                timeout_s=s.frame_timeout_s,
                settle=s.settle_frames,
                fractions=(frac, frac),
                check=source_alive(source, stage="scan"),
            )
            responses[i] = (stats.mean - dark.mean).sum(axis=1)
            yield Progress(
                "scan",
                f"strobe delay {delay:g} us ({i + 1} of {delays.size})",
                frac,
                frame=np.asarray(stats.last.pixels),
                data={"delay_us": float(delay), "index": i, "of": int(delays.size)},
            )
        source_off(source, stage="scan")
        strobing = False

        frame = dark.last
        rows_of = _frame_rows(frame.roi, frame.binning, dark.shape[0])
        sensor_rows = sensor_rows or (model.rows if model is not None else frame.roi.height)
        start_lines = row_start_lines(sensor_rows, pattern).astype(np.float64)
        row_lines = np.array([start_lines[rs].mean() for rs in rows_of])
        model_starts = None
        if model is not None:
            ms = model.row_start_us()
            model_starts = np.array([ms[rs].mean() for rs in rows_of])
        row_noise = np.sqrt((dark.std**2).sum(axis=1) / s.frames_per_delay + 1e-12)
        yield Progress("fit", "fitting line time and offset", 0.96)
        meas = analyse_strobe_scan(
            delays,
            responses,
            row_lines,
            row_noise,
            pulse_us=pulse,
            pattern=pattern,
            sensor_rows=sensor_rows,
            model=model,
            model_row_start_us=model_starts,
            min_snr=s.min_snr,
            min_relative=s.min_relative,
        )
        sf = shutter_from_timing(
            meas.timing(),
            bin_lines=bin_lines,
            roi_rows=(frame.roi.y, frame.roi.height),
            binning=frame.binning,
            row_factor=row_factor,
        )
        sf = replace(sf, method="measured", measurement=meas,
                     camera=camera_description(camera, frame), source=identity)
        yield Progress("fit", meas.summary(), 0.97, data=meas.report())
        if out is not None:
            yield Progress("save", f"saving {out}", 0.98)
            sf = replace(sf, path=sf.save(out))
        yield Progress("done", "shutter measured: " + meas.summary(), 1.0)
        return sf
    finally:
        if strobing:
            source_off_quietly(source)


# --------------------------------------------------------------------------------------------
# the one path of the front ends (CLI and GUI)


def strobe_time(value_us: float, what: str) -> tuple[float, str | None]:
    """A strobe pulse or delay step as the point source sends it: ``(sent_us, warning)``.

    The source times its strobes in steps of ``TIME_RESOLUTION_US`` (0.1 us: the driver sends
    one decimal). A value that rounds below one step is refused (ValueError, one line: it
    would go out as 0 and the firmware's refusal would blame the hardware); a value off the
    grid is rounded to what is sent, and ``warning`` says so (None when nothing changed).
    ``what`` names the value in the messages (``"--pulse 0.26us"``, ``"strobe pulse 0.26 us"``).
    """
    from drivers.lightsource import TIME_RESOLUTION_US

    value = float(value_us)
    sent = round(value / TIME_RESOLUTION_US) * TIME_RESOLUTION_US
    if not math.isfinite(value) or sent < TIME_RESOLUTION_US:
        raise ValueError(f"{what}: the point source times its pulses in steps of "
                         f"{TIME_RESOLUTION_US:g} us; use {TIME_RESOLUTION_US:g}us or more")
    sent = round(sent, 1)
    if abs(sent - value) > 1e-9:
        return sent, (f"{what} is rounded to {sent:g} us, the point source's "
                      f"{TIME_RESOLUTION_US:g} us resolution")
    return sent, None


def shutter_model(frame: Frame, *, bin_lines: int | None = None,
                  row_factor: int = 1) -> ShutterFunction:
    """The frame's shutter function at ``bin_lines``, or at the finest bins the rows resolve.

    Without ``bin_lines`` (None): at least ``row_factor`` lines wide, wider until the bins are
    no more than the rows (a rolling shutter resolves at most as many frames as rows: 1-line
    bins on 3-line rows, or a long exposure, made a file that recon and simulate refused).
    The result's ``bin_lines`` is the width used. More bins than rows are refused
    (ValueError, one line, in recon's words) before anything is captured or written.
    """
    from recon.checks import check_shutter_frames

    if (bin_lines is not None and int(bin_lines) < 1) or int(row_factor) < 1:
        raise ValueError(f"the time bin ({bin_lines} lines) and the row downsampling "
                         f"({row_factor}) must be 1 or more")

    def model(width: int) -> ShutterFunction:
        return shutter_for_frame(frame, bin_lines=width, row_factor=row_factor)

    if bin_lines is None:
        width = int(row_factor)
        sf = model(width)
        k, rows = sf.shutter.shape
        if k > rows:  # about k * width lines of time: start near the width that fits
            width = max(width + 1, -(-k * width // rows))
            sf = model(width)
            while sf.shutter.shape[0] > sf.shutter.shape[1]:
                width += 1
                sf = model(width)
    else:
        sf = model(int(bin_lines))
    check_shutter_frames(*sf.shutter.shape, "the shutter function", downsample=row_factor)
    return sf


def calibrate_shutter(
    camera: Camera,
    source: LightSource | None,
    settings: ShutterSettings | None = None,
    *,
    bin_lines: int | None = None,
    row_factor: int = 1,
    out: str | os.PathLike[str] | None = None,
    timeout_s: float = 5.0,
) -> Steps[ShutterFunction]:
    """The shutter function of ``calibrate shutter`` and the GUI wizard (saved to ``out``).

    Snaps one frame (``timeout_s``); its timing model chooses the bins (:func:`shutter_model`:
    ``bin_lines`` None is the finest the rows resolve), so a setting that gives more bins than
    rows is refused before any scan. Without a ``source`` the result is the timing model's
    function; with one it is measured (:func:`measure_shutter`, ``settings``) at the same
    bin width. Either way the result holds the camera (and the source) for its metadata.
    """
    yield Progress("timing", "reading the camera's timing model", 0.0)
    frame = camera.snap(timeout_s)
    sf = shutter_model(frame, bin_lines=bin_lines, row_factor=row_factor)
    if source is not None:
        return (yield from measure_shutter(camera, source, settings, bin_lines=sf.bin_lines,
                                           row_factor=row_factor, out=out))
    sf = replace(sf, camera=camera_description(camera, frame))
    if out is not None:
        yield Progress("save", f"saving {out}", 0.9)
        sf = replace(sf, path=sf.save(out))
    yield Progress("done", f"{sf.shutter.shape[0]} time bins of {sf.bin_lines} lines", 1.0)
    return sf
