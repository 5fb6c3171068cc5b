"""What a reconstruction costs on this machine, and which method a time budget affords.

The cost model is measured, not guessed: :func:`iteration_cost` builds nothing itself; given the
planned forward model it times a few FISTA-TV iterations on a random measurement (after two
warm-up steps, median of the rest) and caches the seconds per iteration in a JSON file keyed by
everything that changes it (model kind and sizes, FFT grid, dtype, device, torch threads, torch
version, host). The cache lives in ``$LENSLESSCAM_CACHE_DIR`` (default
``$XDG_CACHE_HOME/lenslesscam``, ``~/.cache/lenslesscam``), file ``plan_costs.json``; entries
older than a week are re-measured.

:func:`method_for_budget` turns a budget into a method and an iteration count:

- FISTA-TV with ``floor(budget / cost) - setup`` iterations, at most 500 (noise-free FISTA is
  still improving at 500, noisy cases level off near 300: ARCHITECTURE.md), 300 with no budget;
- the UDN is suggested only when :mod:`recon.udn` is importable and the budget is long enough
  for it to win: a GPU and at least 20 minutes, or at least 8 hours on a CPU. On a CPU budget
  of minutes (about 1000 iterations in 8 minutes at 75x100) a deep-image-prior network does not
  yet beat tuned FISTA-TV (ARCHITECTURE.md, "Pitfalls already measured").

When ``recon.trade`` (the measured speed/accuracy trade) provides a suggestion, the planner
should prefer it; until then this rule is the planner's, and the plan says so.
"""

from __future__ import annotations

import datetime as _dt
import importlib.util
import json
import math
import os
import platform
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from recon.atomic import atomic_write_json
from recon.fista import Fista
from recon.models import ForwardModel
from recon.operators import power_norm
from recon.tv import TV

__all__ = [
    "DEFAULT_ITERS",
    "MAX_ITERS",
    "MIN_ITERS",
    "UDN_MIN_BUDGET_CPU_S",
    "UDN_MIN_BUDGET_GPU_S",
    "CostEstimate",
    "MethodChoice",
    "cache_path",
    "iteration_cost",
    "method_for_budget",
    "udn_available",
]

DEFAULT_ITERS = 300
MAX_ITERS = 500
MIN_ITERS = 50
#: Iteration-equivalents of the setup (power iteration for the step size, 50 A^T A products).
SETUP_ITERS = 25
UDN_MIN_BUDGET_GPU_S = 20 * 60.0
UDN_MIN_BUDGET_CPU_S = 8 * 3600.0
_MAX_AGE_S = 7 * 24 * 3600.0


def cache_path() -> Path:
    """The cost cache file (``$LENSLESSCAM_CACHE_DIR/plan_costs.json``)."""
    root = os.environ.get("LENSLESSCAM_CACHE_DIR")
    xdg = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    base = Path(root).expanduser() if root else Path(xdg) / "lenslesscam"
    return base / "plan_costs.json"


@dataclass(frozen=True)
class CostEstimate:
    """Seconds per FISTA-TV iteration of one model, and where the number came from."""

    seconds_per_iter: float
    source: str
    key: str

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {"seconds_per_iter": float(f"{self.seconds_per_iter:.4g}"),
                "source": self.source, "key": self.key}


def _key(model: ForwardModel) -> str:
    pad = model.info.get("pad")
    return "|".join([
        model.kind.value,
        "scene=" + "x".join(str(s) for s in model.scene_shape),
        "meas=" + "x".join(str(s) for s in model.meas_shape),
        "pad=" + ("x".join(str(int(p)) for p in pad) if pad is not None else "?"),
        str(model.op.dtype).replace("torch.", ""),
        str(model.op.device),
        f"threads={torch.get_num_threads()}",
        f"torch={torch.__version__}",
        f"host={platform.node()}",
    ])


def _read_cache(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def _probe(model: ForwardModel, iters: int, tv: TV) -> float:
    gen = torch.Generator().manual_seed(0)
    b = torch.rand(model.meas_shape, generator=gen, dtype=model.op.dtype).to(model.op.device)
    lip = 1.02 * power_norm(model.op, iters=10) ** 2
    solver = Fista(model.op, b, tau=1e-3, tv=tv, max_iter=10**9, tol=0.0, lipschitz=lip)
    for _ in range(2):
        solver.step()
    times: list[float] = []
    for _ in range(iters):
        t0 = time.perf_counter()
        solver.step()
        times.append(time.perf_counter() - t0)
    times.sort()
    return times[len(times) // 2]


def iteration_cost(model: ForwardModel, *, probe_iters: int = 5, use_cache: bool = True,
                   path: Path | None = None) -> CostEstimate:
    """Seconds per FISTA-TV iteration of ``model`` here: cached, else measured and cached."""
    key = _key(model)
    file = path if path is not None else cache_path()
    now = time.time()
    if use_cache:
        entry = _read_cache(file).get(key)
        if (isinstance(entry, dict) and isinstance(entry.get("seconds_per_iter"), float)
                and now - float(entry.get("unix_time", 0.0)) < _MAX_AGE_S):
            return CostEstimate(float(entry["seconds_per_iter"]), "cache", key)
    tv = TV(weight_k=0.5) if model.k > 1 else TV()
    s = _probe(model, probe_iters, tv)
    if use_cache:
        data = _read_cache(file)
        data[key] = {"seconds_per_iter": s, "unix_time": now,
                     "measured_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
                     "probe_iters": probe_iters}
        try:
            file.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_json(file, data)
        except OSError:
            pass  # a read-only home only costs a re-measurement next time
    return CostEstimate(s, "probe", key)


def udn_available() -> bool:
    """True when :mod:`recon.udn` can be imported (without importing it)."""
    try:
        return importlib.util.find_spec("recon.udn") is not None
    except (ImportError, ValueError):
        return False


@dataclass(frozen=True)
class MethodChoice:
    """A method, its iteration limit, the time it should take and why."""

    method: str
    iterations: int
    estimated_s: float | None
    reason: str
    affordable: bool = True


def method_for_budget(cost: CostEstimate | None, budget_s: float | None, *,
                      gpu: bool | None = None) -> MethodChoice:
    """FISTA-TV with as many iterations as the budget allows (see the module docstring)."""
    spi = cost.seconds_per_iter if cost is not None else None

    def est(n: int) -> float | None:
        return None if spi is None else (n + SETUP_ITERS) * spi

    if budget_s is None:
        return MethodChoice("fista-tv", DEFAULT_ITERS, est(DEFAULT_ITERS),
                            f"no time budget: FISTA-TV, {DEFAULT_ITERS} iterations (noisy "
                            "measurements level off near 300)")
    if not (math.isfinite(budget_s) and budget_s > 0):
        raise ValueError(f"the time budget must be a positive number of seconds, got {budget_s}")
    on_gpu = torch.cuda.is_available() if gpu is None else gpu
    udn_floor = UDN_MIN_BUDGET_GPU_S if on_gpu else UDN_MIN_BUDGET_CPU_S
    if udn_available() and budget_s >= udn_floor:
        where = "a GPU" if on_gpu else "a CPU"
        return MethodChoice("udn", 0, budget_s,
                            f"{budget_s:.6g} s on {where} is at least {udn_floor:.0f} s: long "
                            "untrained-network runs beat FISTA-TV (ARCHITECTURE.md); the run "
                            "stops at the budget or on its held-out early stop")
    if spi is None:
        return MethodChoice("fista-tv", DEFAULT_ITERS, None,
                            "no cost measurement: FISTA-TV, default iterations")
    n = math.floor(budget_s / spi) - SETUP_ITERS
    src = f"{spi * 1e3:.3g} ms per iteration ({cost.source if cost else '?'})"
    if n >= MAX_ITERS:
        return MethodChoice("fista-tv", MAX_ITERS, est(MAX_ITERS),
                            f"{budget_s:.3g} s at {src} allows {n} iterations; FISTA-TV gains "
                            f"little after {MAX_ITERS}, so {MAX_ITERS} (it stops earlier once "
                            "converged)")
    if n >= MIN_ITERS:
        return MethodChoice("fista-tv", n, est(n),
                            f"{budget_s:.3g} s at {src} allows {n} iterations of FISTA-TV")
    return MethodChoice("fista-tv", max(n, 1), est(max(n, 1)),
                        f"{budget_s:.3g} s at {src} allows only {max(n, 0)} iterations "
                        f"(fewer than {MIN_ITERS}): the result will be under-converged",
                        affordable=False)
