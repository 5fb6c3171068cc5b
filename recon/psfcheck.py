"""Checks of a raw PSF before it is used: a constant or a saturated PSF is named, with numbers.

A diffuser PSF is a high-contrast caustic: a constant image (a flat field, a dark frame, a
file of one value) has no structure to invert, and a clipped peak (the sensor at full scale)
makes every reconstruction biased near bright points. Neither is an error (the user may know),
so :func:`check_psf` returns what it measured and, with ``warn=True``, emits one
:class:`PsfWarning` whose message gives the measured reason.

Rules (raw data, before dark subtraction and normalisation):

- **constant**: ``max - min <= CONSTANT_RTOL * max(|max|, |min|)`` (0.1 %), or every value equal;
- **saturated**: pixels at or above the full scale (``2**bits - 1`` when ``bits`` is given,
  the dtype's maximum for integer data), or, when no full scale is known or none reaches it,
  a flat top: at least ``max(PLATEAU_MIN, PLATEAU_FRACTION * n)`` pixels share the maximum
  value exactly (a real caustic peak is a single pixel or a few; a clipped one is a plateau;
  the DiffuserCam tutorial's ``psf_sample.tif`` has 192 pixels at 65520 = 4095 x 16, the
  12-bit full scale).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = ["CONSTANT_RTOL", "PLATEAU_FRACTION", "PLATEAU_MIN", "PsfCheck", "PsfWarning",
           "check_psf"]

#: Relative spread under which a PSF counts as constant.
CONSTANT_RTOL = 1e-3
#: A flat top needs at least this many pixels at the maximum ...
PLATEAU_MIN = 8
#: ... and at least this fraction of all pixels.
PLATEAU_FRACTION = 1e-4


class PsfWarning(UserWarning):
    """A PSF is constant or saturated (see :func:`check_psf`)."""


@dataclass(frozen=True)
class PsfCheck:
    """What :func:`check_psf` measured; ``flags`` is empty for a usable PSF."""

    n_pixels: int
    minimum: float
    maximum: float
    at_maximum: int
    full_scale: float | None
    saturated: int
    flags: tuple[str, ...]

    def message(self, name: str = "PSF") -> str:
        """One line with the measured reason."""
        parts = []
        if "constant" in self.flags:
            parts.append(f"{name} is constant: all {self.n_pixels} values lie in "
                         f"[{self.minimum:g}, {self.maximum:g}] (a diffuser PSF is a "
                         "high-contrast caustic; is this a flat or dark frame?)")
        if "saturated" in self.flags:
            if self.saturated:
                parts.append(f"{name} is saturated: {self.saturated} pixels "
                             f"({100 * self.saturated / self.n_pixels:.3g}%) at or above the "
                             f"full scale {self.full_scale:g}; capture it with a shorter "
                             "exposure")
            else:
                parts.append(f"{name} looks saturated: {self.at_maximum} pixels "
                             f"({100 * self.at_maximum / self.n_pixels:.3g}%) share the "
                             f"maximum value {self.maximum:g} exactly (a flat, clipped top); "
                             "capture it with a shorter exposure")
        return "; ".join(parts) if parts else f"{name} looks fine"

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for metadata."""
        return {"n_pixels": self.n_pixels, "min": self.minimum, "max": self.maximum,
                "at_maximum": self.at_maximum, "full_scale": self.full_scale,
                "saturated": self.saturated, "flags": list(self.flags)}


def check_psf(raw: npt.ArrayLike, *, bits: int | None = None, warn: bool = False,
              name: str = "PSF") -> PsfCheck:
    """Measure whether a raw PSF is constant or saturated (see the module docstring).

    Non-finite values are ignored here (the loaders refuse them with their own message).
    ``warn``: also emit a :class:`PsfWarning` when something is flagged; ``name`` (the file)
    starts its message.
    """
    arr = np.asarray(raw)
    if arr.dtype.kind not in "fiub":
        raise ValueError(f"a PSF must be numeric, got dtype {arr.dtype}")
    full_scale: float | None = None
    if bits is not None:
        if isinstance(bits, bool) or not isinstance(bits, int) or bits < 1:
            raise ValueError(f"bits must be a positive integer, got {bits!r}")
        full_scale = float(2**bits - 1)
    elif arr.dtype.kind in "iu":
        full_scale = float(np.iinfo(arr.dtype).max)
    vals = arr.astype(np.float64, copy=False).ravel()
    vals = vals[np.isfinite(vals)]
    n = int(vals.size)
    if n == 0:
        return PsfCheck(0, math.nan, math.nan, 0, full_scale, 0, ())
    lo, hi = float(vals.min()), float(vals.max())
    at_max = int(np.count_nonzero(vals == hi))
    saturated = int(np.count_nonzero(vals >= full_scale)) if full_scale is not None else 0
    flags = []
    if hi - lo <= CONSTANT_RTOL * max(abs(hi), abs(lo)):
        flags.append("constant")
    elif saturated or (hi > 0 and at_max >= max(PLATEAU_MIN, PLATEAU_FRACTION * n)):
        flags.append("saturated")
    check = PsfCheck(n, lo, hi, at_max, full_scale, saturated, tuple(flags))
    if warn and flags:
        warnings.warn(check.message(name), PsfWarning, stacklevel=2)
    return check
