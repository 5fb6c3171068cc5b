"""Checks of a raw PSF: constant or saturated (named, with numbers), and the detail it resolves.

The width of detail is :func:`autocorrelation_fwhm` (below). A diffuser PSF is a
high-contrast caustic: a constant image (a flat field, a dark frame, a
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
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from recon.inputwarnings import warn_input

__all__ = ["CONSTANT_RTOL", "ENVELOPE_SIGMA_FRACTION", "FLOOR_PERCENTILE", "FLOOR_WARN_SHARE",
           "PLATEAU_FRACTION", "PLATEAU_MIN", "PsfCheck", "PsfWarning", "autocorrelation_fwhm",
           "check_psf", "psf_floor"]

#: Relative spread under which a PSF counts as constant.
CONSTANT_RTOL = 1e-3
#: A flat top needs at least this many pixels at the maximum ...
PLATEAU_MIN = 8
#: ... and at least this fraction of all pixels.
PLATEAU_FRACTION = 1e-4


#: The floor of a raw PSF is this percentile of its values (a few dead or dark pixels, up to
#: 0.1 % of them, do not hide it); as for a measurement's black level.
FLOOR_PERCENTILE = 0.1
#: A raw (integer) PSF read with no dark level is warned about when a pedestal at its floor
#: would hold at least this share of its light (:func:`psf_floor`): that floor is a black
#: level (or ambient light), not the caustic. The physics: a diffuser caustic concentrates the
#: light, so its darkest pixels hold almost none of it. Even fully developed speckle (the
#: intensity of random interference, contrast std/mean = 1, exponential statistics) has its
#: 0.1th percentile at 0.1 % of its mean; caustics are of higher contrast still (the measured
#: PSFs at hand: 1.6-2.5). A floor at 5 % of the mean needs intensity statistics as smooth as
#: three independent speckle patterns added up (contrast 0.58, the 0.1th percentile of a
#: Gamma(3) at 6 % of its mean), no caustic. The real PSFs at hand sit far below it: the
#: DiffuserCam tutorial's raw uint16 frame, read without its dark level of 34 counts (x16
#: container: about 2 codes of its 12 bits), at 0.7 %; the 3D stack's planes at 0.1 %; the
#: MirFlickr PSF at 0. A black level costs dearly well before it holds a large share: a
#: simulated 12-bit PSF (tutorial caustic, 150x200) with the measurement's dark right and a
#: PSF pedestal holding 1.3 / 3.1 / 6.1 / 14 / 39 % of its light: 0.05 / 0.8 / 7.6 / 14.6 /
#: 20.4 dB below the pedestal-free reconstruction (``recon auto``: FISTA, tau by held-out
#: pixels, 500 iterations; 32.6 dB).
FLOOR_WARN_SHARE = 0.05


class PsfWarning(UserWarning):
    """A PSF is constant, saturated, or sits on a black level (see :func:`check_psf`)."""


def psf_floor(raw: npt.ArrayLike) -> tuple[float, float]:
    """(floor, share) of a raw PSF: its floor, and the share of its light a pedestal there holds.

    The floor is its :data:`FLOOR_PERCENTILE` th percentile; the share ``floor * n_pixels /
    sum`` (the floor over the PSF's mean). Non-finite values are ignored; (0, 0) when the PSF
    holds no light (sum <= 0).
    """
    vals = np.asarray(raw).astype(np.float64, copy=False).ravel()
    vals = vals[np.isfinite(vals)]
    total = float(vals.sum()) if vals.size else 0.0
    if not total > 0:
        return (0.0, 0.0)
    floor = float(np.percentile(vals, FLOOR_PERCENTILE))
    return (floor, max(0.0, floor) * vals.size / total)


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
        warn_input(check.message(name), PsfWarning, stacklevel=2)
    return check


# ---------------------------------------------------------------------------------------------
# resolution

#: A PSF's envelope is its local mean over a Gaussian of this fraction of the frame's smaller
#: side (sigma), removed before the autocorrelation. Caustic detail is a few pixels wide; the
#: envelope (vignetting, the caustic's extent on a padded grid) spans a good part of the frame.
ENVELOPE_SIGMA_FRACTION = 1.0 / 8.0


def _fwhm(profile: npt.NDArray[np.float64]) -> float:
    """Full width (interpolated) where a profile starting at 1 first falls below 0.5.

    NaN if it never does (the peak is wider than the frame).
    """
    below = np.flatnonzero(profile < 0.5)
    if below.size == 0 or below[0] == 0:
        return math.nan
    k = int(below[0])
    a, b = float(profile[k - 1]), float(profile[k])
    return 2.0 * (k - 1 + (a - 0.5) / max(a - b, 1e-12))


def autocorrelation_fwhm(psf: Any) -> tuple[float, float]:
    """(row, col) FWHM in pixels of the central peak of the PSF's autocorrelation.

    The one measure of the detail a PSF resolves (the planner's downsampling factor, the PSF
    calibration's quality report). Two points closer than this width give nearly the same
    caustic. The PSF's envelope is removed first: its mean and its local mean over a Gaussian
    of :data:`ENVELOPE_SIGMA_FRACTION` of the smaller side, structure at the scale of the
    frame that says nothing about detail and, left in, widens the peak to that scale (on the
    DiffuserCam MirFlickr PSF at 1/4 scale: 12.6 x 18.2 px with it, 3.5 x 4.8 px without). The
    autocorrelation is on a zero-padded grid, not circular. A peak wider than about a
    twentieth of the frame loses some of its tails with the envelope (a Gaussian of sigma
    2 px on a 64x64 frame: 6.0 px instead of 6.7). NaN where the PSF is constant or the peak
    does not fall to half within the frame.
    """
    a = np.asarray(psf, dtype=np.float64)
    if a.ndim != 2:
        raise ValueError(f"PSF must be (H, W), got shape {a.shape}")
    h, w = a.shape
    x = a - a.mean()
    spec = np.fft.rfft2(x, s=(2 * h, 2 * w))
    # the envelope's removal in the same transform: x minus its Gaussian blur is x times
    # (1 - the Gaussian's transfer function); a spatial filter this wide took 4x longer
    sigma = ENVELOPE_SIGMA_FRACTION * min(h, w)
    fy = np.fft.fftfreq(2 * h)[:, None]
    fx = np.fft.rfftfreq(2 * w)[None, :]
    spec *= 1.0 - np.exp(-2.0 * (math.pi * sigma) ** 2 * (fy * fy + fx * fx))
    ac = np.fft.irfft2(spec.real**2 + spec.imag**2, s=(2 * h, 2 * w))
    if not ac[0, 0] > 1e-12 * max(float(np.sum(a * a)), 1e-300):
        return (math.nan, math.nan)
    ac /= ac[0, 0]
    return (_fwhm(ac[:h, 0]), _fwhm(ac[0, :w]))
