"""PSF capture with the point source: the workflow, the processing and the quality report.

:func:`capture_psf` is a workflow (see :mod:`calibration.workflow`)::

    setup      identify the source, switch it off, set the start exposure
    darks      N dark frames averaged (source off); hot pixels from them
    exposure   source on; auto-exposure: the brightest PSF pixels reach the target fraction of
               full scale (default 75% +- 5%) with no saturated pixel
    frames     N PSF frames averaged at that exposure
    darks      the darks again when the exposure changed (dark current scales with it)
    process    dark subtracted, hot (and given bad) pixels repaired, clipped at zero,
               optionally centred and cropped/padded (:func:`process_psf`)
    quality    :func:`psf_quality`; refuse (:class:`CalibrationError`) a saturated PSF, a PSF
               with no signal above the dark noise, or an off-centre source
    save       the calibration file (:func:`recon.calibfile.save_psf_calibration`, atomic)

The source is switched off however the workflow ends. :func:`capture_depth_stack` runs it once
per position of a user-driven series and saves one stack file.
"""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from calibration.darks import (
    DARK_NOISE_DEFINITION,
    capture_darks,
    dark_noise_rms,
    hot_pixels,
    repair_pixels,
)
from calibration.frames import FrameStats, acquire_frames
from calibration.sources import (
    camera_description,
    source_alive,
    source_identity,
    source_off,
    source_off_quietly,
    source_on,
)
from calibration.workflow import CalibrationError, Progress, Steps, scaled
from drivers.camera import Camera, CameraError, FeatureNotAvailable
from drivers.lightsource import LightSource
from recon.psfcheck import autocorrelation_fwhm

__all__ = [
    "DepthStack",
    "PsfCalibration",
    "PsfQuality",
    "PsfSettings",
    "autocorrelation_fwhm",
    "capture_depth_stack",
    "capture_psf",
    "centre_psf",
    "centroid",
    "check_quality",
    "crop_or_pad",
    "light_kept",
    "process_psf",
    "psf_quality",
]

Centre = Literal["none", "centroid"] | tuple[float, float]

#: the most frames the SNR advice names (beyond it a target is said to be out of reach)
MAX_AVERAGE = 1_000_000

#: a PSF peak this many times the noise is light, not noise: the auto-exposure's test for
#: light (capped at ``min_snr``), and the line between "no PSF signal" and "the SNR target is
#: beyond this exposure and averaging" when a PSF misses ``min_snr``
SIGNAL_SNR = 10.0
#: a centring or crop (``centre``, ``shape``) that leaves out more than this fraction of the
#: PSF's light (its pixels above 3 x noise) is warned about
CROP_WARN_FRACTION = 0.05
#: ... and one that leaves out more than this is refused: a tenth of the caustic is not the
#: camera's PSF (a 1x1 crop was saved, "resolution nan")
CROP_REFUSE_FRACTION = 0.9


@dataclass(frozen=True)
class PsfSettings:
    """Settings of a PSF capture.

    Exposures are in microseconds; ``None`` bounds mean the camera's range. ``target_peak``
    and ``peak_tolerance`` are fractions of full scale (the top code of the pixel format);
    auto-exposure stays within 1 s unless ``max_exposure_us`` says otherwise. ``intensity``
    None keeps the source's setting.
    ``centre`` is ``'none'``, ``'centroid'`` (move the PSF's centroid to the centre pixel
    (H//2, W//2)) or a (row, col) that is moved there; ``shape`` crops or pads the result
    about its centre (default: the frame's shape). ``max_offcentre`` is the largest allowed
    distance of the PSF centroid from the sensor centre, as a fraction of the sensor size
    along each axis. ``min_snr``: the PSF peak must exceed this many times the noise of the
    averaged, dark-subtracted image.
    """

    n_frames: int = 16
    n_darks: int = 16
    auto_exposure: bool = True
    exposure_us: float | None = None
    min_exposure_us: float | None = None
    max_exposure_us: float | None = 1_000_000.0
    target_peak: float = 0.75
    peak_tolerance: float = 0.05
    max_exposure_steps: int = 12
    intensity: float | None = None
    centre: Centre = "none"
    shape: tuple[int, int] | None = None
    max_offcentre: float = 0.25
    min_snr: float = 10.0
    support_level: float = 0.1
    hot_sigma: float = 6.0
    repair_hot: bool = True
    frame_timeout_s: float = 5.0
    settle_frames: int = 1

    def __post_init__(self) -> None:
        for name in ("n_frames", "n_darks", "max_exposure_steps"):
            v = getattr(self, name)
            if int(v) != v or v < 1:
                raise ValueError(f"PsfSettings.{name} must be an integer >= 1, got {v!r}")
        if not (0.0 < self.target_peak - self.peak_tolerance) or not (
            self.target_peak + self.peak_tolerance < 1.0
        ):
            raise ValueError(
                f"target peak {self.target_peak} +- {self.peak_tolerance} must lie inside (0, 1)"
            )
        if self.intensity is not None and not 0.0 <= self.intensity <= 1.0:
            raise ValueError(f"intensity must be in [0, 1], got {self.intensity}")
        if not 0.0 < self.max_offcentre <= 1.0:
            raise ValueError(f"max_offcentre must be in (0, 1], got {self.max_offcentre}")
        if isinstance(self.centre, str) and self.centre not in ("none", "centroid"):
            raise ValueError(
                f"centre must be 'none', 'centroid' or (row, col), got {self.centre!r}"
            )
        if self.settle_frames < 0 or self.frame_timeout_s <= 0:
            raise ValueError("settle_frames must be >= 0 and frame_timeout_s > 0")


@dataclass(frozen=True)
class PsfQuality:
    """Quality report of a PSF (values in ADU of the dark-subtracted average, pixels).

    ``peak_fraction`` is the brightest good pixel of the averaged raw frames over full scale;
    ``noise_adu`` the noise of one pixel of the averaged, dark-subtracted PSF (from the
    darks); ``snr`` = ``peak_adu / noise_adu``; ``support_pixels`` counts pixels above
    ``support_threshold_adu`` (the larger of ``support_level`` x peak and 5 x noise);
    ``offset_px`` is the centroid's (row, col) distance from the sensor centre and
    ``offset_fraction`` the same over the sensor's (rows, cols); ``autocorr_fwhm_px`` the
    (row, col) full width at half maximum of the PSF's autocorrelation (mean removed), whose
    mean is ``resolution_px``, the two-point resolution the PSF implies.
    """

    peak_adu: float
    peak_fraction: float
    saturated_pixels: int
    noise_adu: float
    snr: float
    support_pixels: int
    support_fraction: float
    support_threshold_adu: float
    centroid_px: tuple[float, float]
    offset_px: tuple[float, float]
    offset_fraction: tuple[float, float]
    autocorr_fwhm_px: tuple[float, float]
    resolution_px: float
    total_adu: float

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON form."""
        d = asdict(self)
        for k, v in d.items():
            if isinstance(v, tuple):
                d[k] = list(v)
        return d

    def summary(self) -> str:
        """One line for people."""
        return (
            f"peak {self.peak_adu:.4g} ADU ({100 * self.peak_fraction:.0f}% of full scale), "
            f"{self.saturated_pixels} saturated, SNR {self.snr:.3g}, support "
            f"{self.support_pixels} px ({100 * self.support_fraction:.1f}%), resolution "
            f"{self.resolution_px:.2f} px, centroid offset ({self.offset_px[0]:+.1f}, "
            f"{self.offset_px[1]:+.1f}) px"
        )


@dataclass(frozen=True)
class PsfCalibration:
    """A captured PSF (float32, ADU, dark subtracted), its report and file metadata.

    ``quality`` is the report of the PSF as saved (centred, cropped or padded to
    ``PsfSettings.shape``); the refusal checks ran on ``captured_quality``, the PSF as the
    sensor saw it.
    """

    psf: np.ndarray
    quality: PsfQuality
    metadata: dict[str, Any]
    hot: np.ndarray
    exposure_us: float
    gain: float | None
    path: Path | None = None
    #: the report of the PSF as captured (before ``centre`` / ``shape``); ``quality``
    #: describes the saved PSF, and the two are one when neither moved or cropped it
    captured_quality: PsfQuality | None = None
    #: one line each for people: what was saved but deserves a look (a crop that cut the PSF)
    warnings: tuple[str, ...] = ()

    def normalised(self) -> np.ndarray:
        """The PSF scaled to unit sum (the convention of ``recon.io.load_psf``), float32."""
        s = float(self.psf.sum(dtype=np.float64))
        return (self.psf / np.float32(s)).astype(np.float32)

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the calibration file (atomically)."""
        from recon.calibfile import save_psf_calibration

        return save_psf_calibration(path, self.psf, self.metadata)


# --------------------------------------------------------------------------------------------
# processing and quality (pure functions)


def centroid(img: np.ndarray) -> tuple[float, float]:
    """Intensity-weighted (row, col) of a non-negative image (its centre when it is empty)."""
    a = np.asarray(img, dtype=np.float64)
    total = float(a.sum())
    h, w = a.shape
    if not total > 0:
        return ((h - 1) / 2.0, (w - 1) / 2.0)
    r = float(a.sum(axis=1) @ np.arange(h)) / total
    c = float(a.sum(axis=0) @ np.arange(w)) / total
    return (r, c)


def crop_or_pad(img: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The centred ``shape`` window of ``img``; a larger window is zero-padded around it."""
    rows, cols = int(shape[0]), int(shape[1])
    if rows < 1 or cols < 1:
        raise ValueError(f"shape must be positive, got {shape}")
    out = np.zeros((rows, cols), dtype=img.dtype)
    h, w = img.shape
    sy, sx = (h - rows) // 2, (w - cols) // 2
    y0, x0 = max(0, -sy), max(0, -sx)
    y1, x1 = min(rows, h - sy), min(cols, w - sx)
    if y1 > y0 and x1 > x0:
        out[y0:y1, x0:x1] = img[y0 + sy : y1 + sy, x0 + sx : x1 + sx]
    return out


def _shift(img: np.ndarray, dy: int, dx: int) -> np.ndarray:
    """Shift by whole pixels, filling with zeros."""
    h, w = img.shape
    out = np.zeros_like(img)
    ys, yd = (slice(0, h - dy), slice(dy, h)) if dy >= 0 else (slice(-dy, h), slice(0, h + dy))
    xs, xd = (slice(0, w - dx), slice(dx, w)) if dx >= 0 else (slice(-dx, w), slice(0, w + dx))
    if abs(dy) < h and abs(dx) < w:
        out[yd, xd] = img[ys, xs]
    return out


def centre_psf(
    psf: np.ndarray, centre: Centre, shape: tuple[int, int] | None = None
) -> tuple[np.ndarray, tuple[int, int]]:
    """Move the centroid (or a chosen (row, col)) to the centre pixel (H//2, W//2).

    Whole-pixel shift with zero fill, then crop/pad to ``shape``. Returns the image and the
    (row, col) shift applied.
    """
    h, w = psf.shape
    if isinstance(centre, str):
        if centre == "none":
            shift = (0, 0)
        elif centre == "centroid":
            r, c = centroid(psf)
            shift = (round(h // 2 - r), round(w // 2 - c))
        else:
            raise ValueError(f"centre must be 'none', 'centroid' or (row, col), got {centre!r}")
    else:
        r, c = float(centre[0]), float(centre[1])
        if not (0 <= r <= h - 1 and 0 <= c <= w - 1):
            raise ValueError(f"centre position ({r}, {c}) is outside the {h}x{w} PSF")
        shift = (round(h // 2 - r), round(w // 2 - c))
    out = _shift(psf, *shift) if shift != (0, 0) else psf.copy()
    if shape is not None and tuple(shape) != out.shape:
        out = crop_or_pad(out, shape)
    return out, (int(shift[0]), int(shift[1]))


def _place(img: np.ndarray, shift: tuple[int, int], shape: tuple[int, int]) -> np.ndarray:
    """``img`` shifted by ``shift`` and cropped/padded to ``shape``, as :func:`centre_psf`."""
    out = _shift(img, *shift) if tuple(shift) != (0, 0) else img
    return crop_or_pad(out, shape) if tuple(shape) != out.shape else out


def light_kept(captured: np.ndarray, saved: np.ndarray, noise_adu: float) -> float:
    """Fraction of the PSF's light that a centring or crop kept (1 when nothing was lost).

    Light is the sum of the pixels above 3 x ``noise_adu`` (the clipped noise floor of the
    many dark pixels of a large sensor is not light); 1 for a PSF without any.
    """
    thr = 3.0 * float(noise_adu)
    a = np.asarray(captured, dtype=np.float64)
    b = np.asarray(saved, dtype=np.float64)
    total = float(a[a > thr].sum())
    return float(b[b > thr].sum()) / total if total > 0 else 1.0


def psf_quality(
    psf: np.ndarray,
    *,
    noise_adu: float,
    peak_fraction: float,
    saturated_pixels: int,
    support_level: float = 0.1,
) -> PsfQuality:
    """Quality report of a processed (dark-subtracted, clipped) PSF in ADU."""
    a = np.asarray(psf, dtype=np.float64)
    h, w = a.shape
    peak = float(a.max())
    noise = float(noise_adu)
    snr = peak / noise if noise > 0 else math.inf
    thr = max(support_level * peak, 5.0 * noise)
    support = int((a > thr).sum()) if peak > 0 else 0
    cy, cx = centroid(a)
    dy, dx = cy - (h - 1) / 2.0, cx - (w - 1) / 2.0
    fy, fx = autocorrelation_fwhm(a)
    res = (fy + fx) / 2.0
    return PsfQuality(
        peak_adu=peak,
        peak_fraction=float(peak_fraction),
        saturated_pixels=int(saturated_pixels),
        noise_adu=noise,
        snr=float(snr),
        support_pixels=support,
        support_fraction=support / float(h * w),
        support_threshold_adu=float(thr),
        centroid_px=(cy, cx),
        offset_px=(dy, dx),
        offset_fraction=(dy / h, dx / w),
        autocorr_fwhm_px=(fy, fx),
        resolution_px=res,
        total_adu=float(a.sum()),
    )


def check_quality(q: PsfQuality, settings: PsfSettings, *, exposure_us: float | None) -> None:
    """Refuse a PSF that would ruin the reconstructions after it (raises CalibrationError)."""
    exp = "" if exposure_us is None else f" at {exposure_us:g} us exposure"
    if q.saturated_pixels > 0:
        raise CalibrationError(
            f"PSF is saturated: {q.saturated_pixels} pixels reached full scale{exp}",
            "Lower the point source intensity or the exposure (or let auto-exposure run), "
            "then capture again; nothing was saved",
            stage="quality",
        )
    if not q.snr >= settings.min_snr:
        if not q.snr >= SIGNAL_SNR:
            raise CalibrationError(
                f"no PSF signal above the dark noise: peak {q.peak_adu:.3g} ADU vs noise "
                f"{q.noise_adu:.3g} ADU (SNR {q.snr:.3g}, need {settings.min_snr:g}){exp}",
                "Check that the point source is on and shines on the diffuser; raise its "
                "intensity, the exposure or the number of frames; nothing was saved",
                stage="quality",
            )
        # the light is there: the SNR target is beyond what this exposure and averaging reach
        n, nd = settings.n_frames, settings.n_darks
        ratio = settings.min_snr / q.snr  # (a float product: inf, never OverflowError)
        need = ratio * ratio * 2.0 / (1.0 / n + 1.0 / nd)
        frames = (f"about {math.ceil(need):d} PSF and {math.ceil(need):d} dark frames reach "
                  "it: the SNR grows as the square root of their number" if need <= MAX_AVERAGE
                  else f"more than {MAX_AVERAGE:,} PSF and dark frames each would be needed: "
                  "the target is out of reach")
        low = q.peak_fraction < settings.target_peak - settings.peak_tolerance
        longer = (
            f"a longer exposure or a brighter source (the peak is at "
            f"{100 * q.peak_fraction:.0f}% of full scale), " if low else ""
        )
        raise CalibrationError(
            f"PSF SNR {q.snr:.3g} is below the SNR target {settings.min_snr:g}: the light is "
            f"there (peak {q.peak_adu:.3g} ADU, {100 * q.peak_fraction:.0f}% of full scale){exp}, "
            f"but {n} PSF and {nd} dark frames average the noise only down to "
            f"{q.noise_adu:.3g} ADU",
            f"Average more frames ({frames}), {longer}or lower the SNR target (--min-snr); "
            "nothing was saved",
            stage="quality",
        )
    fy, fx = q.offset_fraction
    if max(abs(fy), abs(fx)) > settings.max_offcentre:
        raise CalibrationError(
            f"point source is off-centre: the PSF centroid is {q.offset_px[0]:+.1f} rows, "
            f"{q.offset_px[1]:+.1f} columns from the sensor centre ({100 * fy:+.0f}%, "
            f"{100 * fx:+.0f}% of the sensor; limit +-{100 * settings.max_offcentre:.0f}%)",
            "Move the point source onto the optical axis until the pattern is centred on the "
            "sensor (or raise the off-centre limit); nothing was saved",
            stage="quality",
        )


def process_psf(
    light: FrameStats,
    dark: FrameStats,
    bad: np.ndarray | None,
    settings: PsfSettings,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Dark-subtract, repair ``bad`` pixels, clip at zero; returns (PSF float64, info).

    Centring and cropping are applied by :func:`centre_psf` after the quality check (the
    off-centre check looks at the PSF as captured).
    """
    if light.shape != dark.shape:
        raise CalibrationError(
            f"PSF frames {light.shape} and dark frames {dark.shape} differ in shape",
            "Do not change the ROI or binning during a calibration",
            stage="process",
        )
    diff = light.mean - dark.mean
    n_bad = 0
    if bad is not None and settings.repair_hot:
        n_bad = int(np.count_nonzero(bad))
        diff = repair_pixels(diff, bad)
    psf = np.maximum(diff, 0.0)
    return psf, {"repaired_pixels": n_bad}


# --------------------------------------------------------------------------------------------
# the capture workflow


def _kth_largest(values: np.ndarray, k: int = 3) -> float:
    v = np.asarray(values, dtype=np.float64).ravel()
    if v.size == 0:
        return 0.0
    k = min(k, v.size)
    return float(np.partition(v, v.size - k)[v.size - k])


def _exposure_bounds(camera: Camera, settings: PsfSettings) -> tuple[float, float]:
    lo, hi = 1.0, 10_000_000.0
    try:
        rng = camera.capabilities().exposure_range_us
    except CameraError:
        rng = None
    if rng is not None:
        lo, hi = float(rng[0]), float(rng[1])
    if settings.min_exposure_us is not None:
        lo = max(lo, float(settings.min_exposure_us))
    if settings.max_exposure_us is not None:
        hi = min(hi, float(settings.max_exposure_us))
    if lo > hi:
        raise CalibrationError(
            f"exposure range [{lo:g}, {hi:g}] us is empty",
            "Check the minimum and maximum exposure settings against the camera's range",
            stage="setup",
        )
    return lo, hi


def _set_exposure(camera: Camera, value: float, stage: str) -> float:
    try:
        camera.exposure_us = value
        return float(camera.exposure_us)
    except FeatureNotAvailable as exc:
        raise CalibrationError(
            f"{stage}: the camera has no exposure control ({exc})",
            "Turn auto-exposure off and set the exposure on the camera itself",
            stage=stage,
        ) from exc
    except (CameraError, ValueError) as exc:
        raise CalibrationError(
            f"{stage}: the camera refused exposure {value:g} us ({exc})",
            "Choose an exposure within the camera's range",
            stage=stage,
        ) from exc


def _auto_exposure(
    camera: Camera,
    settings: PsfSettings,
    dark: FrameStats,
    hot: np.ndarray,
    start_us: float,
    fractions: tuple[float, float],
    source_intensity: float | None = None,
    check: Callable[[], None] | None = None,
) -> Steps[tuple[float, list[dict[str, Any]]]]:
    """Find the exposure whose brightest PSF pixels reach the target; returns (us, log)."""
    lo, hi = _exposure_bounds(camera, settings)
    good = ~hot
    offset = float(np.median(dark.mean[good])) if good.any() else float(np.median(dark.mean))
    noise1 = max(dark_noise_rms(dark.std, exclude=hot), 1.0 / math.sqrt(12.0))
    # light is a signal above SIGNAL_SNR x the noise of one frame; an SNR target above that
    # (min_snr, for the averaged PSF) is checked on the averaged frames (check_quality): a
    # single test frame cannot reach it, and auto-exposure went round between "no light" and
    # "saturated" until it gave up blaming an unstable light
    light_snr = min(settings.min_snr, SIGNAL_SNR)
    target = settings.target_peak
    exposure = min(max(start_us, lo), hi)
    log: list[dict[str, Any]] = []
    f0, f1 = fractions
    n_steps = settings.max_exposure_steps
    for step in range(n_steps):
        exposure = _set_exposure(camera, exposure, "exposure")
        if log and exposure == log[-1]["exposure_us"] and not log[-1]["saturated"]:
            log[-1]["limited"] = "resolution"  # the camera rounds to the exposure just tried
            return exposure, log
        frac_done = f0 + (f1 - f0) * (step + 1) / n_steps
        stats = yield from acquire_frames(
            camera,
            1,
            stage="exposure",
            what="test frame",
            timeout_s=settings.frame_timeout_s,
            settle=settings.settle_frames,
            fractions=(frac_done, frac_done),
            check=check,
        )
        full = stats.full_scale
        peak_raw = float(stats.mean[good].max()) if good.any() else float(stats.mean.max())
        # the signal test uses the 3rd brightest pixel: one unflagged hot pixel cannot pass it
        signal = _kth_largest(stats.mean[good] - dark.mean[good])
        sat = stats.saturated_pixels(exclude=hot)
        frac = peak_raw / full
        entry: dict[str, Any] = {
            "exposure_us": exposure,
            "peak_fraction": frac,
            "signal_adu": signal,
            "saturated": sat,
        }
        log.append(entry)
        yield Progress(
            "exposure",
            f"exposure {exposure:g} us: peak {100 * frac:.0f}% of full scale, {sat} saturated",
            frac_done,
            frame=np.asarray(stats.last.pixels),
            data=entry,
        )
        if sat > 0:
            if exposure <= lo * (1 + 1e-9):
                raise CalibrationError(
                    f"PSF saturated ({sat} pixels at full scale) even at the shortest exposure "
                    f"{exposure:g} us",
                    "Lower the point source intensity or add a neutral-density filter, then "
                    "capture again; nothing was saved",
                    stage="exposure",
                )
            exposure = max(lo, exposure / 4.0)
            continue
        if signal <= light_snr * noise1:
            if exposure >= hi * (1 - 1e-9):
                said = (
                    ""
                    if source_intensity is None
                    else f" (the source reports intensity {source_intensity:g})"
                )
                raise CalibrationError(
                    f"no light from the point source{said}: the brightest pixels are "
                    f"{signal:.3g} ADU above the dark level, below {light_snr:g} x its noise "
                    f"({noise1:.3g} ADU), even at the longest exposure {exposure:g} us",
                    "Check that the point source is switched on, connected and pointed at the "
                    "diffuser; raise its intensity or the maximum exposure; nothing was saved",
                    stage="exposure",
                )
            exposure = min(hi, exposure * 10.0)
            continue
        if abs(frac - target) <= settings.peak_tolerance:
            return exposure, log
        denom = peak_raw - offset
        want = exposure * (target * full - offset) / denom if denom > 0 else exposure * 10.0
        want = min(max(want, lo), hi)
        if abs(want - exposure) <= 1e-6 * exposure:
            entry["limited"] = "max" if frac < target else "min"
            return exposure, log  # at a bound of the range: the best we can do
        exposure = want
    if log and log[-1]["saturated"] == 0 and log[-1]["signal_adu"] > light_snr * noise1:
        log[-1]["limited"] = "steps"
        return float(log[-1]["exposure_us"]), log
    raise CalibrationError(
        f"auto-exposure did not converge in {n_steps} steps (last: {log[-1] if log else None})",
        "Check that the light is stable, or set a fixed exposure",
        stage="exposure",
    )


def capture_psf(
    camera: Camera,
    source: LightSource,
    settings: PsfSettings | None = None,
    *,
    out: str | os.PathLike[str] | None = None,
    bad_pixels: np.ndarray | None = None,
    bad_pixels_from: str = "the bad-pixel map",
    extra_metadata: dict[str, Any] | None = None,
) -> Steps[PsfCalibration]:
    """Capture, check and (with ``out``) save a PSF; see the module docstring for the steps.

    ``bad_pixels`` (for example the dead pixels of a pixel-maps file) are repaired with the
    hot pixels found in the darks; they must have the frames' shape (``bad_pixels_from``
    names them in the refusal, for example the file they came from). Raises
    :class:`CalibrationError` when it must refuse. A centring or crop that leaves out more
    than :data:`CROP_WARN_FRACTION` of the PSF's light is saved, with a line in the result's
    ``warnings`` (and the file's metadata).
    """
    s = settings or PsfSettings()
    light_on = False
    done = False
    try:
        before_us: float | None = float(camera.exposure_us)
    except Exception:  # no exposure control (or no answer): nothing to put back
        before_us = None
    try:
        yield Progress("setup", "checking the point source", 0.0)
        identity = source_identity(source, stage="setup")
        source_off(source, stage="setup")
        if s.exposure_us is not None:
            _set_exposure(camera, float(s.exposure_us), "setup")
        try:
            start_us = float(camera.exposure_us)
        except FeatureNotAvailable:
            start_us = math.nan
        if s.auto_exposure and not math.isfinite(start_us):
            raise CalibrationError(
                "the camera has no exposure control, so auto-exposure cannot run",
                "Turn auto-exposure off and set the exposure on the camera",
                stage="setup",
            )

        dark0 = yield from capture_darks(
            camera,
            s.n_darks,
            timeout_s=s.frame_timeout_s,
            settle=s.settle_frames,
            fractions=(0.02, 0.2),
        )
        if bad_pixels is not None and np.shape(bad_pixels) != dark0.shape:
            have = "x".join(str(int(v)) for v in np.shape(bad_pixels))
            raise CalibrationError(
                f"{bad_pixels_from} is {have} (rows x columns) and the camera's frames are "
                f"{dark0.shape[0]}x{dark0.shape[1]}: the maps belong to another sensor size, "
                "ROI or binning",
                "Take pixel maps at this ROI and binning (calibrate darks) or leave them out; "
                "nothing was saved",
                stage="darks",
            )
        hot, _ = hot_pixels(dark0, sigma=s.hot_sigma)

        source_on(source, s.intensity, stage="exposure")
        light_on = True
        ae_log: list[dict[str, Any]] = []
        exposure = start_us
        if s.auto_exposure:
            exposure, ae_log = yield from _auto_exposure(
                camera,
                s,
                dark0,
                hot,
                start_us,
                (0.2, 0.4),
                source.intensity,
                check=source_alive(source, stage="exposure"),
            )
        light = yield from acquire_frames(
            camera,
            s.n_frames,
            stage="frames",
            what="PSF frame",
            timeout_s=s.frame_timeout_s,
            settle=s.settle_frames,
            fractions=(0.4, 0.75),
            check=source_alive(source, stage="frames"),
        )
        source_off(source, stage="darks")
        light_on = False

        dark = dark0
        if light.exposure_us is not None and dark0.exposure_us != light.exposure_us:
            dark = yield from capture_darks(
                camera,
                s.n_darks,
                timeout_s=s.frame_timeout_s,
                settle=s.settle_frames,
                fractions=(0.75, 0.92),
            )
            hot, _ = hot_pixels(dark, sigma=s.hot_sigma)

        yield Progress("process", "dark subtraction and hot-pixel repair", 0.93)
        bad = hot if bad_pixels is None else (hot | np.asarray(bad_pixels, dtype=bool))
        psf, info = process_psf(light, dark, bad, s)
        noise = max(dark_noise_rms(dark.std, exclude=bad), 1.0 / math.sqrt(12.0)) * math.sqrt(
            1.0 / light.n + 1.0 / dark.n
        )
        good = ~bad
        peak_fraction = float(light.mean[good].max()) / light.full_scale if good.any() else 0.0
        quality = psf_quality(
            psf,
            noise_adu=noise,
            peak_fraction=peak_fraction,
            saturated_pixels=light.saturated_pixels(exclude=bad),
            support_level=s.support_level,
        )
        yield Progress("quality", quality.summary(), 0.95, frame=psf, data=quality.to_dict())
        check_quality(quality, s, exposure_us=light.exposure_us)

        target_shape = s.shape or psf.shape
        out_psf, shift = centre_psf(psf, s.centre, target_shape)
        out_psf = out_psf.astype(np.float32)
        captured_quality = quality
        notes: list[str] = []
        if out_psf.shape != psf.shape or shift != (0, 0):
            # the report describes what is saved: the centred, cropped or padded PSF
            shape2 = (int(out_psf.shape[0]), int(out_psf.shape[1]))
            raw = _place(np.where(good, light.mean, 0.0), shift, shape2)
            sat = _place(((light.saturated > 0) & good).astype(np.uint8), shift, shape2)
            quality = psf_quality(
                out_psf,
                noise_adu=noise,
                peak_fraction=float(raw.max()) / light.full_scale,
                saturated_pixels=int(np.count_nonzero(sat)),
                support_level=s.support_level,
            )
            kept = light_kept(psf, out_psf, noise)
            what = []
            if shift != (0, 0):
                what.append(f"centring shift ({shift[0]:+d}, {shift[1]:+d}) px")
            if shape2[0] < psf.shape[0] or shape2[1] < psf.shape[1]:
                what.append(f"crop to {shape2[0]}x{shape2[1]}")
            done = (f"the {' and '.join(what) or 'placement'} of the {psf.shape[0]}x"
                    f"{psf.shape[1]} capture leaves out {100 * (1 - kept):.0f}% of the PSF's "
                    "light")
            if 1.0 - kept > CROP_REFUSE_FRACTION:
                raise CalibrationError(
                    f"{done}: a reconstruction with it would miss most of the caustic",
                    "Choose a larger --shape (or none), or move the source towards the sensor "
                    "centre; nothing was saved",
                    stage="quality",
                )
            if 1.0 - kept > CROP_WARN_FRACTION:
                notes.append(
                    f"{done}: reconstructions with it miss that part of the caustic; choose a "
                    "larger shape, or move the source to the sensor centre"
                )
        limited = ae_log[-1].get("limited") if ae_log else None
        if limited in ("max", "min", "steps", "resolution"):
            last = ae_log[-1]
            why = {"max": f"at the longest exposure allowed ({last['exposure_us']:g} us)",
                   "min": f"at the shortest exposure ({last['exposure_us']:g} us)",
                   "steps": f"after {len(ae_log)} steps",
                   "resolution": "at the camera's exposure step"}[limited]
            notes.append(
                f"auto-exposure stopped {why} with the peak at "
                f"{100 * last['peak_fraction']:.0f}% of full scale, not the target "
                f"{100 * s.target_peak:.0f} +/- {100 * s.peak_tolerance:.0f}%: "
                + ("a brighter source or a longer maximum exposure gives more signal"
                   if limited == "max" else "a dimmer source gives the target"
                   if limited == "min" else "the PSF was captured there"))
        timing = light.last.timing
        metadata: dict[str, Any] = {
            "camera": camera_description(camera, light.last),
            "source": identity,
            "exposure_us": light.exposure_us,
            "gain": light.gain,
            "frames_averaged": light.n,
            "darks_averaged": dark.n,
            "dark_level": float(np.median(dark.mean)),
            # unknown (None) from one dark frame: it has no temporal noise to measure
            "dark_noise_adu": dark_noise_rms(dark.std, exclude=bad) if dark.n > 1 else None,
            "dark_noise_definition": DARK_NOISE_DEFINITION,
            "full_scale": light.full_scale,
            "units": "ADU above the dark level",
            "timing": None if timing is None else timing.to_dict(),
            "quality": quality.to_dict(),
            "quality_as_captured": captured_quality.to_dict(),
            "warnings": notes,
            "auto_exposure": {
                "enabled": s.auto_exposure,
                "target_peak": s.target_peak,
                "tolerance": s.peak_tolerance,
                "steps": ae_log,
            },
            "processing": {
                "hot_pixels": int(hot.sum()),
                "repaired_pixels": info["repaired_pixels"],
                "centre": s.centre if isinstance(s.centre, str) else list(s.centre),
                "shift_px": list(shift),
                "shape": list(out_psf.shape),
                # fraction of the PSF's light (pixels above 3 x noise) the centring/crop kept
                "light_kept": light_kept(psf, out_psf, noise),
                "clipped_at_zero": True,
            },
            "settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(s).items()},
        }
        metadata.update(extra_metadata or {})
        result = PsfCalibration(
            psf=out_psf,
            quality=quality,
            metadata=metadata,
            hot=hot,
            exposure_us=float(light.exposure_us if light.exposure_us is not None else exposure),
            gain=light.gain,
            captured_quality=captured_quality,
            warnings=tuple(notes),
        )
        if out is not None:
            yield Progress("save", f"saving {out}", 0.98)
            result = replace(result, path=result.save(out))
        yield Progress("done", "PSF calibration done: " + quality.summary(), 1.0)
        done = True
        return result
    finally:
        if light_on:
            source_off_quietly(source)
        if not done and before_us is not None and math.isfinite(before_us):
            # a refused or cancelled capture leaves the camera as it found it (auto-exposure
            # may have gone up to its limit looking for light)
            with contextlib.suppress(Exception):
                camera.exposure_us = before_us


# --------------------------------------------------------------------------------------------
# depth stacks


@dataclass(frozen=True)
class DepthStack:
    """PSFs of a series of source positions, scaled to a common exposure and gain."""

    stack: np.ndarray
    positions: list[str]
    planes: list[PsfCalibration]
    metadata: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None


def capture_depth_stack(
    camera: Camera,
    source: LightSource,
    positions: Sequence[str],
    *,
    prompt: Callable[[int, str], None] | None = None,
    settings: PsfSettings | None = None,
    out: str | os.PathLike[str] | None = None,
    bad_pixels: np.ndarray | None = None,
    bad_pixels_from: str = "the bad-pixel map",
    extra_metadata: dict[str, Any] | None = None,
) -> Steps[DepthStack]:
    """Capture a PSF per position of a user-driven series and save them as one stack.

    Before each position ``prompt(index, position)`` is called (blocking): the CLI asks on
    the terminal, the GUI waits for the user's "next" in its wizard, a test moves the
    simulated source. Each plane is auto-exposed on its own and scaled to the first plane's
    exposure and gain, so the planes keep their relative energies. A refusal names the
    position it happened at. ``bad_pixels`` are repaired in every plane (as
    :func:`capture_psf` does).
    """
    labels = [str(p) for p in positions]
    if not labels:
        raise ValueError("a depth stack needs at least one position")
    planes: list[PsfCalibration] = []
    k = len(labels)
    for i, pos in enumerate(labels):
        yield Progress(
            "move", f"position {i + 1} of {k}: {pos}", i / k, data={"index": i, "position": pos}
        )
        if prompt is not None:
            prompt(i, pos)
        try:
            cal = yield from scaled(capture_psf(camera, source, settings,
                                                bad_pixels=bad_pixels,
                                                bad_pixels_from=bad_pixels_from),
                                    i / k, (i + 1) / k)
        except CalibrationError as exc:
            raise CalibrationError(
                f"position {pos} ({i + 1} of {k}): {exc.problem}", exc.hint, stage=exc.stage
            ) from exc
        planes.append(cal)
    shapes = {p.psf.shape for p in planes}
    if len(shapes) != 1:
        raise CalibrationError(
            f"the planes have different shapes {sorted(shapes)}",
            "Keep the ROI, binning and output shape fixed during a depth series",
            stage="stack",
        )
    e0, g0 = planes[0].exposure_us, planes[0].gain or 1.0
    scales = [(e0 / p.exposure_us) * (g0 / (p.gain or 1.0)) for p in planes]
    stack = np.stack([p.psf * np.float32(f) for p, f in zip(planes, scales, strict=True)])
    stack = stack.astype(np.float32)
    metadata: dict[str, Any] = {
        "camera": planes[0].metadata["camera"],
        "positions": labels,
        "planes": [
            {
                "position": pos,
                "exposure_us": p.exposure_us,
                "gain": p.gain,
                "scale": f,
                "quality": p.quality.to_dict(),
            }
            for pos, p, f in zip(labels, planes, scales, strict=True)
        ],
        "timing": planes[0].metadata["timing"],
        "exposure_us": e0,
        "gain": planes[0].gain,
        "units": "ADU above the dark level at the first plane's exposure and gain",
        **(extra_metadata or {}),
    }
    result = DepthStack(stack=stack, positions=labels, planes=planes, metadata=metadata)
    if out is not None:
        from recon.calibfile import save_psf_stack

        yield Progress("save", f"saving {out}", 0.99)
        result = replace(result, path=save_psf_stack(out, stack, metadata))
    yield Progress("done", f"depth stack of {k} planes done", 1.0)
    return result
