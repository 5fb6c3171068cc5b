"""The reconstruction plan: the simplest model the scene needs, with the reason for each choice.

:func:`make_plan` analyses a measurement and its calibration (see :mod:`recon.plan.analysis`)
and returns a :class:`Plan`: the model (2D, video or depth), the number of frames or planes K,
the region of the scene field to reconstruct, the downsampling factor, and the method and
iteration count for a time budget (see :mod:`recon.plan.cost`). Every field has a reason and
can be overridden (:meth:`Plan.override`); :meth:`Plan.to_json` / :meth:`Plan.from_json` save
and load it, :meth:`Plan.describe` prints it, and :func:`execute` runs it.

Conventions: the measurement is scaled to maximum 1; the field and the region are in
full-resolution sensor pixels of the scene field centred on the sensor axis (as
:func:`recon.models.build_model` lays it out); a video plan bins the finest shutter function
given (``base_bins`` bins) by ``bin_factor`` and normalises it (rows sum to about 1), with TV
weights ``tau / K`` per frame and ``lambda_t * K`` along time (so a static video costs what its
2D image costs; :mod:`recon.plan.analysis`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from enum import Enum
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
import torch

from recon.checks import (
    check_field,
    downsample_remainder_text,
    warn_downsample_remainder,
)
from recon.fista import Fista, FistaStep
from recon.formats import INT_LIMIT, whole_version
from recon.models import ForwardModel
from recon.plan.analysis import (
    LAMBDA_T,
    depth_extent,
    normalised_shutter,
    psf_resolution,
    scene_extent,
    time_scale,
    video_tv,
)
from recon.plan.cost import MIN_ITERS, SETUP_ITERS, iteration_cost, method_for_budget
from recon.plan.roi import Region, build_region_model, embed_region
from recon.preprocess import box_downsample, downsample_mask, downsample_masked
from recon.tv import TV

__all__ = [
    "DEFAULT_TAU",
    "PLAN_FORMAT",
    "PLAN_VERSION",
    "Plan",
    "PlanResult",
    "SensorTimingLike",
    "auto_tau_plan",
    "base_bin_lines",
    "base_shutter",
    "execute",
    "make_plan",
    "planned_model",
    "region_energy_warning",
    "udn_configs",
    "udn_text",
]

PLAN_FORMAT = "lenslesscam.plan"
#: the newest plan format this release reads. A plan is written as version 1 unless it carries
#: UDN settings (``udn``, version 2): a release that reads only version 1 refuses such a plan
#: rather than run its default network in place of the one the plan names
PLAN_VERSION = 2
#: TV weight of the reconstruction (the ``recon fista`` default), for a measurement of max 1.
DEFAULT_TAU = 1e-3
#: the smallest measurement (rows and columns) make_plan analyses
MIN_PLAN_SIZE = 2
MODELS = ("2d", "video", "depth")
#: a region (or field) set by the user that holds less than this fraction of the energy the
#: extent analysis found in the plan's own region is warned about (reasons['region'], and
#: ``plan`` / ``recon auto`` print it): the scene reaches beyond it
REGION_ENERGY_WARN = 0.8
#: cells per axis of the extent analysis' energy map kept in a plan's evidence
ENERGY_MAP_CELLS = 12
#: the most values of a base shutter function built from a timing (K0 x rows; 128 MB float64:
#: one-line bins for a 2048-row sensor up to 8192 lines from the first row's start to the last
#: row's end)
MAX_SHUTTER_ELEMENTS = 1 << 24
#: base bins kept however many rows the sensor has
MIN_BASE_BINS = 256
METHODS = ("fista-tv", "udn")

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]


class SensorTimingLike(Protocol):
    """What the planner needs of a frame's sensor timing.

    :class:`drivers.timing.SensorTiming` is one (recon does not import drivers: the caller
    builds the timing, for example from a frame's metadata with ``SensorTiming.from_dict``).
    """

    @property
    def rows(self) -> int:
        """Sensor rows."""

    @property
    def exposure_lines(self) -> int:
        """Exposure of one row in line units."""

    @property
    def frame_lines(self) -> int:
        """First row's start to the last row's end, in line units (one-line bins)."""

    @property
    def pattern(self) -> Enum:
        """Readout pattern (its ``value`` names it in the plan's notes)."""

    def shutter(self, bin_lines: int, n_bins: int | None = None) -> npt.NDArray[Any]:
        """Shutter function (K, rows) with time bins of ``bin_lines`` lines."""


# ---------------------------------------------------------------------------------------------
# the plan


def _plan_type_text(annotation: str) -> str:
    """What a plan field's annotation asks for, in words."""
    words = {"str": "a string", "int": "an integer", "float": "a number",
             "tuple[int, int]": "a list of 2 integers",
             "tuple[int, int, int, int]": "a list of 4 integers",
             "tuple[str, ...]": "a list of strings", "dict[str, str]": "an object",
             "dict[str, Any]": "an object"}
    parts = [p.strip() for p in annotation.split("|")]
    text = " or ".join(words.get(p, p) for p in parts if p != "None")
    return text + (" or null" if "None" in parts else "")


def _check_plan_field(name: str, annotation: str, v: Any) -> None:
    """Raise ValueError naming ``name`` and its expected type when ``v`` does not fit it."""
    parts = [p.strip() for p in annotation.split("|")]
    if v is None and "None" in parts:
        return
    for p in parts:
        if p == "str" and isinstance(v, str):
            return
        num = isinstance(v, int | float) and not isinstance(v, bool)
        if p == "int" and isinstance(v, int) and not isinstance(v, bool):
            return
        if p == "float" and num and math.isfinite(v):
            return
        if p.startswith("dict") and isinstance(v, dict):
            return
        if p.startswith("tuple") and isinstance(v, list | tuple):
            items = p[len("tuple["):-1].split(", ")
            if items[-1] == "...":
                if all(isinstance(e, str) for e in v):
                    return
            elif len(v) == len(items) and all(
                    isinstance(e, int) and not isinstance(e, bool) for e in v):
                return
    raise ValueError(f"plan field {name!r} must be {_plan_type_text(annotation)}, got {v!r}")


@dataclass(frozen=True)
class Plan:
    """A reconstruction plan; every field except the bookkeeping ones can be overridden.

    Attributes:
        model: ``2d``, ``video`` or ``depth``.
        k: frames (video), planes (depth), 1 for 2D.
        sensor: (H, W) of the measurement at full resolution.
        field: the scene field (Hs, Ws), full-resolution pixels, centred on the sensor axis.
        region: (top, left, height, width) of the field to reconstruct.
        downsample: box downsampling factor of PSF, measurement and shutter.
        method: ``fista-tv`` or ``udn``.
        iterations: iteration limit (``udn``: 0 = until the budget or its early stop).
        tau: TV weight for the full-resolution grid; a grid d times coarser uses ``tau / d``
            (the discretisation of one continuous objective: the data term sums d^2 fewer
            pixels, the TV of the coarse image in fine units is about d times smaller), and a
            video ``tau / K`` per frame.
        lambda_t: video TV weight along time per unit of exposure (weight_k = lambda_t K).
        tv_depth: depth TV weight along the planes.
        bin_factor: video: bins of the finest shutter function merged into one frame.
        base_bins: video: bins of the finest shutter function given.
        planes: depth (and 2D from a stack): [first, last) planes of the PSF stack.
        budget_s: the time budget (None: none).
        seconds_per_iter: measured cost of one iteration of the planned model.
        estimated_s: expected reconstruction time.
        channels: colour channels of the measurement.
        reasons: why each field has its value.
        evidence: the numbers behind the reasons.
        overridden: fields the user set.
        plan_s: seconds the analysis took.
        udn: the UDN's settings, as a trade row measured them (:func:`recon.trade.udn_settings`):
            ``{"network": NetworkConfig fields, "config": UDNConfig fields}`` (the config
            without ``max_iter`` and ``time_limit_s``: ``iterations`` and ``budget_s`` are
            those). None: the UDN's defaults. Checked against :mod:`recon.udn` when the plan
            runs (:func:`udn_configs`); a field it does not know is an error, not dropped.

    """

    model: str
    k: int
    sensor: tuple[int, int]
    field: tuple[int, int]
    region: tuple[int, int, int, int]
    downsample: int
    method: str
    iterations: int
    tau: float = DEFAULT_TAU
    lambda_t: float = LAMBDA_T
    tv_depth: float = 0.5
    bin_factor: int | None = None
    base_bins: int | None = None
    planes: tuple[int, int] | None = None
    budget_s: float | None = None
    seconds_per_iter: float | None = None
    estimated_s: float | None = None
    channels: int = 1
    reasons: dict[str, str] = dataclasses.field(default_factory=dict)
    evidence: dict[str, Any] = dataclasses.field(default_factory=dict)
    overridden: tuple[str, ...] = ()
    plan_s: float = 0.0
    udn: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        self.validate()

    # -- checks ----------------------------------------------------------------------------
    def validate(self) -> None:
        """Raise ValueError naming the first inconsistent field."""
        if self.model not in MODELS:
            raise ValueError(f"plan.model must be one of {MODELS}, got {self.model!r}")
        if self.method not in METHODS:
            raise ValueError(f"plan.method must be one of {METHODS}, got {self.method!r}")
        if int(self.k) != self.k or self.k < 1:
            raise ValueError(f"plan.k must be an integer >= 1, got {self.k!r}")
        if int(self.downsample) != self.downsample or self.downsample < 1:
            raise ValueError(f"plan.downsample must be an integer >= 1, got {self.downsample!r}")
        if (int(self.iterations) != self.iterations or self.iterations < 0
                or self.iterations > INT_LIMIT):  # as every integer a user gives
            raise ValueError(f"plan.iterations must be an integer from 0 to 2**62, got "
                             f"{self.iterations!r}")
        if self.method == "fista-tv" and self.iterations < 1:
            raise ValueError("plan.iterations must be >= 1 for fista-tv")
        if not (math.isfinite(self.tau) and self.tau >= 0):
            raise ValueError(f"plan.tau must be >= 0, got {self.tau!r}")
        # the one field rule (recon.checks.check_field); the plan's PSF is on its sensor grid
        check_field(self.field, self.sensor, self.sensor, "plan field 'field'")
        if self.region[2] < 1 or self.region[3] < 1:  # as given, not as Region prints it
            raise ValueError(f"plan.region {list(self.region)!r} (top, left, height, width) "
                             "has an empty size: height and width must be >= 1")
        Region(*self.region, *self.field)  # raises if outside the field
        if self.model == "2d" and self.k != 1:
            raise ValueError(f"a 2d plan has k = 1, got {self.k}")
        if self.model == "video":
            if self.bin_factor is None or self.base_bins is None:
                raise ValueError("a video plan needs bin_factor and base_bins (a shutter function)")
            if self.bin_factor < 1 or self.bin_factor > self.base_bins:
                raise ValueError(f"plan.bin_factor must be in [1, {self.base_bins}], "
                                 f"got {self.bin_factor}")
            if self.k != -(-self.base_bins // self.bin_factor):
                raise ValueError(f"plan.k = {self.k} does not match {self.base_bins} shutter bins "
                                 f"binned by {self.bin_factor}")
        if self.model == "depth":
            if self.planes is None:
                raise ValueError("a depth plan needs planes [first, last)")
            if self.k != self.planes[1] - self.planes[0]:
                raise ValueError(f"plan.k = {self.k} does not match planes {self.planes}")
        if self.planes is not None and not 0 <= self.planes[0] < self.planes[1]:
            raise ValueError(f"plan.planes must be [first, last) with first < last: "
                             f"{self.planes}")
        h, w = self.sensor
        if h // self.downsample < 2 or w // self.downsample < 2:
            raise ValueError(f"downsampling {h}x{w} by {self.downsample} leaves too few pixels")
        if self.udn is not None and not (
                isinstance(self.udn, Mapping) and set(self.udn) <= {"network", "config"}
                and all(isinstance(v, Mapping) for v in self.udn.values())):
            raise ValueError(f"plan.udn must be an object with a 'network' and a 'config' "
                             f"object (recon.udn settings), got {self.udn!r:.80}")

    def check_rows(self) -> None:
        """Refuse a video plan of more frames than its grid has rows (naming the k that fits).

        The rule of :func:`recon.checks.check_shutter_frames`, said for a plan. Not part of
        :meth:`validate`: a plan file of an earlier release that broke it still loads, so that
        ``--set k=...`` or ``--set downsample=...`` can mend it before it runs.
        """
        if self.model != "video" or self.base_bins is None:
            return
        rows = self.sensor[0] // self.downsample
        if self.k > rows:
            fewer = -(-self.base_bins // -(-self.base_bins // rows))
            raise ValueError(
                f"a video plan of K = {self.k} frames for {rows} rows ({self.sensor[0]} "
                f"downsampled {self.downsample}x): a rolling shutter resolves at most as many "
                f"frames as rows; set k={fewer} or fewer, or a smaller downsample")

    # -- derived ---------------------------------------------------------------------------
    @property
    def region_obj(self) -> Region:
        """The region as a :class:`Region` at full resolution."""
        return Region(*self.region, *self.field)

    @property
    def grid_region(self) -> Region:
        """The region on the reconstruction grid (after downsampling)."""
        return self.region_obj.scaled(self.downsample)

    @property
    def scene_shape(self) -> tuple[int, int, int, int]:
        """(C, K, h, w) of the reconstruction."""
        g = self.grid_region
        return (self.channels, self.k, g.height, g.width)

    # -- overrides ------------------------------------------------------------------------
    def override(self, **changes: Any) -> Plan:
        """A copy with some fields set by the user; related fields follow, reasons say so.

        ``k`` for a video re-bins the shutter (``bin_factor = ceil(base_bins / k)``, so the K
        that results may differ slightly); ``model='2d'`` sets k = 1 (from a PSF stack, the
        strongest plane); from a PSF stack, ``planes`` without a model choose it (one plane 2d,
        more depth) and ``model='depth'`` alone takes the depth analysis' best range of planes
        (:meth:`_stack_planes`); ``region='whole'`` (or ``None``) is the whole field; a new
        ``field`` resets the region to it. Changing the model's size drops the cost estimate.
        """
        fixed = {"reasons", "evidence", "overridden", "plan_s", "sensor", "channels",
                 "base_bins"}
        names = {f.name for f in dataclasses.fields(self)} - fixed
        bad = set(changes) - names
        if bad:
            raise ValueError(f"cannot override {sorted(bad)}; fields: {sorted(names)}")
        types = {f.name: str(f.type) for f in dataclasses.fields(self)}
        for key, v in changes.items():  # one line naming the field, never a traceback
            if not (key == "region" and v in (None, "whole")):
                _check_plan_field(key, types[key], v)
            if key in ("k", "downsample", "bin_factor") and v is not None and v < 1:
                raise ValueError(f"plan field {key!r} must be >= 1, got {v!r}")
            if key == "iterations" and v is not None and v < 1 and changes.get(
                    "method", self.method) == "fista-tv":
                # the rule of validate(), said for the value the user gave
                raise ValueError(f"plan field 'iterations' must be >= 1 for fista-tv, got {v!r}")
            if key in ("iterations", "tau", "lambda_t", "tv_depth", "estimated_s") and (
                    v is not None and v < 0):
                raise ValueError(f"plan field {key!r} must be >= 0, got {v!r}")
            if key == "region" and v not in (None, "whole") and (v[2] < 1 or v[3] < 1):
                raise ValueError(f"plan field 'region' {list(v)!r} (top, left, height, width) "
                                 "has an empty size: height and width must be >= 1")
            if key in ("budget_s", "seconds_per_iter") and v is not None and v <= 0:
                raise ValueError(f"plan field {key!r} must be > 0, got {v!r}")
            if key in ("field", "planes") and v is not None and (
                    min(v) < (1 if key == "field" else 0)):
                raise ValueError(f"plan field {key!r} must be positive, got {v!r}")
            if key == "field" and v is not None:
                check_field(v, self.sensor, self.sensor, "plan field 'field'")
            if key == "planes" and v is not None:
                n = len(self.evidence.get("depth", {}).get("energy_per_plane") or []) or None
                if v[1] <= v[0]:
                    raise ValueError(f"plan field 'planes' is [first, last) with first < last, "
                                     f"got {v!r}")
                if n is not None and v[1] > n:
                    raise ValueError(f"plan field 'planes' {v!r} reaches past the {n}-plane "
                                     "stack")
        new: dict[str, Any] = {}
        for key, v in changes.items():
            if key in ("field",) and v is not None:
                new[key] = (int(v[0]), int(v[1]))
            elif key == "region":
                new[key] = None if v in (None, "whole") else tuple(int(a) for a in v)
            elif key == "planes" and v is not None:
                new[key] = (int(v[0]), int(v[1]))
            elif key in ("k", "downsample", "iterations", "bin_factor") and v is not None:
                new[key] = int(v)
            elif key in ("tau", "lambda_t", "tv_depth", "budget_s", "seconds_per_iter",
                         "estimated_s") and v is not None:
                new[key] = float(v)
            else:
                new[key] = v
        merged = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        merged.update(new)
        if "field" in new and "region" not in new:
            new["region"] = None
        if merged.get("region") is None or new.get("region", 0) is None:
            f = merged["field"]
            merged["region"] = (0, 0, int(f[0]), int(f[1]))
        planes_why = self._stack_planes(changes, new, merged)
        model = merged["model"]
        if model == "2d":
            # after the planes chose the model: planes=[0,3] with k=3 is a depth plan (it was
            # refused as a 2d one, "set model=video")
            if "k" in changes and changes["k"] is not None and int(changes["k"]) != 1:
                raise ValueError("k applies to a video or depth plan; a 2d plan has k = 1 "
                                 "(set model=video, or planes=[first,last] for depth, with it)")
            merged["k"] = 1
            merged["bin_factor"] = None
        elif model == "video":
            if self.base_bins is None:
                raise ValueError("a video plan needs a shutter function; this plan was made "
                                 "without one")
            if "k" in new or "bin_factor" not in new or merged["bin_factor"] is None:
                k_want = merged["k"] if ("k" in new or self.model == "video") else 2
                k_want = max(1, min(int(k_want), self.base_bins))
                merged["bin_factor"] = -(-self.base_bins // k_want)
            merged["k"] = -(-self.base_bins // int(merged["bin_factor"]))
        elif model == "depth":
            if merged["planes"] is None:
                raise ValueError("a depth plan needs planes (and a PSF stack)")
            if "k" in changes and "planes" not in changes:
                raise ValueError("a depth plan's K follows its planes: set planes=[first, last]")
            merged["k"] = merged["planes"][1] - merged["planes"][0]
            if "k" in changes and int(changes["k"]) != merged["k"]:
                raise ValueError(f"plan field 'k' {changes['k']!r} does not match planes "
                                 f"{list(merged['planes'])!r} ({merged['k']} planes): a depth "
                                 "plan's K follows its planes")
        reasons = dict(self.reasons)
        for key in changes:
            old = getattr(self, key)
            reasons[key] = f"set by the user (the plan had {old!r})"
        if planes_why is not None:
            reasons.update(planes_why)
        if {"region", "field"} & set(changes):
            warning = _region_energy_text(self.evidence, tuple(merged["field"]),
                                          tuple(merged["region"]))
            if warning is not None:
                reasons["region"] = f"{reasons.get('region', '')}; warning: {warning}"
        if model == "video" and "k" in changes and merged["k"] != changes["k"]:
            # K frames are whole bins of the finest shutter function
            reasons["k"] = (f"set by the user: {changes['k']!r} requested (the plan had "
                            f"{self.k!r}); {self.base_bins} shutter bins in groups of "
                            f"{merged['bin_factor']} make {merged['k']} frames"
                            + _last_group_text(merged["k"], merged["bin_factor"],
                                               self.base_bins or 0))
        size_keys = {"model", "k", "bin_factor", "planes", "region", "field", "downsample"}
        if size_keys & set(changes) and "seconds_per_iter" not in changes:
            merged["seconds_per_iter"] = None
            merged["estimated_s"] = None
            reasons["method"] = (reasons.get("method", "") + "; the cost estimate was made "
                                 "for the model before the override")
        elif ("iterations" in changes and "estimated_s" not in changes
              and merged["seconds_per_iter"] is not None and merged["method"] == "fista-tv"):
            # the same model, another count: the estimate follows (recon.plan.cost's rule)
            from recon.plan.cost import SETUP_ITERS

            merged["estimated_s"] = (int(merged["iterations"]) + SETUP_ITERS) * float(
                merged["seconds_per_iter"])
        merged["reasons"] = reasons
        merged["overridden"] = tuple(dict.fromkeys([*self.overridden, *changes]))
        out = Plan(**merged)
        out.check_rows()
        return out

    def _stack_planes(self, changes: Mapping[str, Any], new: Mapping[str, Any],
                      merged: dict[str, Any]) -> dict[str, str] | None:
        """Bring ``merged``'s model and planes of a PSF-stack plan into agreement.

        Planes set without a model choose it (one plane: 2d; more: depth); ``model='2d'`` alone
        keeps the strongest of the plan's planes, ``model='depth'`` alone on a one-plane plan
        takes the depth analysis' best range of more than one plane. A 2d model given more
        than one plane, a depth model given one, or planes on a plan made without a stack are
        refused in one line. Returns the reasons for model, k and planes (None: nothing to
        say, the planes are not involved).
        """
        from_stack = self.planes is not None or "depth" in self.evidence
        if "planes" in changes:
            if not from_stack and new["planes"] is not None:
                raise ValueError("plan field 'planes' applies to a plan made from a PSF stack "
                                 "(--psf-stack); this plan was made without one")
            if from_stack and new["planes"] is None:
                raise ValueError("plan field 'planes' cannot be null in a plan made from a "
                                 "PSF stack: set planes=[first, last]")
        if not from_stack or not {"planes", "model"} & set(changes):
            return None
        if merged["model"] == "video":
            return None  # refused by the video rule: no shutter function with a stack
        lo, hi = merged["planes"]
        dep = self.evidence.get("depth")
        dep = dep if isinstance(dep, Mapping) else {}
        old = _planes_text(self.planes) if self.planes is not None else "no planes"
        had = f"the plan had a {self.model} model of {old}"
        why: dict[str, str] = {}
        if "planes" in changes:
            core = f"{_planes_text((lo, hi))} set by the user"
            if "model" not in changes:
                merged["model"] = "2d" if hi - lo == 1 else "depth"
                why["model"] = (f"{merged['model']}: the user set {_planes_text((lo, hi))}, "
                                + ("one plane" if hi - lo == 1 else "more than one plane")
                                + f" ({had})")
                why["planes"] = f"{core} ({had})"
            elif merged["model"] == "2d" and hi - lo > 1:
                raise ValueError(f"a 2d plan reconstructs one PSF plane, planes "
                                 f"{[lo, hi]!r} are {hi - lo}: set model=depth with them, "
                                 "or one plane (planes=[p, p+1])")
            elif merged["model"] == "depth" and hi - lo == 1:
                raise ValueError(f"a depth plan needs more than one PSF plane, planes "
                                 f"{[lo, hi]!r} are one: set model=2d with it, or "
                                 "planes=[first, last] with last - first >= 2")
        elif merged["model"] == "2d" and hi - lo > 1:
            energy = dep.get("energy_per_plane")
            best = lo + int(np.argmax(energy[lo:hi])) if energy else (lo + hi) // 2
            merged["planes"] = (best, best + 1)
            strongest = ("the strongest in the depth analysis" if energy else
                         "the middle one (the plan records no energy per plane)")
            core = (f"plane {best} of the plan's {_planes_text((lo, hi))}: {strongest}, for "
                    "the 2d model the user set")
        elif merged["model"] == "depth" and hi - lo == 1:
            cands = [c for c in dep.get("candidates") or [] if isinstance(c, Mapping)
                     and isinstance(c.get("heldout_mse"), int | float)
                     and isinstance(c.get("planes"), list | tuple) and len(c["planes"]) == 2
                     and int(c["planes"][1]) - int(c["planes"][0]) > 1]
            if not cands:
                raise ValueError("a depth plan needs more than one PSF plane and this plan "
                                 "records no depth analysis to choose them: set "
                                 "planes=[first, last] with model=depth")
            top = min(cands, key=lambda c: float(c["heldout_mse"]))
            merged["planes"] = (int(top["planes"][0]), int(top["planes"][1]))
            core = (f"{_planes_text(merged['planes'])}: of the depth analysis' ranges of more "
                    "than one plane, the one that predicts held-out pixels best (held-out MSE "
                    f"{top['heldout_mse']:.3g}), for the depth model the user set")
        else:
            return None
        lo, hi = merged["planes"]
        why["k"] = (f"one image: a 2d model of PSF plane {lo}" if merged["model"] == "2d"
                    else f"{hi - lo} planes: the depth model's {_planes_text((lo, hi))}")
        if "model" not in why:  # the model was set: its row names the planes and why
            why["planes"] = f"{core} ({had})"
            why["model"] = f"set by the user ({had}); {core}"
        return why

    # -- serialisation ---------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        """A JSON-ready dict with ``format`` and ``format_version`` (2 with UDN settings)."""
        d: dict[str, Any] = {"format": PLAN_FORMAT,
                             "format_version": 1 if self.udn is None else 2}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            d[f.name] = list(v) if isinstance(v, tuple) else v
        return d

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Plan:
        """Inverse of :meth:`to_json` (checks the format, version and every field's type)."""
        if not isinstance(d, Mapping):
            raise ValueError(f"a plan is a JSON object, got {type(d).__name__}")
        if d.get("format") != PLAN_FORMAT:
            raise ValueError(f"not a plan: format {d.get('format')!r}, expected {PLAN_FORMAT!r}")
        raw_version = d.get("format_version", 1)  # a file without one: the first version
        version = whole_version(raw_version)
        if version is None or version < 1:
            raise ValueError(f"plan format_version must be a whole number >= 1, got "
                             f"{raw_version!r}")
        if version > PLAN_VERSION:
            raise ValueError(f"plan format version {d.get('format_version')} is newer than "
                             f"this software reads ({PLAN_VERSION})")
        kw: dict[str, Any] = {}
        for f in dataclasses.fields(cls):
            if f.name not in d:
                if (f.default is dataclasses.MISSING
                        and f.default_factory is dataclasses.MISSING):
                    raise ValueError(f"plan field {f.name!r} is missing "
                                     f"({_plan_type_text(str(f.type))})")
                continue
            v = d[f.name]
            _check_plan_field(f.name, str(f.type), v)
            if f.name in ("sensor", "field", "region", "planes", "overridden") and v is not None:
                v = tuple(v)
            kw[f.name] = v
        return cls(**kw)

    def describe(self, window: tuple[int, int] | None = None) -> str:
        """Human-readable plan: each choice with its reason.

        ``window``: the real sensor's size when the measurement is embedded in a padded PSF
        grid (``sensor`` is then that grid), so the first line names the measurement's size.
        """
        g = self.grid_region
        h, w = self.sensor
        rows: list[tuple[str, str, str]] = []
        k_txt = {"2d": "1", "video": f"{self.k} frames", "depth": f"{self.k} planes"}
        model_txt = self.model
        if self.planes is not None:
            model_txt += f" (PSF {_planes_text(self.planes)})"
        rows.append(("model", model_txt, self.reasons.get("model", "")))
        rows.append(("K", k_txt[self.model], self.reasons.get("k", "")))
        reg = self.region_obj
        reg_txt = ("whole field" if reg.is_whole else
                   f"{reg.height}x{reg.width} at ({reg.top}, {reg.left})")
        rows.append(("region", f"{reg_txt} of the {self.field[0]}x{self.field[1]} field",
                     self.reasons.get("region", "")))
        rows.append(("downsample", f"{self.downsample} -> grid {g.height}x{g.width}",
                     self.reasons.get("downsample", "")))
        est = f", about {self.estimated_s:.3g} s" if self.estimated_s is not None else ""
        it = (f"{self.iterations} iteration{'s' if self.iterations != 1 else ''}"
              if self.iterations else "until the budget")
        net = ""
        if self.method == "udn":
            net = f"; network {udn_text(self.udn)}"
        rows.append(("method", f"{self.method}, {it}{est}{net}", self.reasons.get("method", "")))
        rows.append(("tau", f"{self.tau:g}", self.reasons.get("tau", "")))
        size = (f"{h}x{w} measurement" if window is None else
                f"{window[0]}x{window[1]} measurement in a {h}x{w} padded PSF grid")
        lines = [f"Reconstruction plan for a {size} ({self.channels} channel"
                 f"{'s' if self.channels > 1 else ''}), analysed in {self.plan_s:.2f} s"]
        for name, value, why in rows:
            user = " [user]" if name in self.overridden else ""
            lines.append(f"  {name:<11}{value}{user}")
            if why:
                lines.append(f"  {'':<11}why: {why}")
        return "\n".join(lines)


def _last_group_text(k: int, factor: int, base_bins: int) -> str:
    """`` (the last of n)`` when the last of ``k`` groups of ``factor`` bins holds only n.

    Empty when ``base_bins`` bins fill every group.
    """
    last = int(base_bins) - (int(k) - 1) * int(factor)
    return "" if last == factor else f" (the last of {last})"


def _frames_text(k: int, factor: int, base_bins: int) -> str:
    """``base_bins`` shutter bins grouped ``factor`` at a time into ``k`` frames, in words.

    ``5 frames of 2 shutter bins (the last of 1)``, ``3 frames of 24 shutter bins each``.
    """
    bins = "1 shutter bin" if factor == 1 else f"{factor} shutter bins"
    last = _last_group_text(k, factor, base_bins)
    return f"{k} frame{'s' if k != 1 else ''} of {bins}{last or ' each'}"


def _planes_text(planes: tuple[int, int]) -> str:
    """``[first, last)`` of a PSF stack in words: ``plane 7`` or ``planes 0..6``."""
    lo, hi = int(planes[0]), int(planes[1])
    return f"plane {lo}" if hi - lo == 1 else f"planes {lo}..{hi - 1}"


# ---------------------------------------------------------------------------------------------
# where the energy lies (the extent analysis' map, kept in the evidence)


def _energy_map(preview: Any, field: tuple[int, int], factor: int,
                cells: int = ENERGY_MAP_CELLS) -> dict[str, Any] | None:
    """The extent analysis' reconstruction (its positive part) as a small energy map.

    ``preview`` is on the analysis grid (``field // factor``, pixel i covering full-resolution
    rows ``[i factor, (i + 1) factor)``; the last cell reaches to the field's end). At most
    ``cells`` x ``cells`` cells, with their edges in full-resolution field pixels; the energy
    of each cell as a fraction of the whole. None when the reconstruction holds no energy.
    """
    e = np.clip(np.asarray(preview, dtype=np.float64), 0, None)
    total = float(e.sum())
    if e.ndim != 2 or total <= 0 or not math.isfinite(total):
        return None
    starts = []
    for axis, n in enumerate(e.shape):
        groups = np.array_split(np.arange(n), min(cells, n))
        starts.append([int(g[0]) for g in groups])
        e = np.add.reduceat(e, starts[-1], axis=axis)
    edges = [[s * factor for s in st] + [int(field[i])] for i, st in enumerate(starts)]
    return {"field": [int(field[0]), int(field[1])], "row_edges": edges[0],
            "col_edges": edges[1], "energy": np.round(e / total, 4).tolist()}


def _map_energy(emap: Mapping[str, Any], field: tuple[int, int],
                region: tuple[int, int, int, int]) -> float:
    """Fraction of the map's energy inside ``region`` of a field ``field``.

    Both fields are centred on the sensor axis (field pixel ``H // 2`` images to the PSF's
    origin), so a region of another field is moved onto the map's; a cell partly inside
    counts in proportion to its area inside (energy taken as uniform within a cell).
    """
    mh, mw = emap["field"]
    top = region[0] + mh // 2 - field[0] // 2
    left = region[1] + mw // 2 - field[1] // 2

    def overlap(edges: list[int], lo: int, n: int) -> Any:
        a, b = np.asarray(edges[:-1], float), np.asarray(edges[1:], float)
        inside = np.clip(np.minimum(b, lo + n) - np.maximum(a, lo), 0, None)
        return inside / np.maximum(b - a, 1.0)

    wy = overlap(emap["row_edges"], top, region[2])
    wx = overlap(emap["col_edges"], left, region[3])
    return float(wy @ np.asarray(emap["energy"], dtype=np.float64) @ wx)


def _region_energy_text(evidence: Mapping[str, Any], field: tuple[int, int],
                        region: tuple[int, int, int, int]) -> str | None:
    """One line when ``region`` of ``field`` holds too little of the energy the plan found.

    Too little: under :data:`REGION_ENERGY_WARN` of what the extent analysis' own region
    held (``evidence['extent']``, its energy map). None when it holds enough, or the plan
    has no map (made by an earlier version).
    """
    ext = evidence.get("extent") if isinstance(evidence, Mapping) else None
    emap = ext.get("energy_map") if isinstance(ext, Mapping) else None
    if not isinstance(emap, Mapping):
        return None
    try:
        found_region = tuple(int(n) for n in ext["region"])
        found = _map_energy(emap, tuple(emap["field"]), found_region)  # type: ignore[arg-type]
        held = _map_energy(emap, field, region)
    except (KeyError, TypeError, ValueError, IndexError):  # a map edited by hand
        return None
    if found <= 0 or held >= REGION_ENERGY_WARN * found:
        return None
    whole = tuple(region) == (0, 0, field[0], field[1])
    what = (f"the {field[0]}x{field[1]} field" if whole else
            f"region {region[2]}x{region[3]} at ({region[0]}, {region[1]}) of the "
            f"{field[0]}x{field[1]} field")
    fh, fw = emap["field"]
    t, lft, h, w = found_region
    return (f"{what} holds {100 * held / found:.0f}% of the scene's energy that the extent "
            f"analysis found in {h}x{w} at ({t}, {lft}) of the {fh}x{fw} field (threshold "
            f"{100 * REGION_ENERGY_WARN:.0f}%): the scene reaches beyond it, and the light from "
            "outside is fitted inside it")


def region_energy_warning(plan: Plan) -> str | None:
    """The warning about a region or field the user set, as :meth:`Plan.override` gives it.

    None when neither was set by the user or the region holds enough of the scene's energy
    (see :data:`REGION_ENERGY_WARN`).
    """
    if not {"region", "field"} & set(plan.overridden):
        return None
    return _region_energy_text(plan.evidence, plan.field, plan.region)


# ---------------------------------------------------------------------------------------------
# inputs


def _as_chw(a: Any, what: str) -> F32:
    arr = np.asarray(a, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3:
        raise ValueError(f"{what} must be (H, W) or (C, H, W), got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{what} has NaN or inf values")
    return arr


def _scaled_meas(meas: Any) -> F32:
    b = _as_chw(meas, "measurement")
    peak = float(b.max())
    if peak <= 0:
        raise ValueError("the measurement is all zero or negative: nothing to reconstruct")
    return np.asarray(b / peak, dtype=np.float32)


def base_shutter(shutter: Any, timing: SensorTimingLike | None,
                 rows: int, bins: int | None = None) -> tuple[F64 | None, str]:
    """The finest shutter function (K0, rows) from an array or a sensor timing, and a note.

    None (with the reason) when there is no shutter, or the sensor has a global shutter.
    ``bins``: a plan's ``base_bins`` (its timing's bins are then built that wide, so a plan
    keeps working whatever :func:`base_bin_lines` would choose now).
    """
    if shutter is not None:
        m = np.asarray(shutter, dtype=np.float64)
        if m.ndim != 2 or m.shape[1] != rows:
            raise ValueError(f"shutter function must be (K, {rows}) for a {rows}-row sensor, "
                             f"got {m.shape}")
        if not np.isfinite(m).all() or (m < 0).any():
            raise ValueError("shutter function must be finite and non-negative")
        return m, f"shutter function of {m.shape[0]} bins given"
    if timing is None:
        return None, "no shutter function or sensor timing given: time is not resolvable"
    if isinstance(timing, Mapping) or not callable(getattr(timing, "shutter", None)):
        raise TypeError("timing must be a sensor timing object (drivers.timing.SensorTiming, "
                        f"built from its dict by the caller), got {type(timing).__name__}")
    t = timing
    if t.rows != rows:
        raise ValueError(f"sensor timing has {t.rows} rows, the measurement {rows}")
    width = (base_bin_lines(t.frame_lines, t.rows) if bins is None
             else max(1, -(-int(t.frame_lines) // max(int(bins), 1))))
    m = np.asarray(t.shutter(bin_lines=width), dtype=np.float64)
    if bool(np.all(m == m[:, :1])):
        return None, "global shutter: every row integrates the same window, no time resolution"
    bins = (f"{m.shape[0]} one-line bins" if width == 1 else
            f"{m.shape[0]} bins of {width} lines (the frame's {t.frame_lines} one-line bins "
            f"merged to keep the shutter function within {MAX_SHUTTER_ELEMENTS} values)")
    return m, f"{t.pattern.value} readout, exposure {t.exposure_lines} lines: {bins}"


def base_bin_lines(frame_lines: int, rows: int) -> int:
    """Width in lines of the finest shutter bins a timing is planned with (1 when it fits).

    One-line bins (K0 = ``frame_lines``) unless the (K0, rows) shutter function would hold more
    than :data:`MAX_SHUTTER_ELEMENTS` values (at least :data:`MIN_BASE_BINS` bins are kept):
    then the narrowest whole-line width that fits. A wider bin is the mean of the one-line bins
    it covers (``recon.preprocess.bin_time``), so nothing but time resolution finer than the
    planner's K (at most 32 frames in its analysis) is lost. Without this a 1000-row sensor
    exposed 100000 lines built 100499 one-line bins: 1.9 GB for ``plan``.
    """
    frame_lines, rows = int(frame_lines), int(rows)
    cap = max(MIN_BASE_BINS, MAX_SHUTTER_ELEMENTS // max(rows, 1))
    return max(1, -(-frame_lines // cap))


def planned_model(plan: Plan, psf: Any = None, *, shutter: F64 | None = None,
                  psf_stack: Any = None, mask: Any = None,
                  dtype: torch.dtype = torch.float32,
                  device: torch.device | str = "cpu") -> ForwardModel:
    """The forward model a plan reconstructs with (on its downsampled grid and region).

    ``shutter`` is the finest shutter function (K0, H) the plan was made with; ``mask`` the
    full-resolution sensor mask (downsampled by the one rule,
    :func:`recon.preprocess.downsample_mask`: a coarse pixel is measured when any of its
    sensor pixels is).
    """
    d = plan.downsample
    region = plan.region_obj
    m_d = None
    if mask is not None:
        m_d = downsample_mask(np.asarray(mask, dtype=np.float32), d)
    kw: dict[str, Any] = {"downsample": d, "mask": m_d, "dtype": dtype, "device": device}
    if plan.planes is not None:
        if psf_stack is None:
            raise ValueError("this plan uses planes of a PSF stack: pass psf_stack")
        sub = np.asarray(psf_stack, dtype=np.float32)[plan.planes[0]:plan.planes[1]]
        if plan.model == "2d":
            return build_region_model("2d", sub[0], region, **kw)
        return build_region_model("depth", sub, region, **kw)
    if psf is None:
        raise ValueError("pass the PSF")
    p = _as_chw(psf, "PSF")
    p_arg: Any = p[0] if p.shape[0] == 1 else p
    if plan.model == "video":
        if shutter is None or plan.bin_factor is None:
            raise ValueError("a video plan needs the shutter function it was planned with")
        if shutter.shape[0] != plan.base_bins:
            raise ValueError(f"the plan was made for {plan.base_bins} shutter bins, "
                             f"got {shutter.shape[0]}")
        m = normalised_shutter(shutter, plan.bin_factor)
        return build_region_model("video", p_arg, region, shutter=m, **kw)
    return build_region_model("2d", p_arg, region, **kw)


# ---------------------------------------------------------------------------------------------
# planning


def make_plan(
    psf: Any,
    meas: Any,
    *,
    shutter: Any = None,
    timing: SensorTimingLike | None = None,
    psf_stack: Any = None,
    mask: Any = None,
    field: tuple[int, int] | None = None,
    sensor: tuple[int, int] | None = None,
    budget_s: float | None = None,
    tau: float | None = None,
    analysis_rows: int = 24,
    seed: int = 0,
    probe: bool = True,
    use_cache: bool = True,
    progress: Callable[[str], None] | None = None,
) -> Plan:
    """Analyse a measurement and its calibration and return the plan.

    Args:
        psf: (H, W) or (C, H, W) PSF (None when ``psf_stack`` is given).
        meas: (H, W) or (C, H, W) measurement (dark subtracted; any scale).
        shutter: finest shutter function (K0, H) of a rolling-shutter frame, or
        timing: the frame's sensor timing (:class:`SensorTimingLike`, for example a
            ``drivers.timing.SensorTiming``).
        psf_stack: (K, H, W) PSFs of depth planes: plan 2D (one plane) or depth.
        mask: (H, W) sensor mask, 1 = measured (erased / dead pixels are left out).
        field: scene field (Hs, Ws) to consider (default the sensor size).
        sensor: the real sensor's (rows, cols) when ``meas`` lies on a larger (padded PSF)
            grid; the downsampling keeps at least 16 px of it and of the field.
        budget_s: time budget of the reconstruction in seconds (None: none).
        tau: TV weight of the reconstruction (None: :data:`DEFAULT_TAU`, the reasons say
            "default"; a value given, even the default's, is "given").
        analysis_rows: the analysis runs on a grid of about this many rows.
        seed: seeds the held-out pixels of the cross-validation.
        probe: measure the planned model's cost (else no time estimate, default iterations).
        use_cache: read and write the cost cache.
        progress: called with a line of text at each stage.

    """
    t_start = time.perf_counter()
    given_tau, tau = tau, DEFAULT_TAU if tau is None else float(tau)

    def say(msg: str) -> None:
        if progress is not None:
            progress(msg)

    b = _scaled_meas(meas)
    c, h, w = b.shape
    if h < MIN_PLAN_SIZE or w < MIN_PLAN_SIZE:
        raise ValueError(f"a {h}x{w} measurement is too small to plan: the analysis needs at "
                         f"least {MIN_PLAN_SIZE}x{MIN_PLAN_SIZE} pixels (its held-out folds, "
                         "TV and shutter rows); reconstruct it with recon fista or recon admm")
    stack: F32 | None = None
    if psf_stack is not None:
        stack = np.asarray(psf_stack, dtype=np.float32)
        if stack.ndim != 3 or stack.shape[1:] != (h, w):
            raise ValueError(f"PSF stack must be (K, {h}, {w}), got {stack.shape}")
        if c != 1:
            raise ValueError("a depth measurement must be grayscale")
        psf_gray = stack.mean(axis=0)
    else:
        if psf is None:
            raise ValueError("give a PSF (or a PSF stack)")
        p = _as_chw(psf, "PSF")
        if p.shape[1:] != (h, w) or p.shape[0] not in (1, c):
            raise ValueError(f"PSF {p.shape} does not match the measurement {b.shape}")
        psf_gray = p.mean(axis=0)
    fld = (h, w) if field is None else (int(field[0]), int(field[1]))
    if fld[0] < 1 or fld[1] < 1:
        raise ValueError(f"field must be positive, got {fld}")
    check_field(fld, (h, w), (h, w))  # before the analysis pays for pixels no light leaves
    reasons: dict[str, str] = {}
    evidence: dict[str, Any] = {}

    # resolution (of a stack: its sharpest plane; the mean of the planes would be blurred),
    # the factor capped so the real sensor and the field keep 16 px
    cap_on = fld if sensor is None else (min(fld[0], int(sensor[0])), min(fld[1], int(sensor[1])))
    if stack is not None:
        res = min((psf_resolution(plane, sensor=cap_on) for plane in stack),
                  key=lambda r: min(r.fwhm_y, r.fwhm_x))
    else:
        res = psf_resolution(psf_gray, sensor=cap_on)
    d = res.factor
    evidence["resolution"] = res.to_dict()
    reasons["downsample"] = (
        f"the PSF autocorrelation peak is {res.fwhm_y:.1f} x {res.fwhm_x:.1f} px wide (FWHM); "
        f"details finer than that are not resolved, so {d} px per sample keeps two samples "
        f"per resolvable width" + ("" if res.limited_by == "autocorrelation width"
                                   else f" (capped by {res.limited_by})"))

    # analysis grid
    a = max(d, round(h / analysis_rows), 1)
    while a > 1 and (h // a < 8 or w // a < 8):
        a -= 1
    mk: F32 | None = None
    if mask is not None:
        mk = np.asarray(mask, dtype=np.float32)
        if mk.shape[-2:] != (h, w):
            raise ValueError(f"mask {mk.shape} does not match the sensor {(h, w)}")

    def analysis_data(f: int) -> tuple[F32, npt.NDArray[np.bool_] | None]:
        """The measurement (gray) box-downsampled by ``f``, and where it is measured."""
        if mk is None:
            return box_downsample(b.mean(axis=0), f), None
        # the one mask rule: measured when any sensor pixel is, the mean of the measured ones
        b_m, m_a = downsample_masked(b.mean(axis=0)[None], mk.reshape(h, w), f)
        return b_m[0], m_a > 0

    b_a, measured = analysis_data(a)
    evidence["analysis_grid"] = {"factor": a, "shape": list(b_a.shape)}

    # extent
    say("extent: low-resolution 2D reconstruction of the field")
    ext = scene_extent(psf_gray, b_a, fld, a, measured=measured)
    region = ext.region
    evidence["extent"] = ext.to_dict()
    emap = _energy_map(ext.preview, fld, a)
    if emap is not None:  # where the energy lies: a region the user sets is checked on it
        evidence["extent"]["energy_map"] = emap
    if ext.cropped:
        reasons["region"] = (
            f"a {b_a.shape[0]}x{b_a.shape[1]} reconstruction puts the energy in "
            f"{ext.bbox.height}x{ext.bbox.width} px at ({ext.bbox.top}, {ext.bbox.left}); "
            f"with a margin the region holds {100 * ext.energy_fraction:.0f}% of the energy in "
            f"{100 * region.area_fraction:.0f}% of the field")
    else:
        reasons["region"] = (
            f"the scene's energy spans {ext.bbox.height}x{ext.bbox.width} px of the "
            f"{fld[0]}x{fld[1]} field: with a margin that is more than 60% of it, so the "
            "whole field")

    # time and depth
    model, k = "2d", 1
    bin_factor: int | None = None
    planes: tuple[int, int] | None = None
    base, note = base_shutter(shutter, timing, h)
    base_bins = None if base is None else int(base.shape[0])
    if stack is not None:
        say(f"depth: cross-validation over {stack.shape[0]} PSF planes")
        dep = depth_extent(stack, b_a, region, a, measured=measured, seed=seed)
        evidence["depth"] = dep.to_dict()
        planes = (dep.first, dep.last)
        tab = "; ".join(f"{cand.label}: {cand.heldout_mse:.3g}" for cand in dep.candidates)
        if dep.k == 1:
            reasons["model"] = (f"one PSF plane ({dep.first}) predicts held-out pixels as well "
                                f"as more planes (held-out MSE {tab}): a 2D model")
        else:
            model, k = "depth", dep.k
            reasons["model"] = (f"planes {dep.first}..{dep.last - 1} are needed to predict "
                                f"held-out pixels (held-out MSE {tab})")
        reasons["k"] = reasons["model"]
        if base is not None:
            reasons["model"] += "; the shutter function is not used with a PSF stack"
        base_bins = None
    elif base is None:
        reasons["model"] = f"2D: {note}"
        reasons["k"] = "one image"
    else:
        say(f"time: cross-validation over K ({base.shape[0]} shutter bins)")
        # the shutter codes time along the rows: the time analysis keeps about
        # ``analysis_rows`` of them even when the PSF's resolution allows a coarser grid (on
        # fewer rows the video models' extra freedom fits the coarse grid's model error: a
        # still scene on a 32x40 sensor looked 38 % better explained with motion at 16 rows)
        a_t = max(1, min(a, h // analysis_rows))
        b_t, measured_t = (b_a, measured) if a_t == a else analysis_data(a_t)
        ts = time_scale(psf_gray, b_t, base, region, a_t, measured=measured_t, seed=seed)
        evidence["time"] = ts.to_dict()
        evidence["time"]["grid"] = {"factor": a_t, "shape": list(b_t.shape)}
        c0 = ts.candidates[0]
        best = min(ts.candidates, key=lambda cand: cand.heldout_mse)
        tab = ", ".join(f"K={cand.k}: {cand.heldout_mse:.3g}" for cand in ts.candidates)
        if ts.motion:
            model, k, bin_factor = "video", ts.k, ts.factor
            reasons["model"] = (
                f"motion: the 2D model predicts held-out pixels "
                f"{c0.heldout_mse / best.heldout_mse:.1f}x worse than the best video model "
                f"(z = {c0.z:.1f}; held-out MSE {tab})")
            reasons["k"] = (
                f"the smallest K whose held-out error is within 5% (or 2 standard errors) of "
                f"the best K={best.k}; {_frames_text(ts.k, ts.factor, int(base.shape[0]))} "
                f"({note})")
        else:
            gap = c0.heldout_mse / best.heldout_mse - 1.0
            reasons["model"] = (
                f"no motion: video models predict held-out pixels at most "
                f"{100 * max(gap, 0.0):.0f}% better than the 2D model (threshold 25%; "
                f"held-out MSE {tab}); a static scene needs one image")
            reasons["k"] = "one image (static scene)"

    if model == "video" and k > h // d:  # a rolling shutter resolves at most a frame a row
        d_res = d
        while d > 1 and k > h // d:  # (k <= h: the shutter's bins were checked against rows)
            d -= 1
        reasons["downsample"] += (f"; lowered from {d_res} to {d} so the {h // d} rows resolve "
                                  f"the K = {k} frames")

    # method for the budget
    reg4 = (region.top, region.left, region.height, region.width)
    plan = Plan(model=model, k=k, sensor=(h, w), field=fld, region=reg4,
                downsample=d, method="fista-tv", iterations=300, tau=tau, bin_factor=bin_factor,
                base_bins=base_bins, planes=planes, budget_s=budget_s, channels=c,
                reasons=reasons, evidence=evidence)
    cost = None
    if probe:
        say("cost: timing a few iterations of the planned model")
        first = plan.downsample
        for _ in range(8):
            pm = planned_model(plan, psf, shutter=base, psf_stack=stack, mask=mask)
            cost = iteration_cost(pm, use_cache=use_cache)
            choice = method_for_budget(cost, budget_s)
            bigger = plan.downsample * 2
            if (choice.affordable or h // bigger < 16 or w // bigger < 16
                    or plan.k > h // bigger):  # K frames need K rows (video)
                break
            plan = dataclasses.replace(plan, downsample=bigger)
        if plan.downsample != first:
            # one clause that says what the raise achieved (it may not have been enough)
            reasons["downsample"] += (
                f"; raised from {first} to {plan.downsample} so the budget allows at least "
                f"{MIN_ITERS} iterations" if choice.affordable else
                f"; raised from {first} to {plan.downsample} for the budget, the coarsest grid "
                "the planner goes to (a coarser one would have a side under 16 px, or fewer "
                "rows than frames), where it "
                f"still allows fewer than {MIN_ITERS} iterations")
    dropped = downsample_remainder_text(
        h, w, plan.downsample, measured=None if mask is None else np.asarray(mask).reshape(h, w))
    if dropped is not None:
        reasons["downsample"] += f"; {dropped}"
    choice = method_for_budget(cost, budget_s)
    reasons["method"] = (choice.reason if choice.affordable or cost is None or budget_s is None
                         else _too_small_budget_text(budget_s, cost, choice.iterations)) + (
        "; rule and cost probe of recon.plan.cost (measured here at plan time)"
        if cost is not None else "")
    reasons["tau"] = ("the default TV weight of recon fista (measurement scaled to max 1)"
                      if given_tau is None else "given")
    if cost is not None:
        evidence["cost"] = cost.to_dict()
    return dataclasses.replace(
        plan, method=choice.method, iterations=choice.iterations,
        seconds_per_iter=None if cost is None else cost.seconds_per_iter,
        estimated_s=choice.estimated_s, reasons=reasons, evidence=evidence,
        plan_s=time.perf_counter() - t_start)


def min_useful_budget_s(seconds_per_iter: float) -> float:
    """The smallest budget that affords ``MIN_ITERS`` FISTA-TV iterations and their set-up."""
    return (MIN_ITERS + SETUP_ITERS) * seconds_per_iter


def budget_room(budget_s: float, seconds_per_iter: float) -> int:
    """FISTA-TV iterations a budget affords after their set-up (0 or less: not even that).

    The one rule of the plan's reason and ``recon auto``'s warning.
    """
    return math.floor(budget_s / seconds_per_iter) - SETUP_ITERS


def _too_small_budget_text(budget_s: float, cost: Any, iterations: int) -> str:
    """The method's reason when the budget affords fewer than ``MIN_ITERS`` iterations."""
    spi = cost.seconds_per_iter
    n = budget_room(budget_s, spi)
    its = f"{iterations} iteration{'s' if iterations != 1 else ''}"
    if n > 0:
        room = f"allows only {n} iteration{'s' if n != 1 else ''}"
        verdict = f"FISTA-TV runs {its}: the result will be under-converged"
    else:
        room = f"does not even cover the set-up (about {SETUP_ITERS} iterations' time)"
        verdict = (f"FISTA-TV runs {its} anyway, too few to reconstruct anything useful "
                   "(recon auto checks the result against a flat image)")
    return (f"{budget_s:.3g} s at {spi * 1e3:.3g} ms per iteration ({cost.source}) {room}; "
            f"{verdict}: a budget of at least {min_useful_budget_s(spi):.2g} s affords "
            f"{MIN_ITERS} iterations and the set-up at this grid")


# ---------------------------------------------------------------------------------------------
# execution


@dataclass
class PlanResult:
    """A plan's reconstruction: x (C, K, h, w) on the grid of ``region`` (downsampled)."""

    x: F32
    plan: Plan
    region: Region
    iterations: int
    stop_reason: str
    wall_s: float
    residual: float | None
    params: dict[str, Any]
    mask_hash: str | None = None  # array hash of the coarse sensor mask the model used
    #: the model and measurement the run solved (a caller's result check uses them rather
    #: than preparing the plan again); not part of the result's metadata
    prepared: Prepared | None = dataclasses.field(default=None, repr=False, compare=False)

    def field_image(self) -> F32:
        """The reconstruction placed in the whole (downsampled) field, zero outside."""
        return np.asarray(embed_region(self.x, self.region), dtype=np.float32)

    def metadata(self) -> dict[str, Any]:
        """JSON-ready description for the saved reconstruction."""
        return {"method": self.plan.method, "model": self.plan.model, "plan": self.plan.to_json(),
                "iterations": self.iterations, "stop_reason": self.stop_reason,
                "wall_time_s": round(self.wall_s, 3), "residual": self.residual,
                "region_on_grid": self.region.to_list(), "parameters": self.params,
                "mask_hash": self.mask_hash}


@dataclass(frozen=True)
class Prepared:
    """What every run of a plan starts from: the planned model and its measurement."""

    model: ForwardModel
    b: F32  #: the measurement scaled and downsampled (the one mask rule), the model's shape
    mask_hash: str | None  #: hash of the model's coarse mask (None without a mask)


def prepare(
    plan: Plan,
    psf: Any,
    meas: Any,
    *,
    shutter: Any = None,
    timing: SensorTimingLike | None = None,
    psf_stack: Any = None,
    mask: Any = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
) -> Prepared:
    """Build the planned model and bring the measurement to it.

    :func:`execute` runs on it and ``plan``'s tau auto searches on it: one preparation for both.
    """
    plan.check_rows()  # a plan file of an earlier release, run without --set mending it
    b = _scaled_meas(meas)
    if tuple(b.shape[1:]) != tuple(plan.sensor):
        # both are grids: a measurement embedded in a padded PSF grid is that grid here
        # (lenslesscam recon auto names the real sensor before it gets here)
        raise ValueError(f"the plan is for a {plan.sensor[0]}x{plan.sensor[1]} measurement "
                         f"grid (its 'sensor'), this measurement's grid is {b.shape[1]}x"
                         f"{b.shape[2]}: make the plan for this measurement")
    base, _ = base_shutter(shutter, timing, plan.sensor[0], plan.base_bins)
    model = planned_model(plan, psf, shutter=base, psf_stack=psf_stack, mask=mask,
                          dtype=dtype, device=device)
    if "downsample" in plan.overridden:  # the user's factor (the plan's reason says its own)
        hb, wb = int(b.shape[1]), int(b.shape[2])
        warn_downsample_remainder(hb, wb, plan.downsample, measured=None if mask is None
                                  else np.asarray(mask).reshape(hb, wb))
    if mask is None:
        b_d = box_downsample(b, plan.downsample)
    else:  # the one mask rule (recon.preprocess.downsample_masked), as the model's mask
        b_d, _ = downsample_masked(b, np.asarray(mask, dtype=np.float32), plan.downsample)
    if tuple(b_d.shape) != model.meas_shape:
        raise ValueError(f"measurement {tuple(b_d.shape)} does not fit the model "
                         f"{model.meas_shape} (channels of PSF and measurement differ?)")
    mask_hash = None
    if model.mask is not None:
        from recon.formats import array_hash

        mask_hash = array_hash(model.mask.detach().cpu().numpy().astype(np.float32))
    return Prepared(model, np.asarray(b_d, dtype=np.float32), mask_hash)


def plan_tv(plan: Plan, tau_grid: float) -> tuple[Any, TV]:
    """The solver's tau and TV for a plan, from tau on the solver's grid."""
    if plan.model == "video":
        return video_tv(plan.k, tau_grid, plan.lambda_t)
    if plan.model == "depth":
        return tau_grid, TV(weight_k=plan.tv_depth)
    return tau_grid, TV()


def execute(
    plan: Plan,
    psf: Any,
    meas: Any,
    *,
    shutter: Any = None,
    timing: SensorTimingLike | None = None,
    psf_stack: Any = None,
    mask: Any = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
    callback: Callable[[Any], None] | None = None,
    cancel: Callable[[], bool] | None = None,
) -> PlanResult:
    """Run a plan: downsample, build the planned model on its region, reconstruct.

    ``callback`` receives every solver step (a :class:`~recon.fista.FistaStep` or a UDN step);
    ``cancel()`` returning True stops the run after the current step.
    """
    prep = prepare(plan, psf, meas, shutter=shutter, timing=timing, psf_stack=psf_stack,
                   mask=mask, dtype=dtype, device=device)
    model, b_d, mask_hash = prep.model, prep.b, prep.mask_hash
    bt = torch.as_tensor(b_d, dtype=dtype, device=device)
    t0 = time.perf_counter()
    if plan.method == "udn":
        res = _execute_udn(plan, model, b_d, t0, callback, cancel)
        return dataclasses.replace(res, mask_hash=mask_hash, prepared=prep)
    tau, tv = plan_tv(plan, plan.tau / plan.downsample)  # tau is per full-resolution pixel
    solver = Fista(model.op, bt, tau=tau, tv=tv, max_iter=plan.iterations, tol=1e-5)
    last: FistaStep | None = None
    for step in solver.steps():
        last = step
        if callback is not None:
            callback(step)
        if cancel is not None and cancel():
            break
    wall = time.perf_counter() - t0
    reason = solver.reason.value if solver.reason is not None else "cancelled"
    return PlanResult(solver.x.float().cpu().numpy(), plan, plan.grid_region, solver.iteration,
                      reason, wall, None if last is None else last.residual, solver.params,
                      mask_hash, prep)


def udn_configs(udn: Mapping[str, Any] | None, *, max_iter: int = 3000,
                time_limit_s: float | None = None) -> tuple[Any, Any]:
    """The :class:`recon.udn.NetworkConfig` and :class:`recon.udn.UDNConfig` of a plan's ``udn``.

    None: the defaults. A field :mod:`recon.udn` does not know (a trade of another release), a
    value it refuses, or a ``max_iter`` / ``time_limit_s`` among the settings (the plan's
    ``iterations`` and ``budget_s`` set those) raises ValueError in one line naming it: the
    run never substitutes a default for a setting it was given.
    """
    import dataclasses as dc

    from recon.udn import NetworkConfig, UDNConfig

    udn = udn or {}
    parts: dict[str, dict[str, Any]] = {}
    for part, cls in (("network", NetworkConfig), ("config", UDNConfig)):
        given = dict(udn.get(part) or {})
        known = {f.name for f in dc.fields(cls)}
        if part == "config":
            known -= {"max_iter", "time_limit_s"}
        unknown = sorted(set(given) - known)
        if unknown:
            raise ValueError(f"UDN {part} setting{'s' if len(unknown) > 1 else ''} "
                             f"{', '.join(unknown)} {'are' if len(unknown) > 1 else 'is'} not "
                             f"one this lenslesscam can run (it knows {', '.join(sorted(known))})")
        parts[part] = given
    try:
        net = NetworkConfig(**parts["network"])
        cfg = UDNConfig(**parts["config"], max_iter=max_iter, time_limit_s=time_limit_s)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"UDN settings {dict(udn)!r:.200}: {exc}") from None
    return net, cfg


def udn_text(udn: Mapping[str, Any] | None) -> str:
    """A UDN's settings in words, for the plan's description (``default`` for None)."""
    if not udn:
        return "default (recon.udn)"
    net = dict(udn.get("network") or {})
    cfg = dict(udn.get("config") or {})
    words = [f"{k} {net[k]}" for k in ("variant", "scales", "channels", "skip_channels")
             if k in net]
    words += [f"{k} {cfg[k]}" for k in ("lr", "precision", "holdout", "seed") if k in cfg]
    return ", ".join(words)


def _execute_udn(plan: Plan, model: ForwardModel, b: F32, t0: float,
                 callback: Callable[[Any], None] | None,
                 cancel: Callable[[], bool] | None) -> PlanResult:
    from recon.udn import UDNRunner

    try:
        net, cfg = udn_configs(plan.udn, max_iter=plan.iterations or 10**7,
                               time_limit_s=plan.budget_s)
    except ValueError as exc:
        raise ValueError(f"plan field 'udn': {exc}") from None
    runner = UDNRunner(model, b, network=net, config=cfg)
    # the budget covers the reconstruction: the network's set-up (about 1.5 s: torch, the
    # gain fit) counts towards it too (the time limit counted only the iterations, so a
    # 1 s budget ran 2.3 s)
    runner.elapsed_s = time.perf_counter() - t0
    res = runner.run(callback, cancel)
    return PlanResult(np.asarray(res.best, dtype=np.float32), plan, plan.grid_region,
                      res.iterations, res.reason.value, time.perf_counter() - t0,
                      None, {"method": "udn", **cfg.to_dict(), "network": net.to_dict()})


def auto_tau_plan(plan: Plan, psf: Any, meas: Any, *, shutter: Any = None,
                  timing: Any = None, psf_stack: Any = None, mask: Any = None,
                  cancel: Callable[[], bool] | None = None) -> Plan:
    """The plan with tau and iterations chosen from held-out pixels on its own model.

    What ``lenslesscam plan`` / ``recon auto`` and the app's planner do to a FISTA-TV plan whose
    tau nobody set (the default tau is 1.5-6 dB from the best on unseen scenes).

    The measurement is prepared by :func:`prepare`, as :func:`execute` runs it (scaled,
    downsampled with the one mask rule); tau is searched on the solver's scale and stored per
    full-resolution pixel as the plan defines it (x downsample; x K for a video's per-frame
    weight). ``cancel``: the search stops at its next check once it returns True and the plan
    holds the values tried so far (a caller that cancels discards it).
    """
    from recon.autotau import AUTO_MAX_ITER, choose_tau

    t0 = time.perf_counter()
    prep = prepare(plan, psf, meas, shutter=shutter, timing=timing, psf_stack=psf_stack,
                   mask=mask)
    model, b_d = prep.model, prep.b
    per_frame = plan.k if plan.model == "video" else 1
    tv = plan_tv(plan, 1.0)[1]
    limit = max(plan.iterations if plan.budget_s is not None else AUTO_MAX_ITER, 1)
    # held-out errors after a handful of iterations rank nothing (at 1 iteration the search
    # took the top of its range): below MIN_ITERS the taus are searched at MIN_ITERS, and the
    # run keeps the budget's count
    search_iter = max(limit, MIN_ITERS)
    lo_rel, hi_rel = 1e-7 / per_frame, 1e-2 / per_frame
    choice = choose_tau(model, torch.as_tensor(b_d, dtype=torch.float32), tv=tv,
                        max_iter=search_iter, min_iter=min(100, search_iter),
                        tau_range=(lo_rel, hi_rel), cancel=cancel)
    unit = per_frame * plan.downsample  # the solver's tau -> the plan's (per full-res pixel)
    tau = choice.tau * unit
    iterations = min(choice.iterations, limit)
    search_s = time.perf_counter() - t0  # the search and its preparation
    spent = (f"{search_s:.1f} s, not counted in plan_s" + (
        f" nor in the {plan.budget_s:g} s budget, which covers the reconstruction only"
        if plan.budget_s is not None else ""))
    scale = float(choice.settings.get("scale", 1.0))
    lo, hi = lo_rel * scale * unit, hi_rel * scale * unit
    edge = (" (the top of the range: a larger tau was not tried)" if tau >= hi * (1 - 1e-9)
            else " (the bottom of the range)" if tau <= lo * (1 + 1e-9) else "")
    searched = (f"{search_iter} iterations per tau" + (
        f", not the budget's {limit}, which are too few to rank taus" if search_iter > limit
        else ""))
    tried = [t * unit for t, _e, _i in choice.curve]  # the values tried, not the range's ends
    why = (f"chosen from held-out measured pixels ({choice.heldout_pixels} pixels, "
           f"{len(choice.curve)} values of tau tried from {min(tried):.3g} to {max(tried):.3g}"
           f" within {lo:.3g}-{hi:.3g} per full-resolution pixel{edge}, {searched}; "
           f"recon.autotau); the search took {spent}")
    new = plan.override(tau=tau, iterations=iterations)
    its = f"{iterations} iteration{'s' if iterations != 1 else ''}"
    verb = "were" if iterations != 1 else "was"
    if plan.budget_s is not None and choice.iterations > limit:
        chosen = (f"the budget's {its} {verb} kept (the held-out pixels chose "
                  f"{choice.iterations}); tau was {why}")
    elif plan.budget_s is not None:
        chosen = f"within that limit {its} {verb} {why}"
    else:
        chosen = f"then {its} (at most {limit}) {verb} {why}"
    reasons = {**new.reasons, "tau": why, "iterations": why,
               "method": f"{new.reasons.get('method', '')}; {chosen}"}
    evidence = {**new.evidence, "tau_search": {
        "seconds": round(search_s, 3), "values_tried": len(choice.curve),
        "heldout_pixels": choice.heldout_pixels, "max_iter": search_iter,
        "tau_range": [lo, hi], "taus_tried": tried}}
    # chosen by the planner, not set by the user
    return dataclasses.replace(new, reasons=reasons, evidence=evidence,
                               overridden=plan.overridden)
