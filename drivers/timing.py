"""Sensor timing model: when each row integrates, and the shutter function M_k it implies.

All times inside the model are integers in *line units* (one line time = the delay between
the starts of two successive rows of one rolling shutter), so the overlap of an exposure
window with a time bin is an exact integer count and no float slivers appear.

Readout patterns (for an H-row sensor):

- ``top-down``   (single rolling shutter): row r starts at r.
- ``outside-in`` (dual rolling shutter): rows 0 and H-1 start first, the two shutters move
  towards the centre: row r starts at min(r, H-1-r).
- ``centre-out`` (dual rolling shutter): the two centre rows start first and the shutters move
  outwards: row r starts at (H-1)//2 - min(r, H-1-r).
- ``global``: every row starts at 0.

Row r integrates over [t_r, t_r + E) with E the exposure in lines. With time bins of width w
lines, M_k[r] = |[t_r, t_r + E) ∩ [k w, (k+1) w)| / w, so sum_k M_k[r] = E / w.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from enum import Enum
from typing import Any

import numpy as np

__all__ = [
    "ReadoutPattern",
    "SensorTiming",
    "ShutterMode",
    "row_start_lines",
    "shutter_function",
]


class ShutterMode(str, Enum):
    """How the sensor exposes its rows."""

    GLOBAL = "global"
    ROLLING = "rolling"
    DUAL_ROLLING = "dual-rolling"


class ReadoutPattern(str, Enum):
    """Order in which rows start integrating."""

    TOP_DOWN = "top-down"
    OUTSIDE_IN = "outside-in"
    CENTRE_OUT = "centre-out"
    GLOBAL = "global"


@dataclass(frozen=True)
class SensorTiming:
    """Everything needed to rebuild a frame's shutter function.

    ``exposure_lines`` is the exposure in line units (an integer, >= 1);
    ``line_time_us`` converts line units to microseconds.
    """

    rows: int
    line_time_us: float
    exposure_lines: int
    pattern: ReadoutPattern = ReadoutPattern.OUTSIDE_IN
    trigger_delay_us: float = 0.0

    def __post_init__(self) -> None:
        if int(self.rows) != self.rows or self.rows < 1:
            raise ValueError(f"SensorTiming.rows must be a positive integer, got {self.rows!r}")
        if not (math.isfinite(self.line_time_us) and self.line_time_us > 0):
            raise ValueError(f"SensorTiming.line_time_us must be > 0, got {self.line_time_us!r}")
        if int(self.exposure_lines) != self.exposure_lines or self.exposure_lines < 1:
            raise ValueError(
                f"SensorTiming.exposure_lines must be an integer >= 1, got {self.exposure_lines!r}"
            )
        if not math.isfinite(self.trigger_delay_us) or self.trigger_delay_us < 0:
            raise ValueError(
                f"SensorTiming.trigger_delay_us must be >= 0, got {self.trigger_delay_us!r}"
            )
        object.__setattr__(self, "pattern", ReadoutPattern(self.pattern))

    @classmethod
    def from_exposure_us(
        cls,
        rows: int,
        line_time_us: float,
        exposure_us: float,
        pattern: ReadoutPattern | str = ReadoutPattern.OUTSIDE_IN,
        trigger_delay_us: float = 0.0,
    ) -> SensorTiming:
        """Build a timing from an exposure in microseconds (rounded to whole lines, >= 1)."""
        lines = max(1, round(exposure_us / line_time_us))
        return cls(rows, line_time_us, lines, ReadoutPattern(pattern), trigger_delay_us)

    @property
    def mode(self) -> ShutterMode:
        """The shutter mode this readout pattern implies."""
        if self.pattern is ReadoutPattern.GLOBAL:
            return ShutterMode.GLOBAL
        if self.pattern is ReadoutPattern.TOP_DOWN:
            return ShutterMode.ROLLING
        return ShutterMode.DUAL_ROLLING

    @property
    def exposure_us(self) -> float:
        """Exposure of one row in microseconds."""
        return self.exposure_lines * self.line_time_us

    @property
    def readout_lines(self) -> int:
        """Last row start, in lines (0 for a global shutter)."""
        return int(row_start_lines(self.rows, self.pattern).max())

    @property
    def frame_lines(self) -> int:
        """Time from the first row's start to the last row's end, in lines."""
        return self.readout_lines + self.exposure_lines

    @property
    def frame_time_us(self) -> float:
        """Time from the first row's start to the last row's end, in microseconds."""
        return self.frame_lines * self.line_time_us

    def row_start_us(self) -> np.ndarray:
        """Start of each row's exposure after the trigger, in microseconds."""
        return self.trigger_delay_us + row_start_lines(self.rows, self.pattern) * self.line_time_us

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form (for metadata)."""
        d = asdict(self)
        d["pattern"] = self.pattern.value
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SensorTiming:
        """Inverse of :meth:`to_dict`."""
        return cls(
            rows=int(d["rows"]),
            line_time_us=float(d["line_time_us"]),
            exposure_lines=int(d["exposure_lines"]),
            pattern=ReadoutPattern(d.get("pattern", ReadoutPattern.OUTSIDE_IN.value)),
            trigger_delay_us=float(d.get("trigger_delay_us", 0.0)),
        )

    def shutter(self, bin_lines: int, n_bins: int | None = None) -> np.ndarray:
        """Shutter function of this timing; see :func:`shutter_function`."""
        return shutter_function(self, bin_lines, n_bins)


def row_start_lines(rows: int, pattern: ReadoutPattern | str) -> np.ndarray:
    """Integer start time (in lines) of every row for a readout pattern."""
    pattern = ReadoutPattern(pattern)
    r = np.arange(rows, dtype=np.int64)
    if pattern is ReadoutPattern.TOP_DOWN:
        return r
    if pattern is ReadoutPattern.GLOBAL:
        return np.zeros(rows, dtype=np.int64)
    dist_to_edge = np.minimum(r, rows - 1 - r)
    if pattern is ReadoutPattern.OUTSIDE_IN:
        return dist_to_edge
    return (rows - 1) // 2 - dist_to_edge  # CENTRE_OUT


def shutter_function(timing: SensorTiming, bin_lines: int, n_bins: int | None = None) -> np.ndarray:
    """Shutter function M (K, rows), float64.

    M[k, r] is the overlap of row r's exposure window with time bin k (bins of ``bin_lines``
    lines starting at the first row's start), divided by the bin width. ``n_bins`` defaults to
    the number of bins that cover the whole frame; a smaller value drops the late bins.
    """
    if int(bin_lines) != bin_lines or bin_lines < 1:
        raise ValueError(f"bin_lines must be an integer >= 1, got {bin_lines!r}")
    starts = row_start_lines(timing.rows, timing.pattern)
    ends = starts + timing.exposure_lines
    k_total = -(-int(ends.max()) // bin_lines)  # ceil
    k = k_total if n_bins is None else int(n_bins)
    if k < 1:
        raise ValueError(f"n_bins must be >= 1, got {n_bins!r}")
    lo = np.arange(k, dtype=np.int64)[:, None] * bin_lines
    hi = lo + bin_lines
    overlap = np.clip(np.minimum(hi, ends[None, :]) - np.maximum(lo, starts[None, :]), 0, None)
    return overlap.astype(np.float64) / float(bin_lines)

