"""Choose FISTA-TV's tau and iteration count from the measurement alone (held-out pixels).

A random ``holdout`` fraction of the measured pixels (10 %, at least ``min_holdout`` pixels
while that leaves three quarters to fit), in whole blocks of the sensor (:mod:`recon.holdout`:
4x4-pixel squares, 1/32 of a large sensor's shorter side; ``block=1``: single pixels), is
hidden from the solver.
Blocks, because a real measurement's mismatch to the model is smooth across the sensor: single
hidden pixels have their error predicted by their fitted neighbours and favour taus that fit
the mismatch (on the four real DiffuserCam pairs the scattered pixels chose 3-100x below the
truth's best tau at 0 and 50 % erasures; docs/auto-tau.md). Each candidate tau is run
cold on the remaining pixels and scored by the mean squared error of its prediction ``A x`` on
the hidden ones. The score of a tau is the best held-out error along its run, checked every
``check_every`` iterations; a run stops when that error has not improved by 0.1 % in all of the last
``patience`` iterations (never before ``min_iter``), so noisy cases stop where they start to
overfit and noise-free cases run to ``max_iter``. The iteration count returned is where the
chosen tau's held-out error was best (at least ``min_iter``) when its run ended with that
error rising (over-fitting: a tau too small for the noise); when it ended on a plateau or was
still improving, it is ``max_iter`` (measured on the protocol: stopping at the plateau cost
0.2-0.3 dB on noisy cases, where PSNR still improves while the held-out error, dominated by
the noise, barely moves).

Search over log10 tau, coarse to fine: whole decades from the top of ``tau_range`` down (the
scan stops once the score has been worse than the best for two decades in a row), then the
half decades either side of the best (no finer step: it would cost two more runs). tau is
relative to the measurement's scale: the range
(default 1e-7 .. 1e-2) is for a measurement with max 1 and a unit-sum PSF, and is multiplied
by max |b| otherwise.

The pick (``rule``): ``"1se"``, the default, is the one-standard-error rule of
cross-validation: going up from the tau of the smallest held-out error, the largest tau whose
mean held-out error exceeds the minimum's by at most one standard error of the paired
differences, taken over the held-out blocks (the more regularised setting the held-out pixels
cannot tell from the best); ``"min"`` takes the minimum itself. Measured with ``lenslesscam
bench tau-rules`` (docs/auto-tau.md). Both picks come from the one
search and are stored (``settings``: ``tau_min_error`` / ``iterations_min_error``,
``tau_one_se`` / ``iterations_one_se``).

The held-out pixels only rank the settings; the caller reconstructs with the chosen tau and
iteration count from all measured pixels (``recon fista`` does this by default).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from recon.fista import Fista
from recon.holdout import block_mean_se, block_side_for, few_heldout_note, heldout_blocks
from recon.models import ForwardModel
from recon.operators import Compose, Mask
from recon.tv import TV

__all__ = ["AUTO_MAX_ITER", "RULE", "AutoTau", "choose_tau", "parse_tau", "resolve"]

#: the rules ``choose_tau(rule=...)`` knows, and the short name each stores in result
#: metadata: "min", the tau of the smallest held-out error; "1se" (the default), the largest
#: tau within one standard error of it
RULES = {"min": "heldout-blocks", "1se": "heldout-blocks-1se"}
#: short name of the default rule, stored in result metadata
RULE = RULES["1se"]
#: iteration limit of the automatic search (and of the reconstruction it chooses for)
AUTO_MAX_ITER = 500


#: the fewest measured pixels a held-out choice (of tau, or of the iteration count) runs on
MIN_MEASURED = 20


def too_few_measured(n: int, *, tau_given: bool, iterations_given: bool = False) -> str:
    """The one-line refusal of a held-out choice on ``n`` < ``MIN_MEASURED`` measured pixels.

    It names what was being chosen (tau, or with a given tau only the iteration count) and
    advises giving only what was not given.
    """
    what = "the iteration count" if tau_given else "tau"
    give = ("--iters" if tau_given else "--tau" if iterations_given else "--tau and --iters")
    return (f"only {n} measured pixels: choosing {what} from held-out pixels needs at least "
            f"{MIN_MEASURED} (give {give})")


@dataclass(frozen=True)
class AutoTau:
    """The automatic choice: tau, the iteration count, and what it cost.

    ``curve`` holds (tau, held-out MSE, best iteration) for every tau tried, sorted by tau.
    """

    tau: float
    iterations: int
    rule: str
    cost_s: float
    curve: tuple[tuple[float, float, int], ...]
    heldout_pixels: int
    total_iterations: int
    settings: dict[str, Any] = field(default_factory=dict)

    def metadata(self) -> dict[str, Any]:
        """A JSON-able summary for result metadata and run records."""
        return {
            "tau": self.tau,
            "iterations": self.iterations,
            "rule": self.rule,
            "cost_s": round(self.cost_s, 3),
            "heldout_pixels": self.heldout_pixels,
            "total_iterations": self.total_iterations,
            "curve": [[t, e, i] for t, e, i in self.curve],
            "settings": dict(self.settings),
            "warning": self.warning(),
        }

    def warning(self) -> str | None:
        """One line when too few held-out pixels made the choice (None: enough)."""
        given = self.rule.endswith(" (iterations)")
        note = few_heldout_note(self.heldout_pixels,
                                "the iteration count" if given else "tau")
        return None if note is None else note + (
            "; give --iters" if given else "; give --tau (and --iters)")

    def describe(self) -> str:
        """One line for the terminal."""
        w = self.warning()
        tail = "" if w is None else f" ({w})"
        if self.rule.endswith(" (iterations)"):
            # a tau given by the user: only the iteration count was chosen
            return (f"iterations auto ({self.rule}, {self.heldout_pixels} held-out pixels, "
                    f"{self.cost_s:.1f} s): {self.iterations} iterations at the given tau "
                    f"{self.tau:.3g}{tail}")
        return (f"tau auto ({self.rule}, {self.heldout_pixels} held-out pixels, "
                f"{len(self.curve)} values tried in {self.cost_s:.1f} s): tau {self.tau:.3g}, "
                f"{self.iterations} iterations{tail}")


def _measured_pixels(model: ForwardModel, b: torch.Tensor) -> np.ndarray:
    """(H, W) bool: pixels measured in every channel (and every k of the mask)."""
    h, w = int(b.shape[-2]), int(b.shape[-1])
    if model.mask is None:
        return np.ones((h, w), bool)
    m = model.mask.detach().cpu().numpy()
    m = np.broadcast_to(m, (*m.shape[:-2], h, w)).reshape(-1, h, w)
    return np.asarray((m > 0).all(axis=0))


def _score_run(
    op: Any, full_op: Any, b_fit: torch.Tensor, b_hold: torch.Tensor, hold: torch.Tensor,
    tau: float, *, tv: TV,
    lipschitz: float, max_iter: int, min_iter: int, patience: int, check_every: int,
    prox_iters: int, restart: str, cancel: Callable[[], bool] | None,
    precondition: float | str | None = "auto",
) -> tuple[float, int, int, bool, torch.Tensor]:
    """One tau's run: (best held-out MSE, its iteration, iterations run, overfit, errors).

    ``errors``: the held-out pixels' squared errors where the MSE was best.
    ``overfit``: the run ended with its held-out error 0.1 % or more above its best (it was
    rising), rather than on a plateau.
    """
    solver = Fista(op, b_fit, tau=tau, tv=tv, max_iter=max_iter, tol=0.0,
                   lipschitz=lipschitz, prox_iters=prox_iters, restart=restart,
                   precondition=precondition)
    best, best_it, ref, err = math.inf, 0, math.inf, math.inf  # ref: the error at best_it
    best_sq = torch.empty(0)
    for step in solver.steps():
        it = step.iteration
        if it % check_every and not solver.done:
            continue
        with torch.no_grad():
            sq = (full_op.apply(solver.x)[hold] - b_hold) ** 2
            err = float(torch.mean(sq))
        if not math.isfinite(err):
            break
        if err < best:
            best, best_sq = err, sq
        if err < ref * (1.0 - 1e-3):  # improved by 0.1 % since the last improvement
            ref, best_it = err, it
        if it >= min_iter and it - best_it >= patience:
            break
        if cancel is not None and cancel():
            break
    return best, best_it, solver.iteration, not err <= best * (1.0 + 1e-3), best_sq


def choose_tau(
    model: ForwardModel,
    b: torch.Tensor,
    *,
    tv: TV | None = None,
    max_iter: int = 500,
    min_iter: int = 100,
    patience: int = 100,
    check_every: int = 10,
    holdout: float = 0.1,
    min_holdout: int = 200,
    tau_range: tuple[float, float] = (1e-7, 1e-2),
    prox_iters: int = 3,
    restart: str = "gradient",
    seed: int = 0,
    fixed_tau: float | None = None,
    cancel: Callable[[], bool] | None = None,
    rule: str = "1se",
    precondition: float | str | None = "auto",
    block: int | None = None,
) -> AutoTau:
    """Choose tau and the iteration count for FISTA-TV on ``model`` from ``b`` alone.

    ``model`` is the forward model of the measurement (its erasure mask included); ``b`` the
    measurement. See the module docstring for the rule. With ``fixed_tau`` only the iteration
    count is chosen (one run at that tau). ``precondition`` is FISTA's (:class:`recon.fista.Fista`):
    the search runs the iteration the reconstruction will run. ``block``: side in pixels of
    the held-out blocks (None: :func:`recon.holdout.block_side_for` the measured pixels, 1:
    single pixels).
    """
    t_start = time.perf_counter()
    if tuple(b.shape) != model.meas_shape:
        raise ValueError(f"measurement has shape {tuple(b.shape)}, the model expects "
                         f"{model.meas_shape}")
    if not 0.0 < holdout < 0.5:
        raise ValueError(f"holdout must be in (0, 0.5), got {holdout}")
    lo, hi = tau_range
    if not (0.0 < lo < hi and math.isfinite(hi)) and fixed_tau is None:
        raise ValueError(f"tau_range must be 0 < low < high, got {tau_range}")
    if not 1 <= min_iter <= max_iter:
        raise ValueError(f"need 1 <= min_iter <= max_iter, got {min_iter}, {max_iter}")
    if patience < check_every or check_every < 1:
        raise ValueError(f"need 1 <= check_every <= patience, got {check_every}, {patience}")
    if rule not in RULES:
        raise ValueError(f"rule must be one of {sorted(RULES)}, got {rule!r}")
    tv = tv if tv is not None else TV()
    b = b.to(dtype=model.op.dtype, device=model.op.device)
    measured = _measured_pixels(model, b)
    idx = np.flatnonzero(measured)
    if idx.size < MIN_MEASURED:
        raise ValueError(too_few_measured(idx.size, tau_given=fixed_tau is not None))
    if block is not None and block < 1:
        raise ValueError(f"block must be >= 1 pixel, got {block}")
    n_hold = max(round(holdout * idx.size), min(min_holdout, idx.size // 4), 5)
    side = block_side_for(measured) if block is None else block
    hold_np, labels_np = heldout_blocks(measured, n_hold, np.random.default_rng(seed), side)
    n_hold = int(hold_np.sum())
    hold = torch.as_tensor(hold_np, device=b.device).expand(b.shape)
    # the block of every held-out value, in the order b[hold] lists them
    hold_labels = torch.as_tensor(labels_np).expand(b.shape)[hold.cpu()].numpy()
    keep = Mask(torch.as_tensor(~hold_np, dtype=b.dtype), model.meas_shape, dtype=b.dtype,
                device=b.device)
    fit_op = Compose([keep, model.op])
    lipschitz = model.op.lipschitz()
    b_fit = keep.apply(b)
    b_hold = b[hold]
    scale = float(b.abs().max()) or 1.0
    scores: dict[float, tuple[float, int, bool]] = {}
    errors: dict[float, torch.Tensor] = {}  # per held-out pixel, at each tau's best
    total = 0

    def score(log_t: float) -> float:
        nonlocal total
        key = round(log_t, 6)
        if key not in scores:
            err, best_it, ran, overfit, errors[key] = _score_run(
                fit_op, model.op, b_fit, b_hold, hold, scale * 10.0**key, tv=tv,
                lipschitz=lipschitz, max_iter=max_iter, min_iter=min_iter, patience=patience,
                check_every=check_every, prox_iters=prox_iters, restart=restart,
                cancel=cancel, precondition=precondition)
            scores[key] = (err, best_it, overfit)
            total += ran
        return scores[key][0]

    if fixed_tau is not None:
        if not (math.isfinite(fixed_tau) and fixed_tau > 0):
            raise ValueError(f"fixed_tau must be > 0, got {fixed_tau}")
        scale = 1.0
        lo = hi = fixed_tau
    # coarse: whole decades, top down, until the score has been worse than the best twice
    lo_e, hi_e = math.log10(lo), math.log10(hi)
    decades = [hi_e - d for d in range(math.floor(hi_e - lo_e + 1e-9) + 1)]
    if decades[-1] > lo_e + 1e-9:
        decades.append(lo_e)
    worse = 0
    for e in decades:
        if cancel is not None and cancel() and scores:  # one tau at least: a result to return
            break
        s = score(e)
        worse = 0 if s <= min(v[0] for v in scores.values()) else worse + 1
        if worse >= 2:
            break
    # fine: the half decades either side of the best so far (inside the range)
    for half in () if fixed_tau is not None else (0.5,):
        best_e = min(scores, key=lambda k: scores[k][0])
        for e in (best_e - half, best_e + half):
            if lo_e - 1e-9 <= e <= hi_e + 1e-9 and not (cancel is not None and cancel()):
                score(e)
    min_e = min(scores, key=lambda k: scores[k][0])
    se_e = _one_standard_error(scores, errors, min_e, hold_labels)

    def iterations_at(e: float) -> int:
        # the held-out error rose: stop where it was best; on a plateau (or still improving)
        # more iterations do not hurt the held-out pixels, and they sharpen: use them all
        _, best_it, overfit = scores[e]
        return max(best_it, min_iter) if overfit else max_iter

    best_e = se_e if rule == "1se" else min_e
    curve = tuple(sorted((scale * 10.0**k, v[0], v[1]) for k, v in scores.items()))
    return AutoTau(
        tau=fixed_tau if fixed_tau is not None else scale * 10.0**best_e,
        iterations=iterations_at(best_e),
        # with a given tau there is nothing to pick: only the held-out iteration count
        rule=RULES[rule] if fixed_tau is None else RULES["min"] + " (iterations)",
        cost_s=time.perf_counter() - t_start, curve=curve, heldout_pixels=n_hold,
        total_iterations=total,
        settings={"holdout": holdout, "holdout_block": side, "seed": seed,
                  "tau_range": [lo, hi], "scale": scale,
                  "max_iter": max_iter, "min_iter": min_iter, "patience": patience,
                  "check_every": check_every,
                  # both rules' picks (tau, iterations) from this one search
                  "tau_min_error": scale * 10.0**min_e, "iterations_min_error":
                  iterations_at(min_e), "tau_one_se": scale * 10.0**se_e,
                  "iterations_one_se": iterations_at(se_e)},
    )


def _one_standard_error(scores: dict[float, tuple[float, int, bool]],
                        errors: dict[float, torch.Tensor], min_e: float,
                        labels: np.ndarray) -> float:
    """The largest log10 tau within one standard error of the minimum's held-out error.

    Going up from the minimum, while each tau's mean error exceeds the minimum's by at most
    one standard error of the paired differences over the same held-out pixels, with the
    held-out blocks (``labels``, one per value) as the sampling unit.
    """
    pick = min_e
    base = errors[min_e]
    for k in sorted(k for k in scores if k > min_e):
        if errors[k].shape != base.shape or base.numel() < 2:  # a run with no finite error
            break
        mean, se = block_mean_se((errors[k] - base).double().cpu().numpy(), labels)
        if mean > se:
            break
        pick = k
    return pick


def parse_tau(text: str) -> float | None:
    """``auto`` -> None, else a finite tau >= 0 (ValueError with a one-line message)."""
    if text.strip().lower() == "auto":
        return None
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"tau must be 'auto' or a finite number >= 0, got {text!r}") from None
    if not (math.isfinite(value) and value >= 0):
        raise ValueError(f"tau must be 'auto' or a finite number >= 0, got {text!r}")
    return value


def resolve(
    model: ForwardModel,
    b: torch.Tensor,
    tau: float | None,
    iterations: int | None,
    *,
    tv: TV | None = None,
    max_iter: int = AUTO_MAX_ITER,
    seed: int = 0,
    log: Callable[[str], None] | None = None,
    precondition: float | str | None = "auto",
    iterations_why: str = "as given",
) -> tuple[float, int, dict[str, Any]]:
    """The (tau, iterations) a command runs with, and the metadata that says how they came.

    ``tau`` / ``iterations`` None mean automatic; a given value is used exactly. A given tau
    with automatic iterations chooses only the iteration count at that tau (held-out pixels);
    tau 0 with automatic iterations runs ``max_iter``. When ``iterations`` is given and the
    search's own count differs, ``log`` gets a second line with the count the run uses and
    ``iterations_why`` (the search's line alone named its count, which the run did not use).
    """
    if tau is not None and iterations is not None:
        return tau, iterations, {"tau": tau, "tau_rule": "given", "iterations": iterations,
                                 "iterations_rule": "given"}
    if tau == 0.0:
        assert iterations is None
        return 0.0, max_iter, {"tau": 0.0, "tau_rule": "given", "iterations": max_iter,
                               "iterations_rule": "limit (tau 0)"}
    limit = iterations or max_iter
    measured = int(_measured_pixels(model, b).sum())
    if measured < MIN_MEASURED:  # said here, where it is known which of the two was given
        raise ValueError(too_few_measured(measured, tau_given=tau is not None,
                                          iterations_given=iterations is not None))
    choice = choose_tau(model, b, tv=tv, max_iter=limit, min_iter=min(100, limit),
                        patience=max(min(100, limit), 10), check_every=min(10, limit),
                        seed=seed, fixed_tau=tau, precondition=precondition)
    its = iterations if iterations is not None else choice.iterations
    if log is not None:
        log(choice.describe())
        if its != choice.iterations:
            log(f"the run itself: {its} iterations ({iterations_why})")
    meta = {"tau": choice.tau, "tau_rule": "given" if tau is not None else choice.rule,
            "iterations": its,
            "iterations_rule": "given" if iterations is not None else choice.rule,
            "auto": choice.metadata()}
    return choice.tau, its, meta
