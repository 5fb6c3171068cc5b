"""Averaging frames from a camera, as a workflow step.

:func:`acquire_frames` runs the camera's lossless acquisition path for ``n`` frames (plus
``settle`` frames that are dropped, for a device that may have a frame in flight when the
light changed), accumulates the per-pixel mean, temporal variance, maximum and the count of
frames in which each pixel sat at the top code, and yields a progress event per frame. A
camera error (a timeout, an overflow, a vanished device) becomes a :class:`CalibrationError`
that names the stage and the frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration.workflow import CalibrationError, Progress, Steps
from drivers.camera import Camera, CameraError, Frame, SourceEnded

__all__ = ["FrameStats", "acquire_frames", "full_scale_of", "robust_sigma"]


def full_scale_of(frame: Frame) -> int:
    """Top code of a frame's pixel format (saturation level)."""
    return (1 << int(frame.bit_depth)) - 1


@dataclass(frozen=True)
class FrameStats:
    """Per-pixel statistics of ``n`` frames (float64 arrays of the frame shape).

    ``std`` is the temporal standard deviation (ddof=1; zeros for one frame),
    ``saturated`` counts, per pixel, the frames in which it was at ``full_scale``.
    ``last`` is the last frame (its metadata describes the acquisition).
    """

    mean: np.ndarray
    std: np.ndarray
    max: np.ndarray
    saturated: np.ndarray
    n: int
    full_scale: int
    exposure_us: float | None
    gain: float | None
    last: Frame

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols)."""
        return (int(self.mean.shape[0]), int(self.mean.shape[1]))

    def saturated_pixels(self, exclude: np.ndarray | None = None) -> int:
        """Number of pixels saturated in at least one frame (``exclude``: a bad-pixel map)."""
        sat = self.saturated > 0
        if exclude is not None:
            sat &= ~exclude
        return int(sat.sum())

    def summary(self) -> dict[str, Any]:
        """Small JSON-friendly description."""
        return {
            "frames": self.n,
            "exposure_us": self.exposure_us,
            "gain": self.gain,
            "mean_level": float(np.median(self.mean)),
            "temporal_noise": float(np.median(self.std)),
        }


def acquire_frames(
    camera: Camera,
    n: int,
    *,
    stage: str,
    what: str,
    timeout_s: float = 5.0,
    settle: int = 0,
    fractions: tuple[float, float] = (0.0, 1.0),
    check: Callable[[], None] | None = None,
) -> Steps[FrameStats]:
    """Acquire ``n`` frames (after ``settle`` dropped ones) and return their statistics.

    Yields a :class:`Progress` (stage ``stage``) per frame, its fraction going from
    ``fractions[0]`` to ``fractions[1]``. ``what`` names the frames in messages
    ("dark frame", "PSF frame"). ``check`` (for example: the light source still answers) runs
    after every frame and raises to stop the step, so a vanished source is noticed within one
    frame time. The acquisition is stopped however the step ends.
    """
    if int(n) != n or n < 1:
        raise ValueError(f"number of frames must be an integer >= 1, got {n!r}")
    if int(settle) != settle or settle < 0:
        raise ValueError(f"settle frames must be an integer >= 0, got {settle!r}")
    n, settle = int(n), int(settle)
    f0, f1 = fractions
    total = n + settle
    acc: np.ndarray | None = None
    m2: np.ndarray | None = None
    mx: np.ndarray | None = None
    sat: np.ndarray | None = None
    last: Frame | None = None
    full_scale = 0
    got = 0
    try:
        camera.start_acquisition(n_frames=total, queue_size=total)
    except CameraError as exc:
        raise CalibrationError(
            f"{stage}: the camera could not start acquiring ({exc})",
            "Check that the camera is connected and not in use by another program",
            stage=stage,
        ) from exc
    try:
        for i in range(total):
            try:
                frame = camera.pop_frame(timeout_s)
            except SourceEnded as exc:  # a file source, never looped: its frames are all
                skipped = f", {settle} skipped first to settle" if settle else ""
                raise CalibrationError(
                    f"{stage}: the file source ended after {i} of the {total} frames this "
                    f"stage reads ({n} to average{skipped}) ({exc})",
                    "Ask for fewer frames (--frames, --darks) or record more; a file's frames "
                    "are never averaged twice; nothing was saved",
                    stage=stage,
                ) from exc
            except CameraError as exc:
                raise CalibrationError(
                    f"{stage}: the camera failed at {what} {max(i - settle, 0) + 1} of {n} ({exc})",
                    "Check the camera connection, trigger and exposure (a frame must arrive "
                    f"within {timeout_s:g} s), then run the calibration again; nothing was saved",
                    stage=stage,
                ) from exc
            if check is not None:
                check()
            if i < settle:
                continue
            px = np.asarray(frame.pixels)
            if px.ndim != 2:
                raise CalibrationError(
                    f"{stage}: expected monochrome frames, got shape {px.shape}",
                    "Set a Mono pixel format on the camera",
                    stage=stage,
                )
            x = px.astype(np.float64)
            if acc is None:
                acc = np.zeros_like(x)
                m2 = np.zeros_like(x)
                mx = np.full_like(x, -np.inf)
                sat = np.zeros(x.shape, dtype=np.int32)
                full_scale = full_scale_of(frame)
            elif x.shape != acc.shape:
                raise CalibrationError(
                    f"{stage}: frame shape changed from {acc.shape} to {x.shape}",
                    "Do not change the ROI or binning during a calibration",
                    stage=stage,
                )
            assert m2 is not None and mx is not None and sat is not None
            got += 1
            delta = x - acc
            acc += delta / got  # Welford: running mean and sum of squares
            m2 += delta * (x - acc)
            np.maximum(mx, x, out=mx)
            sat += px >= full_scale
            last = frame
            yield Progress(
                stage,
                f"{what} {got} of {n}",
                f0 + (f1 - f0) * got / n,
                frame=px,
                data={"frame": got, "of": n},
            )
    finally:
        camera.stop()
    assert acc is not None and m2 is not None and mx is not None and sat is not None
    assert last is not None
    std = np.sqrt(m2 / (got - 1)) if got > 1 else np.zeros_like(acc)
    return FrameStats(
        mean=acc,
        std=std,
        max=mx,
        saturated=sat,
        n=got,
        full_scale=full_scale,
        exposure_us=None if last.exposure_us is None else float(last.exposure_us),
        gain=None if last.gain is None else float(last.gain),
        last=last,
    )


def robust_sigma(a: np.ndarray) -> float:
    """Standard deviation estimated from the median absolute deviation (1.4826 MAD)."""
    v = np.asarray(a, dtype=np.float64).ravel()
    if v.size == 0:
        return 0.0
    med = float(np.median(v))
    return 1.4826 * float(np.median(np.abs(v - med)))
