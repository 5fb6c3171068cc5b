"""Checks of lensless inputs: does a PSF fit a measurement, is a measurement saturated.

:func:`check_pair` (shapes of PSF and measurement), :func:`check_field` (a scene field no
larger than the light's reach) and :func:`check_measurement` (saturated, negative, non-finite
pixels, as a :class:`MeasurementCheck`). Pure numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from recon.inputwarnings import warn_input

__all__ = ["NEGATIVE_WARN_DEPTH", "NEGATIVE_WARN_FRACTION", "MeasurementCheck",
           "MeasurementWarning", "check_field", "check_measurement", "check_pair",
           "field_reach", "negative_measurement"]

Array = npt.NDArray[Any]

#: a measurement (dark subtracted) is warned about when more than this fraction of its
#: measured pixels lie below ``-NEGATIVE_WARN_DEPTH`` times its largest magnitude (see
#: :func:`negative_measurement`)
NEGATIVE_WARN_FRACTION = 0.05
#: how far below 0, relative to the measurement's largest magnitude, a pixel must be to count
#: for :data:`NEGATIVE_WARN_FRACTION`: read noise around a correct dark level stays within a
#: few % of the maximum
NEGATIVE_WARN_DEPTH = 0.05


def field_reach(sensor: tuple[int, int], psf_hw: tuple[int, int]) -> tuple[int, int]:
    """The largest scene field (H, W) from which light reaches a sensor through a PSF.

    A scene point reaches the sensor only through the PSF's extent, so the field beyond
    ``sensor + psf`` (in each direction) holds pixels that never reach it: for a PSF on the
    sensor grid twice the sensor (the ``full`` field), for a PSF on the padded grid (twice
    the sensor) three times it. Both in the same pixels (full resolution or one grid).
    """
    return (int(sensor[0]) + int(psf_hw[0]), int(sensor[1]) + int(psf_hw[1]))


def check_field(field: tuple[int, int], sensor: tuple[int, int], psf_hw: tuple[int, int],
                what: str = "scene field") -> None:
    """Refuse a field larger than :func:`field_reach`: ValueError, one line naming the limit.

    The one rule for ``--field``, ``--set field=HxW`` and a plan's field: such a field costs
    time and memory for pixels that cannot be reconstructed.
    """
    reach = field_reach(sensor, psf_hw)
    fld = (int(field[0]), int(field[1]))
    if fld[0] > reach[0] or fld[1] > reach[1]:
        raise ValueError(f"{what} {fld[0]}x{fld[1]} is larger than the {reach[0]}x{reach[1]} "
                         f"from which light reaches the {int(sensor[0])}x{int(sensor[1])} "
                         f"sensor through its {int(psf_hw[0])}x{int(psf_hw[1])} PSF: nothing "
                         "outside it can be reconstructed")


def check_pair(psf: Array, meas: Array, *, psf_is_stack: bool = False) -> None:
    """Check that a PSF (or PSF stack) fits a measurement; ValueError naming both shapes.

    Both are 3-axis: ``psf`` ``(C, H, W)`` (or ``(K, H, W)`` when ``psf_is_stack``), ``meas``
    ``(C, H, W)``. Height and width must be equal; a non-stack PSF must have one channel or as
    many channels as the measurement.
    """
    ps, ms = np.shape(psf), np.shape(meas)
    if len(ps) != 3 or len(ms) != 3:
        raise ValueError(
            f"PSF shape {ps} and measurement shape {ms}: both must have 3 axes "
            "(C, H, W) (PSF stack: (K, H, W))"
        )
    if ps[-2:] != ms[-2:]:
        raise ValueError(
            f"PSF shape {ps} and measurement shape {ms} do not match: the PSF must have the "
            f"measurement's height and width ({ms[1]}x{ms[2]}), it has {ps[1]}x{ps[2]}"
        )
    if not psf_is_stack and ps[0] not in (1, ms[0]):
        raise ValueError(
            f"PSF shape {ps} and measurement shape {ms} do not match: the PSF has {ps[0]} "
            f"channels, the measurement {ms[0]}"
        )


class MeasurementWarning(UserWarning):
    """A measurement has saturated, negative or no signal (see :func:`check_measurement`)."""


@dataclass(frozen=True)
class MeasurementCheck:
    """What :func:`check_measurement` found; ``flags`` is empty for a clean measurement.

    ``to_dict()`` is meant for the metadata of a reconstruction and its run record.
    """

    n_pixels: int
    full_scale: float | None
    saturated: int
    saturated_fraction: float
    negative: int
    negative_fraction: float
    nonfinite: int
    flags: tuple[str, ...]

    @property
    def flagged(self) -> bool:
        """True when something is worth a warning."""
        return bool(self.flags)

    def message(self) -> str:
        """One line for a log or a warning."""
        if not self.flags:
            return "measurement looks fine"
        parts = []
        if "saturated" in self.flags:
            parts.append(f"{self.saturated} pixels ({100 * self.saturated_fraction:.3g}%) are "
                         f"saturated (at or above full scale {self.full_scale:g}): the forward "
                         "model cannot explain them and the reconstruction near them is biased")
        if "negative" in self.flags:
            parts.append(f"{self.negative} pixels ({100 * self.negative_fraction:.3g}%) are "
                         "negative (dark subtraction); clip_nonneg() clips them")
        if "nonfinite" in self.flags:
            parts.append(f"{self.nonfinite} pixels are NaN or inf")
        if "all_zero" in self.flags:
            parts.append("every measured pixel is 0: the reconstruction is 0")
        return "; ".join(parts)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for metadata."""
        return {"n_pixels": self.n_pixels, "full_scale": self.full_scale,
                "saturated": self.saturated, "saturated_fraction": self.saturated_fraction,
                "negative": self.negative, "negative_fraction": self.negative_fraction,
                "nonfinite": self.nonfinite, "flags": list(self.flags)}


def check_measurement(
    b: Array,
    full_scale: float | None = None,
    *,
    bits: int | None = None,
    mask: Array | None = None,
    warn: bool = False,
) -> MeasurementCheck:
    """Count saturated, negative and non-finite pixels of a measurement and flag them.

    Pixels at or above ``full_scale`` count as saturated. Flags: ``saturated``, ``negative``,
    ``nonfinite``, ``all_zero``.

    Args:
        b: the measurement (any shape; raw counts or normalised).
        full_scale: the value at which the sensor saturates. Default: ``2**bits - 1`` when
            ``bits`` is given, else the maximum of an integer dtype (255 for uint8, 65535 for
            uint16); for float data without either, saturation is not checked.
        bits: the sensor's bit depth (a 12-bit camera in a uint16 container: ``bits=12``).
        mask: pixels to check (nonzero = measured, broadcast to ``b``); default all.
        warn: also emit a :class:`MeasurementWarning` when something is flagged.

    """
    arr = np.asarray(b)
    if arr.dtype.kind not in "fiub":
        raise ValueError(f"a measurement must be numeric, got dtype {arr.dtype}")
    if full_scale is None and bits is not None:
        if isinstance(bits, bool) or not isinstance(bits, int | np.integer) or bits < 1:
            raise ValueError(f"bits must be a positive integer, got {bits!r}")
        full_scale = float(2 ** int(bits) - 1)
    if full_scale is None and arr.dtype.kind in "iu":
        full_scale = float(np.iinfo(arr.dtype).max)
    if full_scale is not None and not (math.isfinite(full_scale) and full_scale > 0):
        raise ValueError(f"full_scale must be a finite number > 0, got {full_scale!r}")
    vals = arr.astype(np.float64, copy=False)
    if mask is not None:
        sel = np.broadcast_to(np.asarray(mask) != 0, arr.shape)
        vals = vals[sel]
    n = int(vals.size)
    finite = np.isfinite(vals)
    nonfinite = n - int(np.count_nonzero(finite))
    fv = vals[finite] if nonfinite else vals
    saturated = int(np.count_nonzero(fv >= full_scale)) if full_scale is not None else 0
    negative = int(np.count_nonzero(fv < 0))
    flags = []
    if saturated:
        flags.append("saturated")
    if negative:
        flags.append("negative")
    if nonfinite:
        flags.append("nonfinite")
    if n and not np.any(fv != 0) and not nonfinite:
        flags.append("all_zero")
    check = MeasurementCheck(n, None if full_scale is None else float(full_scale), saturated,
                             saturated / n if n else 0.0, negative, negative / n if n else 0.0,
                             nonfinite, tuple(flags))
    if warn and check.flagged:
        warn_input(check.message(), MeasurementWarning, stacklevel=2)
    return check


def negative_measurement(b: Array, mask: Array | None = None) -> str | None:
    """One line when a dark-subtracted measurement is negative in too many measured pixels.

    The rule: more than :data:`NEGATIVE_WARN_FRACTION` (5 %) of the measured, finite pixels
    are below ``-NEGATIVE_WARN_DEPTH`` (5 %) times the measurement's largest magnitude. Both
    parts are needed: after a correct dark level, the read noise of dark pixels puts many of
    them slightly below 0 (a sparse frame with noise of 1 % of its maximum: a third of its
    pixels negative, none below -5 %), which is harmless; a dark level above the sensor's
    black level (or a frame saved after subtracting one) puts a large share well below 0, and
    the clip to 0 that follows (``clip_nonneg``) flattens them, which the reconstruction
    fits as black (a simulated frame minus half its maximum: 55 % negative). A measurement
    with no positive pixel is not warned about here: the loaders refuse it ("all zero").
    None when the measurement passes.

    Args:
        b: the measurement after dark subtraction, before any clip (any shape, float).
        mask: measured pixels (nonzero), broadcast to ``b``; default all.

    """
    vals = np.asarray(b, dtype=np.float64)
    if mask is not None:
        vals = vals[np.broadcast_to(np.asarray(mask) != 0, vals.shape)]
    vals = vals[np.isfinite(vals)]
    if vals.size == 0:
        return None
    if float(vals.max()) <= 0:  # nothing left to reconstruct: an error, not a warning
        return None
    scale = float(np.max(np.abs(vals)))
    deep = int(np.count_nonzero(vals < -NEGATIVE_WARN_DEPTH * scale))
    if deep <= NEGATIVE_WARN_FRACTION * vals.size:
        return None
    negative = int(np.count_nonzero(vals < 0))
    n = int(vals.size)
    return (f"{100 * negative / n:.0f}% of its measured pixels are negative, "
            f"{100 * deep / n:.0f}% below -{100 * NEGATIVE_WARN_DEPTH:g}% of its largest "
            f"value (minimum {float(vals.min()):.4g}, maximum {float(vals.max()):.4g}): the "
            "dark level is likely above the sensor's black level (too large a dark, subtracted "
            "here or before the file was saved); they are clipped to 0 and the reconstruction "
            "fits them as black")
