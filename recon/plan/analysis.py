"""Scene analysis: what a measurement and its calibration support, measured on the data.

Four questions, each answered by a small computation whose numbers are kept as evidence:

- **Resolution** (:func:`psf_resolution`): the width of the PSF's autocorrelation peak is the
  smallest detail the camera separates (two points closer than that give nearly the same
  caustic). Sampling that at two pixels per width gives the downsampling factor
  ``floor(FWHM / 2)`` (the narrower axis decides, so no axis loses detail). The PSF's envelope
  (vignetting, the caustic's extent on a padded grid) is removed first: it is structure at
  the scale of the frame, not detail, and left in it raises the peak's width to that scale.
- **Extent** (:func:`scene_extent`): a cheap low-resolution 2D reconstruction of the whole
  field; the bounding box of its energy (smoothed, above a fraction of its peak) plus a margin
  is the region to reconstruct.
- **Time** (:func:`time_scale`): for a rolling-shutter measurement, K-fold cross-validation on
  held-out sensor pixels. Each candidate model (2D, then video models with the shutter function
  binned to K = 2, 3, 4, 6, ... time bins) is fitted on the other pixels and predicts the held-out
  ones. A model that cannot represent the motion predicts worse; a model finer than the motion
  predicts no better. Motion is declared when the 2D model predicts clearly worse than the best
  video model (by more than the spread seen between models on static scenes); K is then the
  smallest video K whose held-out error is not significantly worse than the best (paired
  z-test over pixels, or within a relative tolerance).
- **Depth** (:func:`depth_extent`): the same cross-validation over subsets of a PSF stack:
  the single plane that holds most of the energy (a 2D model) against ranges of planes.

The video candidates use the shutter function normalised so every row's bins sum to about 1
(then a static scene has the same values in every frame as in the 2D model), a per-frame TV
weight ``tau / K`` and a TV weight along time ``lambda_t * K``. With these, a static video costs
the same objective as its 2D image and a temporal edge costs the same for any K, so the
comparison between K measures the data and not the scaling of the prior.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import torch

from recon.fista import Fista
from recon.models import ForwardModel
from recon.plan.roi import Region, build_region_model
from recon.preprocess import bin_time
from recon.psfcheck import autocorrelation_fwhm
from recon.tv import TV

__all__ = [
    "ANALYSIS_TAU",
    "LAMBDA_T",
    "CVCandidate",
    "DepthExtent",
    "Extent",
    "Resolution",
    "TimeScale",
    "cv_select",
    "depth_extent",
    "heldout_folds",
    "normalised_shutter",
    "psf_resolution",
    "scene_extent",
    "time_scale",
    "video_tv",
]

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

#: TV weight of the analysis fits (measurement scaled to max 1): weak, so that the held-out
#: error measures the model rather than the prior's bias.
ANALYSIS_TAU = 1e-4
#: TV weight along time per unit of the whole exposure (see the module docstring).
LAMBDA_T = 0.1


# ---------------------------------------------------------------------------------------------
# resolution


@dataclass(frozen=True)
class Resolution:
    """Autocorrelation width of the PSF (pixels, full width at half maximum) and the factor."""

    fwhm_y: float
    fwhm_x: float
    factor: int
    limited_by: str

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {"acf_fwhm_px": [round(self.fwhm_y, 2), round(self.fwhm_x, 2)],
                "factor": self.factor, "limited_by": self.limited_by}


def psf_resolution(psf: Any, *, max_factor: int = 8, min_size: int = 16,
                   sensor: tuple[int, int] | None = None) -> Resolution:
    """Downsampling factor the PSF supports: ``floor(min(FWHM_y, FWHM_x) / 2)`` of its ACF.

    The width is :func:`recon.psfcheck.autocorrelation_fwhm` (the PSF's envelope removed: on
    the DiffuserCam MirFlickr PSF at 1/4 scale the envelope alone made the peak 12.6 px wide
    where its caustics are 3.5 px). The factor is capped at ``max_factor`` and so that the
    downsampled sensor keeps ``min_size`` rows and columns; ``sensor`` is the sensor's size
    when the PSF lies on a larger (padded) grid, or the scene field's size (default: the
    PSF's size).
    """
    p = np.asarray(psf, dtype=np.float64)
    if p.ndim == 3:
        p = p.mean(axis=0)
    if p.ndim != 2:
        raise ValueError(f"PSF must be (H, W) or (C, H, W), got shape {p.shape}")
    h, w = p.shape
    if float(p.max() - p.min()) == 0.0:
        raise ValueError("the PSF is constant: it carries no structure to reconstruct with")
    fy, fx = autocorrelation_fwhm(p)
    # NaN: no half-maximum within the frame, the peak is as wide as the frame (then capped)
    fy = float(2 * h) if math.isnan(fy) else fy
    fx = float(2 * w) if math.isnan(fx) else fx
    factor = max(1, math.floor(min(fy, fx) / 2.0))
    limited_by = "autocorrelation width"
    sh, sw = (h, w) if sensor is None else (min(h, int(sensor[0])), min(w, int(sensor[1])))
    cap = max(1, min(max_factor, sh // min_size, sw // min_size))
    if factor > cap:
        factor, limited_by = cap, f"sensor size (keep >= {min_size} px) or max_factor"
    return Resolution(fy, fx, factor, limited_by)


# ---------------------------------------------------------------------------------------------
# cross-validation machinery


def heldout_folds(shape: tuple[int, int], folds: int, seed: int = 0) -> list[npt.NDArray[np.bool_]]:
    """A random partition of the (H, W) pixels into ``folds`` held-out masks."""
    if folds < 2:
        raise ValueError(f"cross-validation needs at least 2 folds, got {folds}")
    n = shape[0] * shape[1]
    labels = np.random.default_rng(seed).permutation(n) % folds
    return [(labels == f).reshape(shape) for f in range(folds)]


@dataclass(frozen=True)
class CVCandidate:
    """One candidate model's held-out score.

    ``rel`` is its held-out MSE relative to the best candidate's minus 1; ``z`` the paired
    z-score of the per-pixel difference to the best (0 for the best itself).
    """

    label: str
    k: int
    heldout_mse: float
    rel: float
    z: float
    info: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {"label": self.label, "k": self.k, "heldout_mse": float(f"{self.heldout_mse:.4g}"),
                "rel": round(self.rel, 4), "z": round(self.z, 2), **self.info}


def _fit(model: ForwardModel, b: torch.Tensor, tau: float, tv: TV, iters: int,
         x0: torch.Tensor | None) -> torch.Tensor:
    # plain steps: the analysis compares candidates on short, fixed-budget fits (100-150
    # iterations), the video ones warm-started from 2D pilots (which FISTA's "auto" leaves
    # plain), with thresholds set on plain runs; every candidate takes the same kind of step
    solver = Fista(model.op, b, tau=tau, tv=tv, max_iter=iters, tol=1e-6, x0=x0,
                   precondition="off")
    return solver.run().x


def _pixel_errors(
    build: Callable[[Any], ForwardModel],
    b: F32,
    folds: Sequence[npt.NDArray[np.bool_]],
    tau: float,
    tv: TV,
    iters: int,
    x0: Callable[[int], torch.Tensor | None],
    measured: npt.NDArray[np.bool_] | None = None,
) -> F64:
    """Squared held-out errors of the measured pixels (flattened).

    Each pixel is predicted by the fit of the fold that held it out.
    """
    ok = np.ones(b.shape, dtype=bool) if measured is None else measured
    err = np.zeros(b.shape, dtype=np.float64)
    bt = torch.as_tensor(b[None])
    full = build(None)
    for i, held in enumerate(folds):
        train = ((~held) & ok).astype(np.float32)
        model = build(train)
        x = _fit(model, bt * torch.as_tensor(train), tau, tv, iters, x0(i))
        with torch.no_grad():
            pred = full.apply(x)[0].double().numpy()
        err[held] = (pred[held] - b[held]) ** 2
    return np.asarray(err[ok])


def cv_select(errors: Sequence[tuple[str, int, F64, dict[str, Any]]], *, z_max: float = 2.0,
              rel_tol: float = 0.05) -> tuple[int, list[CVCandidate]]:
    """Index of the simplest candidate not significantly worse than the best, and the table.

    Candidates are given simplest first. "Not significantly worse": the paired z-score of the
    per-pixel error difference to the best is at most ``z_max``, or the held-out MSE is within
    ``rel_tol`` of the best's (residuals of neighbouring pixels are correlated, so the z-test
    alone is too eager to call small differences real).
    """
    if not errors:
        raise ValueError("no candidates")
    mses = [float(e.mean()) for _, _, e, _ in errors]
    best = int(np.argmin(mses))
    e_best = errors[best][2].ravel()
    table: list[CVCandidate] = []
    for (label, k, e, info), m in zip(errors, mses, strict=True):
        d = e.ravel() - e_best
        se = float(d.std()) / math.sqrt(d.size)
        z = float(d.mean()) / se if se > 0 else 0.0
        rel = m / mses[best] - 1.0 if mses[best] > 0 else 0.0
        table.append(CVCandidate(label, k, m, rel, z, dict(info)))
    chosen = next(i for i, c in enumerate(table) if c.z <= z_max or c.rel <= rel_tol)
    return chosen, table


# ---------------------------------------------------------------------------------------------
# extent


@dataclass(frozen=True)
class Extent:
    """Where the scene's energy lies in the field (full-resolution field pixels)."""

    region: Region
    bbox: Region
    energy_fraction: float
    cropped: bool
    preview: F32 = field(repr=False, compare=False)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (without the preview)."""
        return {"bbox": self.bbox.to_list(), "region": self.region.to_list(),
                "energy_in_region": round(self.energy_fraction, 4),
                "area_fraction": round(self.region.area_fraction, 4), "cropped": self.cropped}


def _smooth3(x: F64) -> F64:
    """3x3 box mean with edge replication."""
    p = np.pad(x, 1, mode="edge")
    out = np.zeros_like(x)
    for dy in range(3):
        for dx in range(3):
            out += p[dy:dy + x.shape[0], dx:dx + x.shape[1]]
    return out / 9.0


def scene_extent(
    psf: F32,
    b_a: F32,
    field: tuple[int, int],
    factor: int,
    *,
    threshold: float = 0.05,
    margin: float = 0.15,
    min_margin_px: int = 4,
    max_area: float = 0.6,
    iters: int = 100,
    tau: float = ANALYSIS_TAU,
    measured: npt.NDArray[np.bool_] | None = None,
) -> Extent:
    """Region of ``field`` (full-resolution pixels) that holds the scene.

    ``psf`` is at full resolution, ``b_a`` the measurement box-downsampled by ``factor`` (the
    analysis grid, where the exact coarse model is used). A 2D reconstruction of the whole
    field at that grid is smoothed (3x3); pixels above ``threshold`` times its maximum give a
    bounding box, grown by ``margin`` of its size on each side (at least ``min_margin_px``
    full-resolution pixels) and clipped to the field. If that region covers more than
    ``max_area`` of the field, the whole field is kept.
    """
    fh, fw = field
    whole = Region.whole(field)
    mask = None if measured is None else measured.astype(np.float32)
    model = build_region_model("2d", psf, whole, downsample=factor, mask=mask)
    x = _fit(model, torch.as_tensor(b_a[None]), tau, TV(), iters, None)
    img = x[0, 0].double().numpy()
    sm = _smooth3(np.clip(img, 0, None))
    peak = float(sm.max())
    if peak <= 0:
        return Extent(whole, whole, 1.0, False, img.astype(np.float32))
    ys, xs = np.nonzero(sm > threshold * peak)
    y0, y1 = int(ys.min()) * factor, (int(ys.max()) + 1) * factor
    x0, x1 = int(xs.min()) * factor, (int(xs.max()) + 1) * factor
    y1, x1 = min(y1, fh), min(x1, fw)
    bbox = Region(y0, x0, y1 - y0, x1 - x0, fh, fw)
    my = max(min_margin_px, factor, round(margin * (y1 - y0)))
    mx = max(min_margin_px, factor, round(margin * (x1 - x0)))
    t, left = max(0, y0 - my), max(0, x0 - mx)
    bottom, right = min(fh, y1 + my), min(fw, x1 + mx)
    region = Region(t, left, bottom - t, right - left, fh, fw)
    ra = region.scaled(factor)
    inside = float(np.clip(img, 0, None)[ra.top:ra.top + ra.height,
                                         ra.left:ra.left + ra.width].sum())
    total = float(np.clip(img, 0, None).sum())
    frac = inside / total if total > 0 else 1.0
    if region.area_fraction > max_area:
        return Extent(whole, bbox, 1.0, False, img.astype(np.float32))
    return Extent(region, bbox, frac, True, img.astype(np.float32))


# ---------------------------------------------------------------------------------------------
# time


def normalised_shutter(base: Any, factor: int) -> F64:
    """``bin_time(base, factor)`` scaled so that each row's bins sum to 1 on average."""
    m = bin_time(np.asarray(base, dtype=np.float64), factor)
    mean_row_sum = float(m.sum(axis=0).mean())
    if mean_row_sum <= 0:
        raise ValueError("the shutter function is all zero: no row integrates any light")
    return np.asarray(m / mean_row_sum)


def video_tv(k: int, tau: float, lambda_t: float = LAMBDA_T) -> tuple[float, TV]:
    """Per-frame TV weight and the TV prior of a K-frame video (see the module docstring)."""
    if k <= 1:
        return tau, TV()
    return tau / k, TV(weight_k=lambda_t * k)


def candidate_factors(k0: int, max_k: int) -> list[int]:
    """Bin factors of a K0-bin shutter giving K = 1, 2, 3, 4, 6, 8, 12, 16, ... <= max_k."""
    out: list[int] = []
    seen: set[int] = set()
    targets = [1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128]
    for t in targets:
        if t > min(k0, max_k):
            break
        f = -(-k0 // t)
        k = -(-k0 // f)
        if k not in seen:
            seen.add(k)
            out.append(f)
    return out


@dataclass(frozen=True)
class TimeScale:
    """Outcome of the cross-validation over the number of time bins."""

    k: int
    factor: int
    motion: bool
    candidates: tuple[CVCandidate, ...]
    base_bins: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {"k": self.k, "bin_factor": self.factor, "motion": self.motion,
                "base_bins": self.base_bins,
                "candidates": [c.to_dict() for c in self.candidates]}


def time_scale(
    psf: F32,
    b_a: F32,
    base_shutter: F64,
    region: Region,
    factor: int,
    *,
    folds: int = 4,
    max_k: int = 32,
    pilot_iters: int = 150,
    iters: int = 100,
    tau: float = ANALYSIS_TAU,
    lambda_t: float = LAMBDA_T,
    patience: int = 2,
    z_max: float = 2.0,
    rel_tol: float = 0.05,
    motion_rel: float = 0.25,
    motion_z: float = 3.0,
    measured: npt.NDArray[np.bool_] | None = None,
    seed: int = 0,
) -> TimeScale:
    """How many time bins the data supports (on the analysis grid; see the module docstring).

    ``psf``, ``base_shutter`` (K0, H) and ``region`` are at full resolution; ``b_a`` is the
    measurement box-downsampled by ``factor``, where the fits run.

    Every fit of a fold starts from that fold's 2D pilot fit (``pilot_iters``) copied into each
    frame and runs ``iters`` more iterations, the 2D candidate included, so all candidates get
    the same effort. Candidates are tried with increasing K and the search stops once
    ``patience`` of them in a row improved on the best by less than ``rel_tol``.

    Motion is declared when the 2D model's held-out error is more than ``motion_rel`` above the
    best video model's and the difference has a paired z-score above ``motion_z``:
    on static simulated scenes the 2D model's held-out error was at most 16% above the best
    video model's (the video models have more freedom; docs/plan.md), on moving scenes 4-15
    times the best video model's. K is then the smallest video K within ``rel_tol`` (or
    ``z_max``) of the best video K.
    """
    k0 = int(base_shutter.shape[0])
    fold_masks = heldout_folds((int(b_a.shape[-2]), int(b_a.shape[-1])), folds, seed)
    bt = torch.as_tensor(b_a[None])
    pilots: list[torch.Tensor] = []
    ok = np.ones(b_a.shape, dtype=bool) if measured is None else measured
    for held in fold_masks:
        train = ((~held) & ok).astype(np.float32)
        m2 = build_region_model("2d", psf, region, downsample=factor, mask=train)
        pilots.append(_fit(m2, bt * torch.as_tensor(train), tau, TV(), pilot_iters, None))

    errors: list[tuple[str, int, F64, dict[str, Any]]] = []
    best = math.inf
    stale = 0
    for f in candidate_factors(k0, max_k):
        shutter = normalised_shutter(base_shutter, f)
        k = int(shutter.shape[0])
        tau_k, tv = video_tv(k, tau, lambda_t)

        def build(mask: Any, k: int = k, shutter: F64 = shutter) -> ForwardModel:
            if k == 1:
                return build_region_model("2d", psf, region, downsample=factor, mask=mask)
            return build_region_model("video", psf, region, downsample=factor, mask=mask,
                                      shutter=shutter)

        def start(i: int, k: int = k) -> torch.Tensor:
            return pilots[i].expand(1, k, *pilots[i].shape[2:]).contiguous()

        e = _pixel_errors(build, b_a, fold_masks, tau_k, tv, iters, start, measured)
        label = "2d" if k == 1 else f"video K={k}"
        errors.append((label, k, e, {"bin_factor": f}))
        mse = float(e.mean())
        if mse < best * (1.0 - rel_tol):
            stale = 0
        else:
            stale += 1
        best = min(best, mse)
        if stale >= patience:
            break
    _, table = cv_select(errors, z_max=z_max, rel_tol=rel_tol)
    motion = False
    k, factor = 1, k0
    if len(errors) > 1:
        video_best = min(range(1, len(errors)), key=lambda i: table[i].heldout_mse)
        d = errors[0][2].ravel() - errors[video_best][2].ravel()
        se = float(d.std()) / math.sqrt(d.size)
        z1 = float(d.mean()) / se if se > 0 else 0.0
        gain = table[0].heldout_mse / table[video_best].heldout_mse - 1.0
        motion = gain > motion_rel and z1 > motion_z
        if motion:
            chosen, _ = cv_select(errors[1:], z_max=z_max, rel_tol=rel_tol)
            k = table[1 + chosen].k
            factor = int(table[1 + chosen].info["bin_factor"])
    return TimeScale(k, factor, motion, tuple(table), k0)


# ---------------------------------------------------------------------------------------------
# depth


@dataclass(frozen=True)
class DepthExtent:
    """Outcome of the cross-validation over subsets of a PSF stack: planes [first, last)."""

    first: int
    last: int
    energy: tuple[float, ...]
    candidates: tuple[CVCandidate, ...]

    @property
    def k(self) -> int:
        """Number of planes kept."""
        return self.last - self.first

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {"planes": [self.first, self.last],
                "energy_per_plane": [round(e, 4) for e in self.energy],
                "candidates": [c.to_dict() for c in self.candidates]}


def depth_extent(
    stack: F32,
    b_a: F32,
    region: Region,
    factor: int,
    *,
    folds: int = 4,
    iters: int = 150,
    tau: float = ANALYSIS_TAU,
    lambda_z: float = 0.5,
    z_max: float = 2.0,
    rel_tol: float = 0.05,
    measured: npt.NDArray[np.bool_] | None = None,
    seed: int = 0,
) -> DepthExtent:
    """Which depth planes of a PSF stack (K, H, W) the data supports (analysis grid).

    ``stack`` and ``region`` are at full resolution, ``b_a`` is box-downsampled by ``factor``.

    A depth reconstruction with every plane gives the energy per plane; candidates are the
    strongest plane alone (a 2D model with that plane's PSF), then ranges of planes grown one
    neighbour at a time towards the stronger side, up to the whole stack. Cross-validation as
    in :func:`time_scale` picks the smallest range not significantly worse than the best.
    """
    n = int(stack.shape[0])
    mask = None if measured is None else measured.astype(np.float32)
    full = build_region_model("depth", stack, region, downsample=factor, mask=mask)
    x = _fit(full, torch.as_tensor(b_a[None]), tau, TV(weight_k=lambda_z), iters, None)
    energy = np.clip(x[0].double().numpy(), 0, None).sum(axis=(-2, -1))
    energy = energy / max(float(energy.sum()), 1e-30)
    p = int(np.argmax(energy))
    ranges = [(p, p + 1)]
    lo, hi = p, p + 1
    while lo > 0 or hi < n:
        left = energy[lo - 1] if lo > 0 else -1.0
        right = energy[hi] if hi < n else -1.0
        if left >= right:
            lo -= 1
        else:
            hi += 1
        ranges.append((lo, hi))
    if len(ranges) > 6:  # keep the search short: 1, 2, 3 planes, then coarser steps
        idx = sorted({0, 1, 2, len(ranges) // 2, (3 * len(ranges)) // 4, len(ranges) - 1})
        ranges = [ranges[i] for i in idx]
    fold_masks = heldout_folds((int(b_a.shape[-2]), int(b_a.shape[-1])), folds, seed)
    errors: list[tuple[str, int, F64, dict[str, Any]]] = []
    for lo, hi in ranges:
        sub = stack[lo:hi]

        def build(mask: Any, sub: F32 = sub) -> ForwardModel:
            if sub.shape[0] == 1:
                return build_region_model("2d", sub[0], region, downsample=factor, mask=mask)
            return build_region_model("depth", sub, region, downsample=factor, mask=mask)

        tv = TV(weight_k=lambda_z) if hi - lo > 1 else TV()
        e = _pixel_errors(build, b_a, fold_masks, tau, tv, iters, lambda i: None, measured)
        label = f"2d plane {lo}" if hi - lo == 1 else f"depth planes {lo}..{hi - 1}"
        errors.append((label, hi - lo, e, {"planes": [lo, hi]}))
    chosen, table = cv_select(errors, z_max=z_max, rel_tol=rel_tol)
    lo, hi = table[chosen].info["planes"]
    return DepthExtent(int(lo), int(hi), tuple(float(v) for v in energy), tuple(table))
