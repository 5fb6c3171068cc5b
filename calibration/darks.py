"""Dark frames, hot and dead pixel maps, and pixel repair.

- :func:`capture_darks`: N frames with the light off, averaged (a workflow step); dark frames
  at full scale (a saturated sensor, not a dark one) are refused by :func:`check_darks`.
- :func:`hot_pixels`: pixels whose dark level stands out from the sensor's (robust statistics).
- :func:`dead_pixels`: pixels whose response to a flat field is far below their neighbours'.
- :func:`pixel_maps` combines both into :class:`PixelMaps`, whose ``mask`` (1 = good,
  0 = hot or dead) is the erasure mask of the 2D-with-erasures model
  (``recon.models.build_model('2d', psf, mask=maps.mask)``).
- :func:`calibrate_pixel_maps`: the whole workflow (darks, then optionally flats after the
  caller has set up a uniform illumination), saved with :func:`recon.calibfile.save_pixel_maps`.
- :func:`repair_pixels`: replace bad pixels by the median of their good neighbours.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from calibration.frames import FrameStats, acquire_frames, robust_sigma
from calibration.sources import camera_description, source_off
from calibration.workflow import CalibrationError, Progress, Steps, scaled
from drivers.camera import Camera
from drivers.lightsource import LightSource

__all__ = [
    "DARK_NOISE_DEFINITION",
    "DARK_SATURATION_LIMIT",
    "PixelMaps",
    "calibrate_pixel_maps",
    "capture_darks",
    "check_darks",
    "dark_noise_rms",
    "dead_pixels",
    "hot_pixels",
    "local_median",
    "pixel_maps",
    "repair_pixels",
]


def capture_darks(
    camera: Camera,
    n: int = 16,
    *,
    source: LightSource | None = None,
    timeout_s: float = 5.0,
    settle: int = 1,
    fractions: tuple[float, float] = (0.0, 1.0),
) -> Steps[FrameStats]:
    """Average ``n`` dark frames at the camera's current exposure (the source is switched off).

    Without a ``source`` the caller makes sure no light reaches the sensor (cap on).
    """
    if source is not None:
        source_off(source, stage="darks")
    yield Progress("darks", "source off; taking dark frames", fractions[0])
    darks = yield from acquire_frames(
        camera,
        n,
        stage="darks",
        what="dark frame",
        timeout_s=timeout_s,
        settle=settle,
        fractions=fractions,
    )
    check_darks(darks)
    return darks


#: dark frames with more than this fraction of their pixels at full scale (in any frame) are
#: refused: the sensor saw light or the exposure / gain / black level is far too high. Hot
#: pixels are a per-mille on real sensors (up to 1 % in the simulated tests) and are mapped.
DARK_SATURATION_LIMIT = 0.05


def check_darks(darks: FrameStats, *, stage: str = "darks") -> None:
    """Refuse dark frames that are not dark: too many pixels at full scale.

    A dark frame at full scale (a Mono8 camera at 255 in 99.7 % of its pixels) has no dark
    level or noise to measure: its mean is the clipping level, its temporal noise 0.
    Raises :class:`CalibrationError` naming the fraction at full scale and what to change.
    """
    frac = float((np.asarray(darks.saturated) > 0).mean()) if darks.saturated.size else 0.0
    if frac > DARK_SATURATION_LIMIT:
        fmt = darks.last.pixel_format
        raise CalibrationError(
            f"dark frames are at full scale ({darks.full_scale}, {fmt}) in {100 * frac:.1f}% "
            f"of the pixels (limit {100 * DARK_SATURATION_LIMIT:g}%): the sensor is saturated, "
            "not dark",
            "Close the shutter or cap the lens and lower the exposure or gain (or the black "
            "level), then capture again; nothing was saved",
            stage=stage,
        )


#: what ``dark_noise_adu`` in a calibration file's metadata means (pixel maps and PSF)
DARK_NOISE_DEFINITION = ("rms: sqrt of the mean per-pixel temporal variance of the pixels "
                         "that are not hot or dead")


def dark_noise_rms(std: np.ndarray, exclude: np.ndarray | None = None) -> float:
    """Temporal dark noise of the sensor in ADU: sqrt of the mean per-pixel variance.

    ``std`` is the per-pixel temporal std; pixels in ``exclude`` (hot or dead) are left out.
    Not fooled by quantisation as the median per-pixel std is: with a read noise below one
    code, most pixels never change code in a few frames (std 0, so the median is 0) while
    the few that do carry the variance. This is the noise the codes actually have; for a
    noise well below one code it is below the q / sqrt(12) of a dithered quantiser, and the
    PSF calibration's noise floor (``max(this, 1 / sqrt(12))``) still applies there.
    """
    var = np.square(np.asarray(std, dtype=np.float64))
    if exclude is not None:
        var = var[~np.asarray(exclude, dtype=bool)]
    return float(math.sqrt(float(var.mean()))) if var.size else 0.0


def hot_pixels(
    darks: FrameStats, *, sigma: float = 6.0, min_adu: float = 2.0
) -> tuple[np.ndarray, dict[str, float]]:
    """Pixels whose mean dark level exceeds the sensor's median by more than a threshold.

    The threshold is ``max(sigma * s, min_adu)`` ADU, where ``s`` is the larger of the
    spatial spread of the dark levels (1.4826 MAD) and the noise of one pixel's mean (median
    temporal noise / sqrt(frames)). Returns the map and the numbers used.
    """
    level = darks.mean
    med = float(np.median(level))
    s_spatial = robust_sigma(level)
    s_mean = float(np.median(darks.std)) / math.sqrt(max(darks.n, 1))
    threshold = max(sigma * max(s_spatial, s_mean), float(min_adu))
    hot = level - med > threshold
    return hot, {
        "dark_median_adu": med,
        "hot_threshold_adu": threshold,
        "hot_sigma": float(sigma),
        "spatial_sigma_adu": s_spatial,
    }


def local_median(a: np.ndarray, size: int = 5, *, chunk_rows: int = 256) -> np.ndarray:
    """Median over a ``size x size`` window around every pixel (edges mirrored), float64.

    Computed in blocks of ``chunk_rows`` rows to bound memory on large sensors.
    """
    if size < 1 or size % 2 == 0:
        raise ValueError(f"window size must be odd and >= 1, got {size}")
    arr = np.asarray(a, dtype=np.float64)
    r = size // 2
    padded = np.pad(arr, r, mode="reflect" if min(arr.shape) > r else "edge")
    out = np.empty_like(arr)
    for y0 in range(0, arr.shape[0], chunk_rows):
        y1 = min(arr.shape[0], y0 + chunk_rows)
        block = padded[y0 : y1 + 2 * r]
        win = np.lib.stride_tricks.sliding_window_view(block, (size, size))
        out[y0:y1] = np.median(win.reshape(win.shape[0], win.shape[1], -1), axis=-1)
    return out


def dead_pixels(
    flats: FrameStats,
    darks: FrameStats,
    *,
    fraction: float = 0.5,
    window: int = 5,
    min_snr: float = 20.0,
) -> tuple[np.ndarray, dict[str, float]]:
    """Pixels whose flat-field response is below ``fraction`` of their neighbourhood median.

    Response = mean flat - mean dark (same exposure). The flat must be well exposed: a median
    response under ``min_snr`` times the dark noise, or more than 1% of pixels saturated, is
    refused with a :class:`CalibrationError`.
    """
    if flats.shape != darks.shape:
        raise CalibrationError(
            f"flat frames {flats.shape} and dark frames {darks.shape} differ in shape",
            "Take both with the same ROI and binning",
            stage="flats",
        )
    response = flats.mean - darks.mean
    med = float(np.median(response))
    noise = max(float(np.median(darks.std)), 0.5)
    sat_frac = float((flats.saturated > 0).mean())
    if sat_frac > 0.01:
        raise CalibrationError(
            f"flat frames are saturated in {100 * sat_frac:.1f}% of the pixels",
            "Lower the flat illumination or the exposure",
            stage="flats",
        )
    if med < min_snr * noise:
        raise CalibrationError(
            f"flat frames are too dark: median response {med:.3g} ADU above the dark level, "
            f"dark noise {noise:.3g} ADU",
            "Illuminate the sensor uniformly and brighter, or raise the exposure",
            stage="flats",
        )
    ref = local_median(response, window)
    dead = response < fraction * np.maximum(ref, 0.0)
    return dead, {"flat_median_adu": med, "dead_fraction": float(fraction), "window": window}


@dataclass(frozen=True)
class PixelMaps:
    """Dark statistics and bad-pixel maps of one sensor configuration."""

    dark_mean: np.ndarray
    dark_std: np.ndarray
    hot: np.ndarray
    dead: np.ndarray
    exposure_us: float | None
    frames_averaged: int
    flats_averaged: int
    thresholds: dict[str, float]
    camera: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None

    @property
    def bad(self) -> np.ndarray:
        """Hot or dead."""
        return np.asarray(self.hot | self.dead)

    @property
    def mask(self) -> np.ndarray:
        """Erasure mask (H, W) float32: 1 = good pixel, 0 = hot or dead."""
        return (~self.bad).astype(np.float32)

    def metadata(self) -> dict[str, Any]:
        """Metadata of the saved file."""
        return {
            "camera": self.camera,
            "exposure_us": self.exposure_us,
            "frames_averaged": self.frames_averaged,
            "flats_averaged": self.flats_averaged,
            "thresholds": self.thresholds,
            "hot_pixels": int(self.hot.sum()),
            "dead_pixels": int(self.dead.sum()),
            "dark_level": float(np.median(self.dark_mean)),
            # RMS of the good pixels' temporal std (see dark_noise_rms); the median per-pixel
            # std (0 when most pixels never change code) is kept beside it. Both are None
            # (unknown) for a single dark frame: one frame has no temporal noise to measure
            "dark_noise_adu": self.dark_noise_adu,
            "dark_noise_definition": DARK_NOISE_DEFINITION,
            "dark_noise_median_std_adu": (
                None if self.dark_noise_adu is None else float(np.median(self.dark_std))
            ),
        }

    @property
    def dark_noise_adu(self) -> float | None:
        """Temporal dark noise in ADU (:func:`dark_noise_rms` over the good pixels).

        None (unknown) from a single dark frame: temporal noise needs two frames or more.
        """
        if self.frames_averaged < 2:
            return None
        return dark_noise_rms(self.dark_std, exclude=self.bad)

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the ``.npz`` pixel-maps calibration file (atomically)."""
        from recon.calibfile import save_pixel_maps

        return save_pixel_maps(
            path,
            mask=self.mask,
            dark_mean=self.dark_mean,
            dark_std=self.dark_std,
            hot=self.hot,
            dead=self.dead,
            metadata=self.metadata(),
        )


def pixel_maps(
    darks: FrameStats,
    flats: FrameStats | None = None,
    *,
    hot_sigma: float = 6.0,
    hot_min_adu: float = 2.0,
    dead_fraction: float = 0.5,
    camera: dict[str, Any] | None = None,
) -> PixelMaps:
    """Hot pixels from ``darks``, dead pixels from ``flats`` (none without flats).

    Dark frames at full scale are refused (:func:`check_darks`).
    """
    check_darks(darks)
    hot, t_hot = hot_pixels(darks, sigma=hot_sigma, min_adu=hot_min_adu)
    thresholds = dict(t_hot)
    if flats is not None:
        dead, t_dead = dead_pixels(flats, darks, fraction=dead_fraction)
        thresholds.update(t_dead)
        dead &= ~hot
    else:
        dead = np.zeros_like(hot)
    return PixelMaps(
        dark_mean=darks.mean.astype(np.float32),
        dark_std=darks.std.astype(np.float32),
        hot=hot,
        dead=dead,
        exposure_us=darks.exposure_us,
        frames_averaged=darks.n,
        flats_averaged=0 if flats is None else flats.n,
        thresholds=thresholds,
        camera=dict(camera or {}),
    )


def calibrate_pixel_maps(
    camera: Camera,
    *,
    source: LightSource | None = None,
    n_darks: int = 16,
    n_flats: int = 0,
    prepare_darks: Callable[[], None] | None = None,
    prepare_flats: Callable[[], None] | None = None,
    hot_sigma: float = 6.0,
    dead_fraction: float = 0.5,
    timeout_s: float = 5.0,
    settle: int = 1,
    out: str | os.PathLike[str] | None = None,
) -> Steps[PixelMaps]:
    """Darks (and flats when ``n_flats`` > 0) -> :class:`PixelMaps`, saved to ``out``.

    ``prepare_darks`` / ``prepare_flats`` are called (blocking) before each series so the
    user can cap the camera or set up a uniform illumination (the CLI asks on the terminal,
    the GUI shows a dialog). The point source, when given, is switched off for the darks.
    """
    if prepare_darks is not None:
        yield Progress("darks", "waiting for the sensor to be covered", 0.0)
        prepare_darks()
    end_darks = 0.45 if n_flats > 0 else 0.9
    darks = yield from scaled(
        capture_darks(camera, n_darks, source=source, timeout_s=timeout_s, settle=settle),
        0.0,
        end_darks,
    )
    flats = None
    if n_flats > 0:
        if prepare_flats is not None:
            yield Progress("flats", "waiting for a uniform illumination", end_darks)
            prepare_flats()
        flats = yield from acquire_frames(
            camera,
            n_flats,
            stage="flats",
            what="flat frame",
            timeout_s=timeout_s,
            settle=settle,
            fractions=(end_darks, 0.9),
        )
    maps = pixel_maps(
        darks,
        flats,
        hot_sigma=hot_sigma,
        dead_fraction=dead_fraction,
        camera=camera_description(camera, darks.last),
    )
    yield Progress(
        "maps",
        f"{int(maps.hot.sum())} hot and {int(maps.dead.sum())} dead pixels",
        0.95,
        data={"hot": int(maps.hot.sum()), "dead": int(maps.dead.sum())},
    )
    if out is not None:
        yield Progress("save", f"saving {out}", 0.97)
        path = maps.save(out)
        maps = PixelMaps(**{**maps.__dict__, "path": path})
    yield Progress("done", "pixel maps done", 1.0)
    return maps


def repair_pixels(img: np.ndarray, bad: np.ndarray) -> np.ndarray:
    """Replace ``bad`` pixels by the median of their good neighbours (3x3, else 5x5).

    A bad pixel with no good pixel within 5x5 gets the median of all good pixels.
    Returns a float64 copy.
    """
    out = np.array(img, dtype=np.float64, copy=True)
    badm = np.asarray(bad, dtype=bool)
    if out.shape != badm.shape:
        raise ValueError(f"bad-pixel map {badm.shape} does not match the image {out.shape}")
    if not badm.any():
        return out
    ys, xs = np.nonzero(badm)
    src = np.where(badm, np.nan, out)
    todo = np.ones(ys.size, dtype=bool)
    for size in (3, 5):
        r = size // 2
        padded = np.pad(src, r, mode="constant", constant_values=np.nan)
        win = np.lib.stride_tricks.sliding_window_view(padded, (size, size))
        vals = win[ys[todo], xs[todo]].reshape(int(todo.sum()), -1)
        has = np.isfinite(vals).any(axis=1)
        if has.any():
            idx = np.flatnonzero(todo)[has]
            out[ys[idx], xs[idx]] = np.nanmedian(vals[has], axis=1)
            todo[idx] = False
        if not todo.any():
            return out
    good = out[~badm]
    out[ys[todo], xs[todo]] = float(np.median(good)) if good.size else 0.0
    return out
