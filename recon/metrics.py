"""Image quality metrics for reconstructions (numpy and scipy only).

Arrays of any shape whose last two axes are rows and columns: a scene ``(C, K, H, W)``, a
measurement ``(C, H, W)`` or one image ``(H, W)``. Structural metrics (SSIM, MS-SSIM) are
computed on each 2D slice and averaged over the slices. Everything is computed in float64.

Conventions, stated once:

- ``data_range`` (the ``L`` of PSNR and SSIM) defaults to ``ref.max() - ref.min()``, the
  dynamic range of the *reference*, so that a method cannot change its own score by changing
  its output range;
- SSIM follows Wang et al. 2004: Gaussian window of 11x11 taps, sigma 1.5, ``K1 = 0.01``,
  ``K2 = 0.03``, statistics over the "valid" part of the image (no padding), biased
  (population) variances;
- every score is computed on the arrays divided by a power of two near their largest
  magnitude (exact, :func:`_unit_scale`), so values up to float64's limits (1e300) neither
  overflow nor underflow in the squares; MSE is scaled back (``inf`` if it exceeds float64);
  SSIM's constants are kept within float64's range;
- MS-SSIM follows Wang et al. 2003: 5 scales, weights (0.0448, 0.2856, 0.3001, 0.2363,
  0.1333), 2x2 mean downsampling between scales; negative contrast-structure terms are clipped
  at 0 (as TensorFlow does) so the fractional powers stay defined. An image smaller than
  176 px (what 5 scales of the 11 px window need) is scored with fewer scales, the first n
  weights renormalised to sum 1 (:func:`ms_ssim_scales`); reports say how many were used
  (``ms_ssim_scales``), since scores with different scale counts are not comparable;
- a report (:func:`metrics_report`) refuses a constant reference (all zero included): there is
  nothing to score against, and after a gain fit an all-zero one scored every estimate as
  perfect. It says so instead of fitting a gain to an all-zero estimate (undefined: every gain
  scores the same; ``gain`` None, ``gain_note``), and it notes (``scale_note``) an unfitted
  estimate whose peak magnitude is more than :data:`SCALE_NOTE_FACTOR` times off the
  reference's (a 0..255 image against a 0..1 truth scores -40 dB for its units alone).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = [
    "MS_SSIM_WEIGHTS",
    "SCALE_NOTE_FACTOR",
    "SSIM_K1",
    "SSIM_K2",
    "SSIM_SIGMA",
    "SSIM_WIN",
    "gain_fit",
    "metrics_report",
    "ms_ssim",
    "ms_ssim_min_size",
    "ms_ssim_scales",
    "mse",
    "per_frame",
    "psnr",
    "spectral_cosine_distance",
    "ssim",
]

Array = npt.NDArray[Any]
F64 = npt.NDArray[np.float64]

SSIM_WIN = 11
SSIM_SIGMA = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03
MS_SSIM_WEIGHTS: tuple[float, ...] = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333)
#: an unfitted estimate whose peak magnitude is more than this factor above or below the
#: reference's gets a ``scale_note`` in :func:`metrics_report` (a reconstruction is often about
#: twice as bright as its truth; a 0..255 image against a 0..1 truth is 255 times)
SCALE_NOTE_FACTOR = 10.0


def _check(ref: Array, est: Array, *, min_ndim: int = 1) -> tuple[F64, F64]:
    r = np.asarray(ref)
    e = np.asarray(est)
    if r.shape != e.shape:
        raise ValueError(f"shapes differ: ref {r.shape} vs est {e.shape}")
    if r.ndim < min_ndim:
        raise ValueError(f"need at least {min_ndim} axes, got shape {r.shape}")
    if r.size == 0:
        raise ValueError(f"empty arrays (shape {r.shape})")
    for name, a in (("ref", r), ("est", e)):
        if a.dtype.kind not in "biuf":
            raise ValueError(f"{name} must be a real numeric array, got dtype {a.dtype}")
        if a.dtype.kind == "f":
            n_nan = int(np.count_nonzero(np.isnan(a)))
            if n_nan:
                raise ValueError(f"{name} contains {n_nan} NaN values")
            n_inf = int(np.count_nonzero(np.isinf(a)))
            if n_inf:
                raise ValueError(f"{name} contains {n_inf} infinite values")
    return r.astype(np.float64), e.astype(np.float64)


def _data_range(r: F64, data_range: float | None) -> float:
    if data_range is None:
        L = float(r.max() - r.min())
        if L <= 0:
            raise ValueError(
                "ref is constant, so its range (the default data_range, ref.max() - ref.min()) "
                "is 0; pass data_range explicitly"
            )
        return L
    L = float(data_range)
    if not math.isfinite(L) or L <= 0:
        raise ValueError(f"data_range must be positive and finite, got {data_range}")
    return L


def _unit_scale(*arrays: F64) -> float:
    """A power of two near the largest magnitude in ``arrays`` (1.0 when all are 0).

    Dividing by it is exact and brings the values near 1, so their squares and products stay
    within float64 (at 1e300 they overflowed, at 1e-300 they underflowed).
    """
    top = max(float(np.max(np.abs(a))) for a in arrays)
    if top == 0.0 or not math.isfinite(top):
        return 1.0
    return math.ldexp(1.0, math.frexp(top)[1])


def _scaled_mse(r: F64, e: F64) -> tuple[float, float]:
    """(MSE of r/s and e/s, s) with s = :func:`_unit_scale`; the MSE is that times s^2."""
    s = _unit_scale(r, e)
    d = (r - e) if s == 1.0 else (r / s - e / s)
    return float(np.mean(d * d)), s


def mse(ref: Array, est: Array) -> float:
    """Mean squared error (``inf`` when it exceeds float64's range)."""
    r, e = _check(ref, est)
    err, s = _scaled_mse(r, e)
    return err * s * s


def psnr(ref: Array, est: Array, data_range: float | None = None) -> float:
    """Peak signal-to-noise ratio in dB: ``10 log10(L^2 / MSE)``; ``inf`` for equal arrays.

    ``L = data_range``, by default ``ref.max() - ref.min()``.
    """
    r, e = _check(ref, est)
    L = _data_range(r, data_range)
    err, s = _scaled_mse(r, e)
    if err == 0.0:
        return math.inf
    return 20.0 * (math.log10(L) - math.log10(s)) - 10.0 * math.log10(err)


def _gauss_window() -> F64:
    x = np.arange(SSIM_WIN, dtype=np.float64) - (SSIM_WIN - 1) / 2.0
    g = np.exp(-(x**2) / (2.0 * SSIM_SIGMA**2))
    return np.asarray(g / g.sum())


def _filter_valid(a: F64, g: F64) -> F64:
    """Separable correlation of the last two axes with ``g``, 'valid' part only."""
    from scipy.ndimage import correlate1d

    n = g.size
    r = n // 2
    out = correlate1d(a, g, axis=-1, mode="constant")
    out = correlate1d(out, g, axis=-2, mode="constant")
    h, w = a.shape[-2], a.shape[-1]
    return np.asarray(out[..., r : h - (n - 1 - r), r : w - (n - 1 - r)])


def _ssim_terms(r: F64, e: F64, L: float) -> tuple[F64, F64]:
    """Per-slice mean luminance term and mean contrast-structure term (shape r.shape[:-2])."""
    g = _gauss_window()
    # within float64's range (an extreme data range against the values: the limits, 1 and 1)
    tiny, big = float(np.finfo(np.float64).tiny), float(np.finfo(np.float64).max)
    c1 = min(max((SSIM_K1 * L) * (SSIM_K1 * L), tiny), big)
    c2 = min(max((SSIM_K2 * L) * (SSIM_K2 * L), tiny), big)
    mu_r = _filter_valid(r, g)
    mu_e = _filter_valid(e, g)
    rr = _filter_valid(r * r, g) - mu_r * mu_r
    ee = _filter_valid(e * e, g) - mu_e * mu_e
    re = _filter_valid(r * e, g) - mu_r * mu_e
    lum = (2.0 * mu_r * mu_e + c1) / (mu_r * mu_r + mu_e * mu_e + c1)
    cs = (2.0 * re + c2) / (rr + ee + c2)
    return np.asarray(lum * cs), np.asarray(cs)


def _check_size(shape: tuple[int, ...], need: int, what: str) -> None:
    h, w = shape[-2], shape[-1]
    if h < need or w < need:
        raise ValueError(f"{what}: image {h}x{w} is smaller than {need}x{need}")


def ssim(ref: Array, est: Array, data_range: float | None = None) -> float:
    """Structural similarity (Wang et al. 2004), mean over pixels and over 2D slices.

    Gaussian window 11x11, sigma 1.5, K1 = 0.01, K2 = 0.03; ``data_range`` defaults to
    ``ref.max() - ref.min()``. Symmetric in its arguments for a fixed ``data_range``.
    """
    r, e = _check(ref, est, min_ndim=2)
    _check_size(r.shape, SSIM_WIN, f"SSIM needs the {SSIM_WIN}x{SSIM_WIN} window")
    L = _data_range(r, data_range)
    sc = _unit_scale(r, e)
    full, _ = _ssim_terms(r / sc, e / sc, L / sc)
    return float(full.mean(axis=(-2, -1)).mean())


def ms_ssim_min_size(scales: int = len(MS_SSIM_WEIGHTS)) -> int:
    """Smallest height/width for which :func:`ms_ssim` is defined (176 for 5 scales)."""
    return int(SSIM_WIN * 2 ** (scales - 1))


def ms_ssim_scales(shape: tuple[int, ...], most: int = len(MS_SSIM_WEIGHTS)) -> int:
    """The most scales (at most ``most``, at least 2) an image of ``shape`` allows; 0: none.

    Scale j needs the 11 px window on an image halved j - 1 times: 176 px for 5 scales, 88 for
    4, 44 for 3, 22 for 2. Below 22 px there is no multi-scale score (use SSIM).
    """
    side = min(int(shape[-2]), int(shape[-1]))
    for n in range(min(most, len(MS_SSIM_WEIGHTS)), 1, -1):
        if side >= ms_ssim_min_size(n):
            return n
    return 0


def _half(a: F64) -> F64:
    h, w = a.shape[-2] // 2, a.shape[-1] // 2
    b = a[..., : 2 * h, : 2 * w].reshape(*a.shape[:-2], h, 2, w, 2)
    return np.asarray(b.mean(axis=(-3, -1)))


def ms_ssim(ref: Array, est: Array, data_range: float | None = None,
            scales: int = len(MS_SSIM_WEIGHTS)) -> float:
    """Multi-scale SSIM (Wang et al. 2003), ``scales`` scales (5), averaged over 2D slices.

    ``prod_j cs_j ** w_j`` over the first ``scales - 1`` scales times ``(l * cs) ** w_n`` at
    the coarsest, with the standard weights (the first ``scales`` of them renormalised to sum 1
    when ``scales < 5``); each slice is scored separately and the scores are averaged. Raises
    ValueError when an image is smaller than :func:`ms_ssim_min_size` of ``scales`` (176 for
    5) in height or width.
    """
    r, e = _check(ref, est, min_ndim=2)
    n = int(scales)
    if not 2 <= n <= len(MS_SSIM_WEIGHTS):
        raise ValueError(f"MS-SSIM scales must be 2..{len(MS_SSIM_WEIGHTS)}, got {scales!r}")
    weights = MS_SSIM_WEIGHTS[:n]
    if n < len(MS_SSIM_WEIGHTS):
        total = sum(weights)
        weights = tuple(w / total for w in weights)
    _check_size(
        r.shape,
        ms_ssim_min_size(n),
        f"MS-SSIM needs {n} scales of the {SSIM_WIN}x{SSIM_WIN} window",
    )
    L = _data_range(r, data_range)
    sc = _unit_scale(r, e)
    r2 = r.reshape(-1, r.shape[-2], r.shape[-1]) / sc
    e2 = e.reshape(-1, e.shape[-2], e.shape[-1]) / sc
    L = L / sc
    score = np.ones(r2.shape[0], dtype=np.float64)
    for j, w in enumerate(weights):
        full, cs = _ssim_terms(r2, e2, L)
        term = (full if j == n - 1 else cs).mean(axis=(-2, -1))
        score *= np.maximum(term, 0.0) ** w
        if j < n - 1:
            r2, e2 = _half(r2), _half(e2)
    return float(score.mean())


def gain_fit(ref: Array, est: Array) -> tuple[Array, float]:
    """Least-squares gain: ``g = <ref, est> / <est, est>``; returns ``(g * est, g)``.

    The scale of a reconstruction is often arbitrary (a unit-sum PSF and a max-1 measurement
    make the recovered scene about twice as bright as the truth), so scores are taken after
    this fit when stated. An all-zero ``est`` gives ``g = 1`` (no gain is defined there;
    :func:`metrics_report` reports none). The scaled estimate keeps
    ``est``'s float dtype (float64 for integer input).
    """
    r, e = _check(ref, est)
    sr, se = _unit_scale(r), _unit_scale(e)  # each near 1: the dot products stay finite
    e1 = e / se
    den = float(np.vdot(e1, e1))
    g = 1.0 if den == 0.0 else float(np.vdot(r / sr, e1)) / den * (sr / se)
    e_in = np.asarray(est)
    dtype = e_in.dtype if e_in.dtype.kind == "f" else np.dtype(np.float64)
    return np.asarray(e * g, dtype=dtype), g


_gain = gain_fit  # ``metrics_report``'s ``gain_fit`` argument shadows the function
_NAMED: dict[str, Callable[[Array, Array], float]] = {"mse": mse, "psnr": psnr, "ssim": ssim}


def per_frame(ref: Array, est: Array, metric: str | Callable[[Array, Array], float]) -> list[float]:
    """Score each frame ``k`` of ``(C, K, H, W)`` arrays: ``metric(ref[:, k], est[:, k])``.

    ``metric`` is a callable or one of ``'mse'``, ``'psnr'``, ``'ssim'`` (each frame then uses
    its own default ``data_range``; pass a ``functools.partial`` to fix one).
    """
    r, e = np.asarray(ref), np.asarray(est)
    if r.shape != e.shape:
        raise ValueError(f"shapes differ: ref {r.shape} vs est {e.shape}")
    if r.ndim != 4:
        raise ValueError(f"per_frame expects (C, K, H, W) arrays, got shape {r.shape}")
    if isinstance(metric, str):
        if metric not in _NAMED:
            raise ValueError(f"unknown metric {metric!r}; choose from {', '.join(_NAMED)}")
        fn = _NAMED[metric]
    else:
        fn = metric
    return [float(fn(r[:, k], e[:, k])) for k in range(r.shape[1])]


def spectral_cosine_distance(ref: Array, est: Array, axis: int | None = None) -> float:
    """Mean over pixels of ``1 - cos(angle)`` between the spectra of ``ref`` and ``est``.

    Spectra run along ``axis``: by default axis 1 of a ``(C, K, H, W)`` cube, axis 0 of a
    ``(K, H, W)`` cube. Pixels where either spectrum is all zero have no angle and are left
    out of the mean; ValueError if no pixel is left.
    """
    r, e = _check(ref, est, min_ndim=3)
    r, e = r / _unit_scale(r), e / _unit_scale(e)  # the angle does not change; the squares fit
    if axis is None:
        if r.ndim == 4:
            axis = 1
        elif r.ndim == 3:
            axis = 0
        else:
            raise ValueError(f"give the spectral axis for an array of shape {r.shape}")
    dot = np.sum(r * e, axis=axis)
    nr = np.sqrt(np.sum(r * r, axis=axis))
    ne = np.sqrt(np.sum(e * e, axis=axis))
    ok = (nr > 0) & (ne > 0)
    if not np.any(ok):
        raise ValueError("spectral_cosine_distance: every pixel has an all-zero spectrum")
    cos = np.clip(dot[ok] / (nr[ok] * ne[ok]), -1.0, 1.0)
    return float(np.mean(1.0 - cos))


def metrics_report(
    ref: Array, est: Array, gain_fit: bool = False, data_range: float | None = None
) -> dict[str, Any]:
    """All standard scores of ``est`` against ``ref`` as a JSON-ready dict.

    Keys: ``mse``, ``psnr``, ``ssim``, ``ms_ssim`` with ``ms_ssim_scales`` (fewer than 5 for
    images under 176 px, with ``ms_ssim_note``; ``None`` and 0 below 22 px), ``gain`` (1.0
    without a fit), ``gain_fit`` (whether ``est``
    was scaled by the least-squares gain before scoring), ``data_range`` and
    ``data_range_source``, ``shape``. ``psnr`` is ``inf`` for identical arrays.

    An all-zero ``ref`` is refused (ValueError): nothing to score against (a gain fit scored
    every estimate perfect against it); so is another constant one without a ``data_range``
    (its range, the default, is 0). A constant non-zero ``ref`` with a ``data_range`` (a
    flat-field target) is scored.
    With ``gain_fit`` and an all-zero ``est`` no gain is fitted (none is defined; every gain
    scores the same): ``gain`` None, ``gain_fit`` False and ``gain_note`` say so. Without
    ``gain_fit``, peak magnitudes more than :data:`SCALE_NOTE_FACTOR` apart add ``scale_note``.
    """
    r, e = _check(ref, est, min_ndim=2)
    lo, hi = float(r.min()), float(r.max())
    if lo == hi and (lo == 0 or data_range is None):
        how = "" if lo == 0 else " and no data range was given (its range, the default, is 0)"
        raise ValueError(f"ref is constant (every value is {lo:g}){how}: nothing to score "
                         "against")
    g: float | None = 1.0
    fitted = False
    notes: dict[str, str] = {}
    if gain_fit and not np.any(e):
        g = None
        notes["gain_note"] = ("no gain fitted: est is all zero, so no least-squares gain is "
                              "defined (every gain scores the same); scored as it is")
    elif gain_fit:
        e, g = _gain(r, e)
        fitted = True
    else:
        note = _scale_note(r, e)
        if note:
            notes["scale_note"] = note
    L = _data_range(r, data_range)
    report: dict[str, Any] = {
        "mse": mse(r, e),
        "psnr": psnr(r, e, L),
        "ssim": ssim(r, e, L) if min(r.shape[-2:]) >= SSIM_WIN else None,
    }
    if report["ssim"] is None:
        report["ssim_note"] = (
            f"not computed, image {r.shape[-2]}x{r.shape[-1]} smaller than the "
            f"{SSIM_WIN}x{SSIM_WIN} window"
        )
    n = ms_ssim_scales(r.shape)
    full_n = len(MS_SSIM_WEIGHTS)
    report["ms_ssim"] = ms_ssim(r, e, L, scales=n) if n else None
    report["ms_ssim_scales"] = n
    if n == 0:
        need = ms_ssim_min_size(2)
        report["ms_ssim_note"] = (
            f"not computed, image {r.shape[-2]}x{r.shape[-1]} smaller than {need}x{need} "
            "(2 scales)"
        )
    elif n < full_n:
        need = ms_ssim_min_size(full_n)
        report["ms_ssim_note"] = (
            f"{n} scales, not {full_n}: image {r.shape[-2]}x{r.shape[-1]} smaller than "
            f"{need}x{need}; weights of the first {n} renormalised (compare only with "
            f"{n}-scale scores)"
        )
    report.update(
        {
            "gain": g,
            "gain_fit": fitted,
            "data_range": L,
            "data_range_source": "given" if data_range is not None else "ref.max() - ref.min()",
            "shape": list(r.shape),
            **notes,
        }
    )
    return report


def _scale_note(r: F64, e: F64) -> str | None:
    """A note when the peak magnitudes of ``r`` and ``e`` are far apart (None: they are not).

    More than :data:`SCALE_NOTE_FACTOR` apart, compared as logarithms (no overflow at 1e300);
    an all-zero ``e`` has no scale to compare.
    """
    pr, pe = float(np.max(np.abs(r))), float(np.max(np.abs(e)))
    if pr == 0.0 or pe == 0.0:
        return None
    apart = abs(math.log10(pe) - math.log10(pr))
    if apart <= math.log10(SCALE_NOTE_FACTOR):
        return None
    factor = f"{10.0 ** apart:.3g}" if apart < 300 else f"1e{apart:.0f}"
    return (f"est's values reach {pe:.4g} and ref's {pr:.4g} ({factor} times "
            f"{'larger' if pe > pr else 'smaller'}): the scores compare different scales; "
            "a gain fit (--gain-fit) scores est after the least-squares gain")
