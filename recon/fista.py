"""FISTA with total variation and non-negativity, stepwise.

Solves  min_x  0.5 ||A x - b||^2 + tau TV(x)  subject to x >= 0.

- Gradient step 1/L with L = 1.02 ||A||^2 from power iteration on the full (masked) operator.
- Fourier preconditioning, ``precondition=`` ("auto", the default; "off"; or a damping level
  kappa in (0, 1]): a non-negative PSF puts its sum at the DC, so ||A||^2, and with it the
  step, is set by a handful of frequencies next to the DC (99.9 % of the frequencies of the
  tutorial PSF have under 0.6 % of the largest |H|^2), while the scene's detail converges at
  the rate of the small ones. The gradient is multiplied by P = C F^H diag(p) F C^T on the
  convolution's padded grid (C the crop to the scene), p(f) = min(1, kappa / r(f)),
  r = |H(f)|^2 / max |H|^2: those few frequencies are damped to kappa, the rest untouched, and
  the step 1/L_P, L_P = 1.02 lambda_max(A P A^T) by power iteration, grows about 4-fold at
  kappa 0.1 (:func:`fourier_preconditioner`). The momentum (POGM or FISTA) is unchanged.
  The prox stays the Euclidean TV prox (the exact one in P's metric would need P^-1 inside
  the TV solver), so the preconditioned iteration alone has a biased fixed point and, where
  the TV term is strong, need not settle. It is therefore only the first phase: it ends
  after 50 iterations without a new lowest objective (``STALL_WINDOW``), when its relative
  change falls below ``tol``, or at once when a step would raise the objective 10 % above its
  lowest (``PREC_RISE``; the step is dropped), whichever comes first; from there on the
  iteration is the plain one (momentum reset, step 1/L), whose fixed point is the minimiser.
  (The metric changes once, so the limit is that of the plain method: the first phase is a
  warm start.) A run whose ``max_iter`` comes first ends in the phase: the protocol's
  noise-free 0 % cases stall only after 1000-1800 iterations, and their 500-iteration results
  are above the accurate reference's in PSNR and objective. On the simulation protocol's
  fixed-tau cases it turns 500 iterations from 0.60 dB below an accurate reference into 0.08
  dB above it on average (docs/simulation-protocol.md). Cost: one more pruned FFT pair per
  preconditioned iteration. "auto" uses kappa 0.1 for a cold start (no ``x0``) of a model
  whose scene enters a 2D convolution first (not the depth model's PSF stack) and is not
  larger than the sensor (a 2x field is left plain: there the phase did damage its rise rule
  could not undo), when the step of the median frequency, p_median L / L_P, grows at least
  1.5-fold (a flat spectrum gains nothing); never with the monotone rule. The live preview (a
  solver that never ends, fed new frames) uses plain steps. A given ``lipschitz=`` is the
  plain steps' L; the phase always computes its own L_P.
- Momentum, ``momentum=``:
  ``"pogm"`` (default): the proximal optimized gradient method (POGM; Taylor, Hendrickx &
  Glineur 2017, Kim & Fessler 2018). With u_{k+1} = x_k - grad f(x_k) / L and theta as
  FISTA's t: z_{k+1} = u_{k+1} + (theta_k - 1)/theta_{k+1} (u_{k+1} - u_k)
  + theta_k/theta_{k+1} (u_{k+1} - x_k) + (theta_k - 1)/(L gamma_k theta_{k+1}) (z_k - x_k),
  x_{k+1} = prox_{gamma_{k+1} tau TV}(z_{k+1}),
  gamma_{k+1} = (2 theta_k + theta_{k+1} - 1)/(L theta_{k+1}). Its worst-case bound is half
  FISTA's (OGM's, optimal for smooth convex problems); at 500 iterations on the simulation
  protocol's noise-free cases it is 1.4 dB closer to a converged reference than FISTA on
  average (up to 4 dB at 0 % erasures), on the noisy ones the same
  (docs/simulation-protocol.md, docs/performance.md).
  ``"fista"``: t_{k+1} = (1 + sqrt(1 + 4 t_k^2)) / 2, y = x_k + (t_k - 1)/t_{k+1} (x_k - x_{k-1})
  (the default before; always used by ``restart="monotone"``).
- One forward and one adjoint per iteration (two rfft2/irfft2 pairs per slice): A x_k is kept
  (FISTA gets A y_{k+1} from it by linearity; POGM evaluates the gradient at x_k itself), so the
  objective of every iterate costs no extra transform.
- Divergence guard: POGM's momentum is stable only up to a step of about 1/||A||^2, so an L
  given too small (``lipschitz=``) makes it diverge or cycle (FISTA up to a step of about
  4/(3 ||A||^2)). Every step checks ||A d||^2 <= L ||d||^2 along its own step d = x_k+1 - x_k
  (A d is A x_k+1 - A x_k, both kept: one more pass over the measurement) and that the
  objective stays below twice that of x = 0 and of the start; if not, the new iterate is
  dropped, L is raised (by half at least) and the momentum reset (``Fista.guard_resets``
  counts it; with the computed L it cannot fire on the first test, and never fired on the
  simulation protocol). The monotone rule needs no guard (it rejects rising steps).
- Adaptive restart (O'Donoghue & Candes), ``restart=``:
  ``"gradient"`` (default): the momentum is reset when the step x_{k+1} - y_k points against
  the momentum x_{k+1} - x_k (FISTA), or the composite gradient grad f(x_k) + (z_{k+1} -
  x_{k+1})/gamma_{k+1} against u_{k+1} - u_k (POGM, Kim & Fessler 2018); the step is kept.
  The test uses no objective value, so the inexact, warm-started TV prox cannot trigger it,
  and no iteration is wasted.
  ``"monotone"`` (the default before): a step that would raise the objective is rejected and
  the momentum reset, so reported objectives never increase; if even a plain
  proximal-gradient step cannot lower it (the inexact TV prox), the inner iterations double,
  and after repeated failures the run stops as ``stalled``. On the simulation protocol it
  fires about every tenth iteration at 99 % erasures (objective noise of the inexact prox),
  never helped PSNR and cost up to 0.1 dB (docs/auto-tau.md). ``"none"``: plain FISTA.
- Stops on a relative change below ``tol`` or at ``max_iter``; every step is a progress report
  and a cancellation point (iterate :meth:`Fista.steps` and stop whenever you like). The
  inexact TV prox leaves a floor under the change: with the default 3 inner iterations it
  can stay above 1e-5 (1e-4 to 3e-5 on the tutorial sample at tau 1e-4), so such runs end at
  ``max_iter``; 20 inner iterations converge there (docs/stability.md).
- Inexact prox at a large tau: a plain-phase step that passes the curvature test but raises
  the objective ``PLAIN_RISE`` (10 %) above its lowest in that phase is the inexact TV prox's
  doing; the step is dropped, the momentum reset and ``prox_iters`` doubled, up to
  ``PROX_ITERS_CAP`` (48; a larger given count is its own cap). ``prox_raises`` counts it and
  ``params["prox_iters_final"]`` records the count the run ended with. Three inner iterations
  used to leave the objective oscillating at 25 where 50 gave 3.5 (tau 0.1, tutorial
  sample); on the simulation protocol it never changes the automatic choice
  (docs/stability.md).
- NaN/inf anywhere raises :class:`NumericalError` naming where it appeared.
- Very large tau: when gamma = tau / L is so large that the exact prox of gamma TV is a
  constant (checked by an explicit dual certificate, :func:`constant_prox`), the constant is
  used instead of the inexact inner solver, which would otherwise need thousands of inner
  iterations there (it used to stall at x = 0).
"""

from __future__ import annotations

import math
import time
from typing import Any, cast

import torch

from recon.operators import Compose, Conv2D, FourierFilter, LinearOperator, power_norm
from recon.stepwise import (
    NumericalError,
    SolverResult,
    SolverStep,
    StepwiseSolver,
    StopReason,
    check_finite,
)
from recon.tv import TV, TVProx

__all__ = [
    "Fista",
    "FistaResult",
    "FistaStep",
    "NumericalError",
    "constant_prox",
]

# FISTA's names for the shared step and result types of recon.stepwise
FistaStep = SolverStep
FistaResult = SolverResult


def constant_prox(tv: TV, z: torch.Tensor, gamma: float, nonneg: bool = True
                  ) -> torch.Tensor | None:
    """The exact prox of ``gamma`` TV (+ x >= 0) at ``z`` when it is constant, else None.

    The prox is the group mean m (per channel, and per k unless TV couples k) exactly when
    z - m = gamma D^T p for some dual p in the unit ball. Such a p is built from cumulative
    sums (along x of z minus its row means, along y of the row means minus m, along k of the
    slice means minus m); if it fits, the mean is the exact prox (clamped at 0 with the
    non-negativity constraint, which is then also exact). A cheap necessary condition
    (|z - m| <= gamma ||D^T||_inf per pixel) skips the check in the usual case (one min/max
    pass over z).
    """
    if gamma <= 0 or z.ndim != 4:
        return None
    couple_k = tv.weight_k > 0 and z.shape[1] > 1
    lo, hi = torch.aminmax(z.flatten(1 if couple_k else 2), dim=-1)
    if float((hi - lo).max()) > gamma * (8.0 + 4.0 * tv.weight_k):
        return None  # some pixel is too far from the mean for any dual in the unit ball
    zd = z.double()
    row = zd.mean(dim=3, keepdim=True)  # (C, K, H, 1)
    px = torch.cumsum(zd - row, dim=3)[..., :-1]
    sl = row.mean(dim=2, keepdim=True)  # (C, K, 1, 1)
    py = torch.cumsum(row - sl, dim=2)[..., :-1, :]
    a = float(px.abs().max()) if px.numel() else 0.0
    b = float(py.abs().max()) if py.numel() else 0.0
    need = math.hypot(a, b) if tv.isotropic else max(a, b)
    mean = sl
    if couple_k:
        mean = sl.mean(dim=1, keepdim=True)  # (C, 1, 1, 1)
        pk = torch.cumsum(sl - mean, dim=1)[:, :-1]
        need = max(need, float(pk.abs().max()) / tv.weight_k)
    if not need <= gamma:
        return None
    out = mean.to(z.dtype).expand(z.shape).clone()
    return out.clamp_(min=0.0) if nonneg else out


class _GramP(LinearOperator):
    """s A P A^T on the measurement space (self-adjoint): its norm over s is L_P / 1.02.

    The scale s = 1 / ||A||^2 keeps the power iteration (which squares the operator) at values
    near 1 whatever the units of the PSF (float32 would underflow at PSF values of 1e-8).
    """

    def __init__(self, op: LinearOperator, prec: LinearOperator, scale: float = 1.0) -> None:
        super().__init__(op.out_shape, op.out_shape, op.dtype, op.device)
        self.op, self.prec, self.scale = op, prec, scale

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        return self.op.apply(self.prec.apply(self.op.adjoint(x))).mul_(self.scale)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        return self.apply(y)


def relative_spectrum(conv: Conv2D) -> torch.Tensor:
    """r(f) = |H(f)|^2 / max |H|^2 of a convolution on its padded grid, per PSF slice.

    The half spectrum of rfft2: what the preconditioner damps, and what the protocol's
    convergence check reports.
    """
    r = conv.hf.real.square() + conv.hf.imag.square()
    return r / r.amax(dim=(-2, -1), keepdim=True).clamp_min(1e-30)


def _median_gain(op: LinearOperator, prec: FourierFilter, lip: float) -> float:
    """How much the preconditioned step grows for the median frequency: p_median L / L_P."""
    return float(prec.mult.median()) * op.lipschitz() / lip


def _kappa(precondition: float | str | None) -> float | None:
    if isinstance(precondition, bool):
        raise ValueError(f"precondition must be 'auto', 'off' or a number in (0, 1], got "
                         f"{precondition!r}")
    if precondition is None or precondition == "off":
        return None
    if precondition == "auto":
        return AUTO_KAPPA
    if isinstance(precondition, str):
        raise ValueError(f"precondition must be 'auto', 'off' or a number in (0, 1], got "
                         f"{precondition!r}")
    kappa = float(precondition)
    if not (math.isfinite(kappa) and 0.0 < kappa <= 1.0):
        raise ValueError(f"precondition (kappa) must be in (0, 1], got {precondition}")
    return kappa


def fourier_preconditioner(op: LinearOperator, kappa: float, required: bool = True
                           ) -> tuple[FourierFilter, float] | None:
    """The Fourier-diagonal preconditioner P of ``op`` and the Lipschitz constant of its step.

    p(f) = min(1, kappa / r(f)) with r = |H(f)|^2 / max |H|^2 of the model's convolution (per
    PSF slice), on its padded grid: the few frequencies next to the DC that set the plain step
    1/||A||^2 are damped to the level kappa, the rest is left alone. P is self-adjoint and
    positive definite (:class:`recon.operators.FourierFilter`); the step of the preconditioned
    gradient x - P grad f(x) / L is safe with L = 1.02 lambda_max(A P A^T) (power iteration).
    Cached on ``op`` per kappa. A model whose scene does not enter a :class:`Conv2D` first has
    no such P: ValueError, or None when not ``required``.
    """
    cache = op.__dict__.setdefault("_fourier_prec", {})
    if kappa in cache:
        return cast(tuple[FourierFilter, float], cache[kappa])
    conv = (op.ops if isinstance(op, Compose) else [op])[-1]
    if not isinstance(conv, Conv2D):
        if not required:
            return None
        raise ValueError("precondition needs a model whose scene enters a 2D convolution first "
                         f"(got {type(conv).__name__})")
    r = relative_spectrum(conv)
    mult = torch.where(r > kappa, kappa / r.clamp_min(1e-30), torch.ones_like(r))
    prec = FourierFilter(conv, mult)
    unit = op.norm() ** 2
    if not (math.isfinite(unit) and unit > 0):
        if not required:
            return None
        raise ValueError(f"the forward model's norm is {unit ** 0.5}: nothing to precondition")
    # ||A P A^T|| is of the order of kappa ||A||^2 (p r <= kappa): scaled by that, the power
    # iteration works at values near 1 for any kappa (unscaled, its squares underflowed
    # float32 to 0 at kappa 1e-15, and the step 1 / L_P divided by zero)
    scale = unit * kappa
    try:
        lip = 1.02 * scale * power_norm(_GramP(op, prec, 1.0 / scale))
    except FloatingPointError:  # 1 / scale beyond the dtype's range
        lip = math.nan
    if not (math.isfinite(lip) and lip > 0):
        if not required:
            return None
        raise ValueError(f"precondition level (kappa) {kappa:g} is too small for {op.dtype}: "
                         "the preconditioned step underflows; use a larger level or 'off'")
    cache[kappa] = (prec, lip)
    return prec, lip


AUTO_KAPPA = 0.1  # the damping level of precondition="auto" (docs/simulation-protocol.md)
AUTO_MIN_GAIN = 1.5  # "auto" only where the median frequency's step grows this much
STALL_WINDOW = 50  # plain steps after 50 preconditioned ones without a new lowest objective
PREC_RISE = 0.1  # ...or once a preconditioned step would raise the objective 10 % above it
#: a plain step that would raise the objective this much above its lowest of the plain phase
#: is the inexact TV prox's doing (the curvature test passed): the step is dropped, the inner
#: iterations double (up to PROX_ITERS_CAP) and the momentum restarts
PLAIN_RISE = 0.1
PROX_ITERS_CAP = 48

RESTART_MODES = ("gradient", "monotone", "none")
MOMENTA = ("pogm", "fista")


def _restart_mode(restart: bool | str) -> str:
    """Normalise ``restart``: True is the default rule ("gradient"), False is "none"."""
    if restart is True:
        return "gradient"
    if restart is False:
        return "none"
    if restart not in RESTART_MODES:
        raise ValueError(f"restart must be one of {', '.join(RESTART_MODES)} (or a bool), "
                         f"got {restart!r}")
    return str(restart)


class Fista(StepwiseSolver):
    """Stepwise FISTA-TV. Use :meth:`step`, iterate :meth:`steps`, or call :meth:`run`."""

    def __init__(
        self,
        op: LinearOperator,
        b: torch.Tensor,
        *,
        tau: float = 1e-3,
        tv: TV | None = None,
        nonneg: bool = True,
        x0: torch.Tensor | None = None,
        max_iter: int = 200,
        tol: float = 1e-5,
        restart: bool | str = "gradient",
        prox_iters: int = 3,
        lipschitz: float | None = None,
        momentum: str | None = None,
        precondition: float | str | None = "auto",
    ) -> None:
        if tuple(b.shape) != op.out_shape:
            raise ValueError(
                f"measurement has shape {tuple(b.shape)}, the model expects {op.out_shape}"
            )
        if not (math.isfinite(tau) and tau >= 0):
            raise ValueError(f"tau must be a finite number >= 0, got {tau}")
        if max_iter < 0:
            raise ValueError(f"max_iter must be >= 0, got {max_iter}")
        if op.dtype not in (torch.float32, torch.float64):
            raise ValueError(
                f"FISTA runs in float32 or float64, not {op.dtype} (the FFTs of the forward "
                "model need it; reduced precision such as bf16 is supported only for the UDN "
                "network, through autocast)"
            )
        self.op = op
        self.b = b.to(dtype=op.dtype, device=op.device)
        check_finite(self.b, "the measurement", 0)
        if not math.isfinite(0.5 * float(torch.sum(self.b * self.b))):
            raise ValueError(
                f"the measurement is too large for {op.dtype} (max |b| = "
                f"{float(self.b.abs().max()):.3g}: its squared norm overflows); normalise it "
                "(recon.io.normalise) or use float64"
            )
        b_max = float(self.b.abs().max()) if self.b.numel() else 0.0
        if 0.0 < b_max and b_max * b_max < torch.finfo(op.dtype).tiny:
            # the residual's squares underflow: the objective is 0 and the run "converges"
            # at once to a wrong result (58-100 % off at max |b| 1e-22 to 1e-30 in float32)
            raise ValueError(
                f"the measurement is too small for {op.dtype} (max |b| = {b_max:.3g}: its "
                "squares underflow); normalise it (recon.io.normalise) or use float64")
        self.tau = float(tau)
        self.tv = tv if tv is not None else TV()
        self.prox = TVProx(self.tv, nonneg=nonneg)
        self.nonneg = nonneg
        self.max_iter = int(max_iter)
        self.tol = float(tol)
        self.restart = _restart_mode(restart)
        if momentum is None:
            momentum = "fista" if self.restart == "monotone" else "pogm"
        if momentum not in MOMENTA:
            raise ValueError(f"momentum must be one of {', '.join(MOMENTA)}, got {momentum!r}")
        if momentum == "pogm" and self.restart == "monotone":
            raise ValueError('restart="monotone" works with momentum="fista" only')
        self.momentum = momentum
        self.prox_iters = int(prox_iters)
        self._prox_iters_given = self.prox_iters
        self._prox_cap = max(PROX_ITERS_CAP, self.prox_iters)
        self.prox_raises = 0  # times the plain phase's rise rule doubled prox_iters
        try:
            self.L = float(lipschitz) if lipschitz is not None else op.lipschitz()
        except FloatingPointError as exc:
            raise NumericalError(
                f"{exc}: the forward model's values are too large for {op.dtype}; normalise "
                "the PSF (for example to unit sum, recon.io.normalise) or use float64"
            ) from exc
        if not (math.isfinite(self.L) and self.L > 0):
            raise ValueError(
                f"operator norm is {self.L} in {op.dtype}: the forward model maps everything to "
                "0, or its values are so small that ||A^T A x|| underflows (a PSF with values "
                "below about 1e-15 in float32); normalise the PSF (for example to unit sum, "
                "recon.io.normalise)"
            )
        self._b_norm = max(float(torch.linalg.vector_norm(self.b)), 1e-30)
        self._L_plain = self.L
        self._prec: LinearOperator | None = None
        self._prec_until = 0  # the last preconditioned iteration (0: none)
        self._f_best_it = 0
        self.precondition: float | None = None
        kappa = _kappa(precondition)
        auto = precondition == "auto"
        # "auto" preconditions cold starts only: not a warm start (it is near the minimiser
        # already; the phase would first move away from it), and not a scene field larger
        # than the sensor (there the convolution's spectrum describes A^T A poorly: on a 2x
        # field the phase left damage its rise rule could not undo, docs/performance.md)
        auto_ok = (x0 is None and len(op.in_shape) == 4
                   and op.in_shape[-2] <= op.out_shape[-2]
                   and op.in_shape[-1] <= op.out_shape[-1])
        if (kappa is not None and self.restart != "monotone" and self.max_iter > 0
                and (auto_ok or not auto)):
            found = fourier_preconditioner(op, kappa, required=not auto)
            if found is not None and (not auto or _median_gain(op, *found) >= AUTO_MIN_GAIN):
                self._prec, self.L = found
                self._prec_until = self.max_iter
                self.precondition = kappa
        with torch.no_grad():
            if x0 is None:
                self.x = op.zeros_in()
            else:
                if tuple(x0.shape) != op.in_shape:
                    raise ValueError(
                        f"warm start has shape {tuple(x0.shape)}, expected {op.in_shape}"
                    )
                self.x = x0.to(dtype=op.dtype, device=op.device).clone()
                check_finite(self.x, "the warm start", 0)
                if nonneg:
                    self.x.clamp_(min=0.0)
            self.Ax = op.apply(self.x)
        # work buffers, reused every step (the iterate itself is a new tensor per step, so a
        # caller's reference to an earlier solver.x never changes)
        self._res = torch.empty_like(self.Ax)  # A y - b (A x - b for POGM), then A x - b
        self._diff = torch.empty_like(self.x)  # x_new - x
        if self.momentum == "fista":
            self.y = self.x.clone()
            self.Ay = torch.empty_like(self.Ax).copy_(self.Ax)
            self._z = torch.empty_like(self.y)  # the gradient step, then y - x_new
        else:
            self._u = self.x.clone()  # u_k, the last gradient step
            self._u_new = torch.empty_like(self.x)
            self._w = torch.zeros_like(self.x)  # z_k - x_k, then z_{k+1}
            self._gamma = 1.0 / self.L
        self.t = 1.0
        self.iteration = 0
        self.guard_resets = 0
        self.objective = self._objective(self.Ax, self.x)[0]
        # the divergence guard's bounds
        self._f_guard = 2.0 * max(self.objective, 0.5 * self._b_norm ** 2)
        self._f_best = self.objective  # the lowest objective of the preconditioned phase
        self._f_plain_best = self.objective  # ...and of the plain phase (PLAIN_RISE)
        # the constant-prox check is tried only while the iterate is constant (TV exactly 0):
        # that is where a huge tau keeps it, and it costs nothing on ordinary runs
        self._x_constant = self._last_tv == 0.0
        self.reason: StopReason | None = StopReason.MAX_ITER if self.max_iter == 0 else None
        self._t0: float | None = None
        self._elapsed = 0.0
        self._stalls = 0

    @property
    def params(self) -> dict[str, Any]:
        """Solver settings, for run records and metadata."""
        return {
            "method": "fista-tv",
            "tau": self.tau,
            "tv": {"isotropic": self.tv.isotropic, "weight_k": self.tv.weight_k},
            "nonneg": self.nonneg,
            "max_iter": self.max_iter,
            "tol": self.tol,
            "restart": self.restart,
            "prox_iters": self._prox_iters_given,
            # the inner iterations the run ended with: more once the rise rule fired
            "prox_iters_final": self.prox_iters,
            "lipschitz": self._L_plain if self._prec is not None else self.L,
            "momentum": self.momentum,
            "precondition": self.precondition,
            "lipschitz_preconditioned": (
                fourier_preconditioner(self.op, self.precondition)[1]  # type: ignore[index]
                if self.precondition is not None else None),
            # the iterations that took preconditioned steps (so far, while the phase is on)
            "preconditioned_iterations": (min(self._prec_until, self.iteration)
                                          if self._prec is not None else self._prec_until),
        }

    def _objective(self, ax: torch.Tensor, x: torch.Tensor) -> tuple[float, float]:
        r = torch.sub(ax, self.b, out=self._res).view(-1)
        data = 0.5 * float(torch.dot(r, r))
        tv = self.prox.value(x) if self.tau > 0 else 0.0
        self._last_tv = tv
        return data + self.tau * tv, data

    def _replace_measurement(self, b: torch.Tensor) -> None:
        self.b = b
        self._b_norm = max(float(torch.linalg.vector_norm(b)), 1e-30)
        self.objective = self._objective(self.Ax, self.x)[0]  # of the kept iterate, new data
        self._stalls = 0
        self._f_guard = 2.0 * max(self.objective, 0.5 * self._b_norm ** 2)
        self._f_best, self._f_best_it = self.objective, self.iteration
        self._f_plain_best = self.objective

    def step(self) -> SolverStep:
        """Do one iteration and report it (raises RunFinished once done)."""
        self._check_running()
        start = time.perf_counter()
        it = self.iteration + 1
        with torch.no_grad():
            if self._prec is not None and it > self._prec_until:
                self._end_preconditioning()
            if self.momentum == "pogm":
                f_report, data, rel, restarted = self._step_pogm(it)
            else:
                f_report, data, rel, restarted = self._step_fista(it)
        self.iteration = it
        self._elapsed += time.perf_counter() - start
        rejected = restarted and self.restart == "monotone"
        if self._prec is None:
            self._f_plain_best = min(self._f_plain_best, f_report)
        else:
            self._watch_preconditioned(it, f_report)
        if not rejected and rel < self.tol and it > 1 and self._prec is not None:
            self._prec_until = it  # the preconditioned phase has converged: plain steps next
            if it >= self.max_iter:
                self.reason = StopReason.MAX_ITER
        elif not rejected and rel < self.tol and it > 1:
            self.reason = StopReason.CONVERGED
        elif self._stalls >= 3:
            self.reason = StopReason.STALLED
        elif it >= self.max_iter:
            self.reason = StopReason.MAX_ITER
        residual = math.sqrt(2.0 * data) / self._b_norm
        return SolverStep(it, f_report, data, residual, rel, self._elapsed, restarted)

    def _reset_momentum(self) -> None:
        self.t = 1.0
        if self.momentum == "fista":
            self.y.copy_(self.x)
            self.Ay.copy_(self.Ax)
        else:
            self._u.copy_(self.x)
            self._w.zero_()
            self._gamma = 1.0 / self.L

    def _watch_preconditioned(self, it: int, f: float) -> None:
        """End the preconditioned phase once its objective stalls (see the module docstring)."""
        if f < self._f_best * (1.0 - 1e-7):
            self._f_best, self._f_best_it = f, it
        elif it - self._f_best_it >= STALL_WINDOW:
            self._prec_until = it

    def _end_preconditioning(self) -> None:
        """Plain steps from here on: the fixed point is then the minimiser (see the docstring)."""
        self._prec = None
        self._prec_until = min(self._prec_until, self.iteration)
        self.L = self._L_plain
        self._reset_momentum()
        self._f_plain_best = self.objective

    def _gradient(self, res: torch.Tensor) -> torch.Tensor:
        grad = self.op.adjoint(res)
        return grad if self._prec is None else self._prec.apply(grad)

    def _prox_step(self, z: torch.Tensor, gamma: float) -> torch.Tensor:
        """x_new = prox of gamma tau TV (+ x >= 0) at z, a new tensor."""
        x_new = (constant_prox(self.tv, z, self.tau * gamma, self.nonneg)
                 if self._x_constant else None)
        if x_new is None:
            x_new = self.prox(z, self.tau * gamma, self.prox_iters, out=torch.empty_like(z))
        return x_new

    def _checked(self, it: int, grad: torch.Tensor, x_new: torch.Tensor
                 ) -> tuple[torch.Tensor, float, float]:
        """A x_new and its objective (data term too); NaN/inf raises, naming where."""
        ax_new = self.op.apply(x_new)
        f_new, data = self._objective(ax_new, x_new)
        if not math.isfinite(f_new):
            check_finite(grad, "the gradient A^T(Ay - b)", it)
            check_finite(x_new, "the TV prox output", it)
            check_finite(ax_new, "the forward model A x", it)
            raise NumericalError(f"FISTA: the objective is {f_new} at iteration {it}")
        return ax_new, f_new, data

    def _diverged(self, f_new: float, dx: float, x_norm: float, ax_new: torch.Tensor) -> bool:
        """Divergence guard (see the module docstring): raise L, reset the momentum.

        It fires when the step d = x_new - x shows L < ||A d||^2 / ||d||^2 (<= ||A||^2), or
        the objective blows up. Steps below 1e-4 of the iterate are not tested: there the
        rounding of A x (float32) would dominate A d. A step that passes but rises too far
        for the inexact prox (:meth:`_prox_too_coarse`) doubles the inner iterations instead.
        True: the step is dropped.
        """
        if self.restart == "monotone":
            return False
        # the curvature test is in the Euclidean metric: with the preconditioner the objective
        # is tested against its lowest so far instead, and a failure ends the preconditioning
        rq = ((float(torch.dist(ax_new, self.Ax)) / dx) ** 2
              if dx > 1e-4 * x_norm and self._prec is None else 0.0)
        bound = (self._f_guard if self._prec is None
                 else min(self._f_guard, (1.0 + PREC_RISE) * self._f_best))
        if rq <= self.L and f_new <= bound:
            if not self._prox_too_coarse(f_new):
                return False
            self.prox_raises += 1
            self.prox_iters = min(2 * self.prox_iters, self._prox_cap)
            self._reset_momentum()
            self.objective = self._objective(self.Ax, self.x)[0]
            return True
        self.guard_resets += 1
        if self._prec is not None:
            self._end_preconditioning()
        else:
            self.L = max(1.5 * self.L, 1.02 * rq)
            self._reset_momentum()
        self.objective = self._objective(self.Ax, self.x)[0]  # leaves A x - b in self._res
        return True

    def _prox_too_coarse(self, f_new: float) -> bool:
        """Whether a plain step raised the objective too far for round-off or momentum.

        Too far: ``PLAIN_RISE`` above its lowest of the plain phase, after the curvature test
        passed, with inner iterations still to add. The step is then the inexact,
        warm-started TV prox's doing: at a large tau three inner iterations leave the
        objective oscillating far above the minimum (docs/stability.md).
        """
        return (self._prec is None and self.tau > 0 and self.prox_iters < self._prox_cap
                and not self._x_constant
                and f_new > (1.0 + PLAIN_RISE) * self._f_plain_best)

    def _step_pogm(self, it: int) -> tuple[float, float, float, bool]:
        inv_l = 1.0 / self.L
        # self._res holds A x - b already: every path leaves it there (the last _objective call
        # of a step, of the divergence guard, of a new measurement and of __init__ is on self.Ax)
        grad = self._gradient(self._res)
        th = self.t
        th_new = (1.0 + math.sqrt(1.0 + 4.0 * th * th)) / 2.0
        u_new = torch.add(self.x, grad, alpha=-inv_l, out=self._u_new)
        # z = u_new + a (u_new - u) + c (u_new - x) + d (z - x), with z - x kept in w and
        # u_new - x = -grad / L: three passes, u_new + a (u_new - u) made in u's buffer
        a = (th - 1.0) / th_new
        c = th / th_new
        z = self._w
        if th > 1.0:
            ext = self._u.lerp_(u_new, 1.0 + a)
            torch.add(ext, z, alpha=(th - 1.0) / (th_new * self.L * self._gamma), out=z)
            z.add_(grad, alpha=-c * inv_l)
        else:
            torch.add(u_new, grad, alpha=-c * inv_l, out=z)
        gamma = (2.0 * th + th_new - 1.0) / (th_new * self.L)
        x_new = self._prox_step(z, gamma)
        ax_new, f_new, data = self._checked(it, grad, x_new)
        dx = float(torch.dist(x_new, self.x))
        x_norm = float(torch.linalg.vector_norm(x_new))
        if self._diverged(f_new, dx, x_norm, ax_new):
            return self.objective, self._objective(self.Ax, self.x)[1], math.inf, True
        rel = dx / max(x_norm, 1e-30)
        z.sub_(x_new)  # w = z_{k+1} - x_{k+1}: gamma times the TV (+ bound) subgradient
        restarted = False
        if self.restart == "gradient" and th > 1.0:
            # the composite gradient grad f(x_k) + w / gamma against the momentum u_new - u,
            # which is a positive multiple (1/a) of ext - u_new (u's buffer holds ext)
            du = self._u.sub_(u_new)
            g_dot = float(torch.dot(grad.reshape(-1), du.view(-1))) + float(
                torch.dot(z.view(-1), du.view(-1))) / gamma
            if g_dot > 0.0:
                restarted = True
                th_new = 1.0
        self._u, self._u_new = u_new, self._u
        self.x, self.Ax, self.t, self._gamma = x_new, ax_new, th_new, gamma
        self.objective = f_new
        self._x_constant = self._last_tv == 0.0
        return f_new, data, rel, restarted

    def _step_fista(self, it: int) -> tuple[float, float, float, bool]:
        grad = self._gradient(torch.sub(self.Ay, self.b, out=self._res))
        z = torch.add(self.y, grad, alpha=-1.0 / self.L, out=self._z)
        x_new = self._prox_step(z, 1.0 / self.L)
        ax_new, f_new, data = self._checked(it, grad, x_new)
        diff = torch.sub(x_new, self.x, out=self._diff)
        dx = float(torch.linalg.vector_norm(diff))
        x_norm = float(torch.linalg.vector_norm(x_new))
        if self.restart != "monotone" and self._diverged(f_new, dx, x_norm, ax_new):
            return self.objective, self._objective(self.Ax, self.x)[1], math.inf, True
        restarted = False
        if self.restart == "monotone" and f_new > self.objective:
            restarted = True
            if self.t > 1.0:
                self._stalls = 0
            else:  # plain prox-gradient step failed: tighten the inexact prox
                self._stalls += 1
                # doubled as the other rise rule does, up to the same cap (it reached 3072
                # inner iterations per step on a 64x64 case)
                self.prox_iters = min(2 * self.prox_iters, self._prox_cap)
            self.t = 1.0
            self.y.copy_(self.x)
            self.Ay.copy_(self.Ax)
            data = self._objective(self.Ax, self.x)[1]
            return self.objective, data, 0.0, True
        self._stalls = 0
        rel = dx / max(x_norm, 1e-30)
        # gradient restart (O'Donoghue & Candes): the step x_new - y (minus the
        # gradient mapping) points against the momentum x_new - x: reset t and keep
        # the step; it uses no objective value, so the inexact prox cannot trigger it
        if (self.restart == "gradient" and self.t > 1.0
                and float(torch.dot(torch.sub(self.y, x_new, out=self._z).view(-1),
                                    diff.view(-1))) > 0.0):
            restarted = True
            self.t = 1.0
        t_new = (1.0 + math.sqrt(1.0 + 4.0 * self.t * self.t)) / 2.0
        beta = (self.t - 1.0) / t_new
        torch.add(x_new, diff, alpha=beta, out=self.y)
        torch.lerp(self.Ax, ax_new, 1.0 + beta, out=self.Ay)  # A x_new + beta (A x_new - A x)
        self.x, self.Ax, self.t = x_new, ax_new, t_new
        self.objective = f_new
        self._x_constant = self._last_tv == 0.0
        return f_new, data, rel, restarted
