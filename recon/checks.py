"""Checks of lensless inputs: does a PSF fit a measurement, is a measurement saturated.

:func:`check_pair` (shapes of PSF and measurement), :func:`check_field` (a scene field no
larger than the light's reach), :func:`check_measurement` (saturated, negative, non-finite
pixels, as a :class:`MeasurementCheck`), :func:`check_filter_cube` (the one rule for a
spectral filter cube's values), :func:`check_shutter` and :func:`check_shutter_frames` (the
rules for a video shutter function). Pure numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from recon.inputwarnings import warn_input
from recon.textfmt import percent

__all__ = [
    "FILTER_NEGATIVE_TOLERANCE",
    "NEGATIVE_PSF_WARN_SHARE",
    "NEGATIVE_WARN_DEPTH",
    "NEGATIVE_WARN_FRACTION",
    "MeasurementCheck",
    "MeasurementWarning",
    "check_field",
    "check_filter_cube",
    "check_measurement",
    "check_pair",
    "check_shutter",
    "check_shutter_frames",
    "downsample_remainder_text",
    "field_reach",
    "index_ranges",
    "negative_after_dark",
    "negative_measurement",
    "warn_downsample_remainder",
]

Array = npt.NDArray[Any]

#: a measurement (dark subtracted) is warned about when more than this fraction of its
#: measured pixels lie below ``-NEGATIVE_WARN_DEPTH`` times its largest magnitude (see
#: :func:`negative_measurement`)
NEGATIVE_WARN_FRACTION = 0.05
#: how far below 0, relative to the measurement's largest magnitude, a pixel must be to count
#: for :data:`NEGATIVE_WARN_FRACTION`: read noise around a correct dark level stays within a
#: few % of the maximum
NEGATIVE_WARN_DEPTH = 0.05
#: a PSF (dark subtracted) is warned about when more than :data:`NEGATIVE_WARN_FRACTION` of its
#: pixels are negative and they hold this share of the light of its positive ones or more (see
#: :func:`negative_after_dark`): the mirror of :data:`recon.psfcheck.FLOOR_WARN_SHARE`, a floor
#: holding that share of its light
NEGATIVE_PSF_WARN_SHARE = 0.05
#: a filter transmission below ``-FILTER_NEGATIVE_TOLERANCE`` times the cube's maximum is
#: refused (:func:`check_filter_cube`); smaller negative values (rounding) are clipped to 0
FILTER_NEGATIVE_TOLERANCE = 1e-6


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
    None when the measurement passes. :func:`negative_after_dark` (this, and the PSF's
    version: the share of its light below 0, not a depth against its peak).

    Args:
        b: the measurement after dark subtraction, before any clip (any shape, float).
        mask: measured pixels (nonzero), broadcast to ``b``; default all.

    """
    return negative_after_dark(b, mask)


def negative_after_dark(b: Array, mask: Array | None = None, *,
                        kind: str = "measurement") -> str | None:
    """The one check of values below 0 after a dark level, for a measurement or a PSF.

    One line (worded for ``kind``, ``'measurement'`` or ``'PSF'``) when more than
    :data:`NEGATIVE_WARN_FRACTION` (5 %) of the (measured, finite) pixels are negative *and*
    deep enough to matter, else None (also when no value is positive: the loaders refuse
    that). What is deep enough depends on what the clip at 0 that follows spoils:

    - a measurement: below ``-NEGATIVE_WARN_DEPTH`` (5 %) times its largest magnitude (its
      light is spread: read noise around a correct dark stays within a few % of the maximum;
      see :func:`negative_measurement`);
    - a PSF: its negative values together hold :data:`NEGATIVE_PSF_WARN_SHARE` (5 %) or more
      of the light of its positive ones. A caustic's peaks are 20-60 times its mean, so a
      depth relative to its maximum is blind to the harm: the tutorial caustic at 12 bits
      with its dark level 31 counts too high (half its mean; 48 % of its pixels negative, none
      below -1 % of its maximum) lost 5.9 dB, 100 too high 12.7 dB, both silent under the
      measurement's depth. Here they hold 9.5 % and more; read noise around a correct dark
      holds far less (the real DiffuserCam tutorial PSF with its dark of 34 counts: 0.03 %;
      noise of 15 % of a PSF's mean: 0.8 %). A PSF that is noise around 0 in its dark parts
      (a sparse simulated one) is said too: the clip then adds that light back as a floor.
    """
    if kind not in ("measurement", "PSF"):
        raise ValueError(f"kind must be 'measurement' or 'PSF', got {kind!r}")
    vals = np.asarray(b, dtype=np.float64)
    if mask is not None:
        vals = vals[np.broadcast_to(np.asarray(mask) != 0, vals.shape)]
    vals = vals[np.isfinite(vals)]
    if vals.size == 0:
        return None
    if float(vals.max()) <= 0:  # nothing left to reconstruct: an error, not a warning
        return None
    n = int(vals.size)
    negative = int(np.count_nonzero(vals < 0))
    span = f"(minimum {float(vals.min()):.4g}, maximum {float(vals.max()):.4g})"
    cause = ("the dark level is likely above the sensor's black level (too large a dark, "
             "subtracted here or before the file was saved)")
    if kind == "PSF":
        if negative <= NEGATIVE_WARN_FRACTION * n:
            return None
        share = float(-vals[vals < 0].sum() / vals[vals > 0].sum())
        if share < NEGATIVE_PSF_WARN_SHARE:
            return None
        light = (f"{share:.0f} times the light" if share >= 10 else
                 f"{100 * share:.0f}% of the light")
        return (f"{percent(negative, n, sep='')} of its pixels are negative, together "
                f"{light} of its positive ones {span}: {cause}, or "
                "it is noise around 0 in its dark parts; they are clipped to 0, a PSF the "
                "camera did not have (a PSF with a dark level of its own: --psf-dark N, "
                "psf_dark; 0 for a PSF saved dark-subtracted)")
    scale = float(np.max(np.abs(vals)))
    deep = int(np.count_nonzero(vals < -NEGATIVE_WARN_DEPTH * scale))
    if deep <= NEGATIVE_WARN_FRACTION * n:
        return None
    return (f"{percent(negative, n, sep='')} of its measured pixels are negative, "
            f"{percent(deep, n, sep='')} below -{100 * NEGATIVE_WARN_DEPTH:g}% of its largest "
            f"value {span}: {cause}; they are clipped to 0 and the reconstruction fits them "
            "as black")


def index_ranges(idx: Any, limit: int = 8) -> str:
    """Indices as compact ranges for a message: ``[0, 3-8, 12]`` (at most ``limit`` runs)."""
    vals = sorted(int(i) for i in np.asarray(idx).ravel())
    runs: list[tuple[int, int]] = []
    for v in vals:
        if runs and v == runs[-1][1] + 1:
            runs[-1] = (runs[-1][0], v)
        else:
            runs.append((v, v))
    text = [f"{a}" if a == b else f"{a}-{b}" for a, b in runs[:limit]]
    more = f", ... ({len(vals)} in all)" if len(runs) > limit else ""
    return "[" + ", ".join(text) + more + "]"


def check_filter_cube(cube: Array, what: str = "filter cube", *,
                      tolerance: float = FILTER_NEGATIVE_TOLERANCE) -> Array:
    """The one rule for a spectral filter cube's values; the cube with rounding clipped.

    ``cube`` is (K, H, W) (a band per transmission map). Used by ``lenslesscam calibrate
    filters`` (:func:`calibration.filters.validate_filter_cube`) and by the problem loader and
    ``simulate`` (:func:`recon.problem.read_filters`), so a cube that one refuses the other
    does too. Raises ValueError, one line naming ``what`` and the problem: NaN or infinite
    values; no positive transmission; negative transmissions (below ``-tolerance`` times the
    maximum: a filter cannot subtract light, and the measurement it simulates or explains is
    negative where no sensor can be); an all-zero band (the measurement holds nothing of it:
    its reconstruction would be the regulariser's fill alone). Negative values above
    ``-tolerance`` times the maximum are rounding: clipped to 0 in the cube returned (same
    dtype).
    """
    arr = np.asarray(cube)
    bad = int(np.count_nonzero(~np.isfinite(arr)))
    if bad:
        raise ValueError(f"{what} has {bad} NaN or infinite values")
    top = float(arr.max()) if arr.size else 0.0
    if not top > 0:
        raise ValueError(f"{what} is all zero or negative (maximum {top:g}): no band passes "
                         "any light")
    low = float(arr.min())
    if low < -tolerance * top:
        n_neg = int(np.count_nonzero(arr < -tolerance * top))
        raise ValueError(
            f"{what} has negative transmissions ({n_neg} values, {100 * n_neg / arr.size:.3g}% "
            f"of the cube; minimum {low:.3g}, maximum {top:.3g}): a transmission must be >= 0")
    out = np.maximum(arr, arr.dtype.type(0)) if low < 0 else arr
    flat = out.reshape(out.shape[0], -1) if out.ndim >= 2 else out.reshape(1, -1)
    empty = np.flatnonzero(~np.any(flat > 0, axis=1))
    if empty.size:
        raise ValueError(f"{what} bands {[int(k) for k in empty]} are all zero: the "
                         "measurement holds nothing of them (leave those bands out of the "
                         "cube)")
    return out


def check_shutter(m: Array, what: str = "shutter function", *,
                  rows_warning: bool = True) -> None:
    """The rules for a video shutter function M (K, rows) (finite and non-negative already).

    Raises ValueError, one line naming the bins, when a time bin is all zero: no row
    integrates light in it, so that frame of the video is not in the measurement and its
    reconstruction would be the regulariser's fill alone. With ``rows_warning``, rows that
    integrate no light in any bin (their pixels measure nothing of the scene) are named in a
    :class:`MeasurementWarning` (kept in a loaded problem's ``metadata['warnings']``).
    """
    arr = np.asarray(m)
    per_bin = np.any(arr > 0, axis=1)
    if not per_bin.all():
        empty = np.flatnonzero(~per_bin)
        raise ValueError(
            f"{what} has {empty.size} of its {arr.shape[0]} time bins all zero (bins "
            f"{index_ranges(empty)}): no row integrates light in them, so those frames are not "
            "in the measurement and cannot be reconstructed; use fewer bins (calibrate shutter "
            "--bin-lines larger, or leave the empty bins out)")
    if rows_warning:
        per_row = np.any(arr > 0, axis=0)
        if not per_row.all():
            dark = np.flatnonzero(~per_row)
            warn_input(f"{what}: {dark.size} of its {arr.shape[1]} rows integrate no light in "
                       f"any time bin (rows {index_ranges(dark)}): their pixels measure nothing "
                       "of the scene", MeasurementWarning, stacklevel=3)


def check_shutter_frames(k: int, rows: int, what: str = "shutter function", *,
                         downsample: int = 1) -> None:
    """Refuse more time bins than rows: ValueError, one line naming K and the rows.

    The measurement sees a scene pixel's K frames only through the shutter function's
    (K, rows) matrix, whose rank is at most ``rows``: more than ``rows`` frames cannot be told
    apart (the extra ones are fill), and they cost K convolutions per step (3000 bins on 75
    rows ran for minutes at 1.8 GB before the first iteration). ``downsample``: the factor
    that took the rows to ``rows`` (the message then suggests a smaller one too).
    """
    if int(k) > int(rows):
        less = (f", or a smaller downsampling factor than {int(downsample)}"
                if downsample > 1 else "")
        raise ValueError(
            f"{what} has K = {int(k)} time bins for {int(rows)} rows: a rolling shutter "
            f"resolves at most as many frames as rows; use fewer, wider bins (calibrate "
            f"shutter --bin-lines){less}")


def downsample_remainder_text(h: int, w: int, ds: int,
                              measured: Array | None = None) -> str | None:
    """What a downsampling factor that does not divide ``h`` x ``w`` drops, or None.

    Box downsampling keeps whole blocks, so the last ``h % ds`` rows and ``w % ds`` columns are
    not reconstructed. None when ``ds`` divides both, or when ``measured`` (an (h, w) mask,
    nonzero = measured) measures none of the dropped pixels (a padded grid's margin).
    """
    if ds <= 1 or not (h % ds or w % ds):
        return None
    if measured is not None:
        m = np.asarray(measured) != 0
        if not (m[h // ds * ds:].any() or m[:, w // ds * ds:].any()):
            return None
    lost = [f"{n} {kind}{'s' if n > 1 else ''}" for n, kind in
            ((h % ds, "row"), (w % ds, "column")) if n]
    return (f"downsampling {ds}x drops the last {' and '.join(lost)} of the {h}x{w} measurement "
            f"({ds} does not divide its size): the reconstruction sees "
            f"{h // ds * ds}x{w // ds * ds} of it")


def warn_downsample_remainder(h: int, w: int, ds: int,
                              measured: Array | None = None) -> None:
    """:func:`downsample_remainder_text` as a :class:`MeasurementWarning`, when there is one.

    For a factor the user chose (a bright edge in the dropped strip was lost unsaid).
    """
    text = downsample_remainder_text(h, w, ds, measured)
    if text is not None:
        warn_input(text, MeasurementWarning, stacklevel=2)
