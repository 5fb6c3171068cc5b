"""Model only what a scene requires: plan the model, K, region, resolution and method.

- :mod:`recon.plan.analysis`: PSF resolution, scene extent, time scale and depth extent,
  measured on the data (cross-validation on held-out pixels).
- :mod:`recon.plan.roi`: forward models on a region of the scene field.
- :mod:`recon.plan.cost`: measured cost per iteration (cached) and the method for a budget.
- :mod:`recon.plan.planner`: :class:`Plan` (with reasons, JSON, overrides),
  :func:`make_plan`, :func:`auto_tau_plan`, :func:`execute`.

Torch is imported by these modules; import them only where torch is wanted.
"""

from recon.plan.planner import (
    DEFAULT_TAU,
    PLAN_FORMAT,
    Plan,
    PlanResult,
    SensorTimingLike,
    auto_tau_plan,
    base_shutter,
    execute,
    make_plan,
    planned_model,
)
from recon.plan.roi import Region, build_region_model, embed_region

__all__ = [
    "DEFAULT_TAU",
    "PLAN_FORMAT",
    "Plan",
    "PlanResult",
    "Region",
    "SensorTimingLike",
    "auto_tau_plan",
    "base_shutter",
    "build_region_model",
    "embed_region",
    "execute",
    "make_plan",
    "planned_model",
]
