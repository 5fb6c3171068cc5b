"""ADMM-TV for the 2D and masked-2D models: the DiffuserCam variable splitting, stepwise.

Solves the same problem as :class:`recon.fista.Fista`,

    min_v  0.5 ||m . crop(h * v) - b||^2 + tau TV(v),   v >= 0, v supported on the field,

with the splitting of Antipa et al. (DiffuserCam, 2018) on the padded FFT grid P:
x = M v (convolution), u = Psi v (circular differences), w = v (non-negativity and support).
Every update is closed form: u a soft threshold, x a pixelwise division (the crop and the
erasure mask are diagonal), w a projection, and v one division in Fourier space, because M and
Psi are circulant on P. One iteration costs two rfft2/irfft2 pairs per channel, like FISTA.

To minimise exactly FISTA's objective, the TV penalty applies only to differences between two
pixels of the field (Neumann TV of the field): the differences that cross the field's edge or
lie outside it are split off but not penalised, and w keeps v zero outside the field.

The reported objective is that of ADMM's internal iterate v (computed from M v, which the
iteration has anyway); the returned estimate is v on the field, clamped at 0. Near
convergence they agree; early on, score the returned estimate yourself (the trade does).

Penalties: mu1 = s (x = M v), mu2 = mu3 = s ``rho`` max|H|^2 (u = Psi v, w = v), fixed; s is
``penalty``, by default (``"auto"``, :func:`penalty_scale`) the geometric mean of the two terms'
scales, sqrt(f tau_rel / TAU_REF) within [PENALTY_MIN, 1]: f the measured share of the sensor's
extent (the data term's curvature per pixel of x, 1 where measured and 0 where not), tau_rel
tau over max |b| (and the PSF's peak). The former fixed s = 1 (rho 0.01) fits tau_rel 1e-3
on a full sensor and left ADMM far from its minimum at weaker tau and on erased sensors: after
500 iterations at the automatic tau, on the simulation protocol's scenes with 1 % noise, 1.2 dB
below FISTA-TV at 0 % erasures and 3.6 / 6.1 dB at 95 / 99 %, 16.7 dB at 0 % without noise;
with the rule within 0.1 dB of it on every noisy simulated and real level but the real 99 %
(0.17 dB below), 0.5 dB below at 99 % without noise (``lenslesscam bench admm-penalty``,
docs/stability.md, "ADMM's penalty"). (Residual balancing was tried before and converged
worse on the simulation protocol.) A fixed penalty enforces a strong TV term slowly:
at a huge tau (u = 0 on the field, s = 1) the default rho 0.01 leaves a far from flat image
after 300 iterations where the minimiser is flat (rho 1 reaches it); the commands warn when
the result's objective is above a flat image's.

Stop: ``converged`` once the relative change of v and the primal residuals of the three
splittings (M v - x relative to ||M v||, Psi v - u and v - w relative to ||v||) are all below
``tol``; the residuals are measured only once the change is below it (two more passes per
split variable then, none before). On the change alone a run at tau 10 stopped 10 % above the
flat minimiser's objective.
"""

from __future__ import annotations

import math
import time
from typing import Any

import torch

from recon.models import ForwardModel, ModelKind
from recon.operators import Conv2D, Crop
from recon.stepwise import NumericalError, SolverStep, StepwiseSolver, StopReason, check_finite
from recon.tv import TV

__all__ = ["PENALTY_MIN", "TAU_REF", "Admm", "penalty_scale"]

#: the relative tau at which the penalty scale is 1 on a fully measured sensor (the former
#: fixed penalty, best there among 1 / 0.3 / 0.1 / 0.03 / 0.01 on a simulated scene)
TAU_REF = 1e-3
#: the smallest penalty scale the rule gives: a guard for a tiny tau (the rule's own value did
#: best down to 0.0018, the smallest measured: tau 3e-7 at 99 % erasures without noise)
PENALTY_MIN = 1e-3


def penalty_scale(tau: float, b_max: float, measured: Any = None, h_peak: float = 1.0
                  ) -> float:
    """ADMM's penalty scale s for ``tau`` on a measurement of max |b| ``b_max``.

    sqrt(f tau_rel / TAU_REF) within [PENALTY_MIN, 1], f the measured share of the sensor's
    extent (the bounding box of the ``measured`` pixels, a boolean (H, W) or (C, H, W) array;
    1 when None), tau_rel = tau / (b_max h_peak), h_peak = max |H| (the PSF's sum for a
    non-negative PSF; 1 for a unit-sum one): the objective with the PSF scaled by a and b by
    beta is the same problem with tau scaled by a beta. The geometric mean of the data
    term's curvature per pixel of x and the regulariser's weight, the rule of thumb for a
    penalty between two curvatures (Ghadimi et al., IEEE TAC 60:644, 2015, for quadratic
    problems); the constant TAU_REF is measured.
    tau 0 (least squares, no regulariser to balance) keeps the former scale 1.
    """
    import numpy as np

    from recon.holdout import sensor_extent

    f = 1.0
    box = None if measured is None else sensor_extent(measured)
    if box is not None:
        f = float(np.asarray(measured, dtype=bool)[..., box[0], box[1]].mean())
    rel = tau / (b_max * h_peak) if b_max > 0 and h_peak > 0 else 0.0
    if rel <= 0:  # no regulariser to balance: the data term's own scale (least squares)
        return 1.0
    return float(min(1.0, max(PENALTY_MIN, math.sqrt(f * rel / TAU_REF))))


class Admm(StepwiseSolver):
    """Stepwise ADMM-TV on a 2D (optionally masked) forward model."""

    def __init__(
        self,
        model: ForwardModel,
        b: torch.Tensor,
        *,
        tau: float = 1e-3,
        tv: TV | None = None,
        nonneg: bool = True,
        max_iter: int = 200,
        tol: float = 1e-5,
        rho: float = 0.01,
        penalty: float | str = "auto",
    ) -> None:
        if model.kind is not ModelKind.TWO_D:
            raise ValueError(f"ADMM-TV handles the 2d model (with or without a mask), not "
                             f"{model.kind.value}")
        if tuple(b.shape) != model.meas_shape:
            raise ValueError(
                f"measurement has shape {tuple(b.shape)}, the model expects {model.meas_shape}"
            )
        if not (math.isfinite(tau) and tau >= 0):
            raise ValueError(f"tau must be a finite number >= 0, got {tau}")
        if not (math.isfinite(rho) and rho > 0):
            raise ValueError(f"rho must be > 0, got {rho}")
        if penalty != "auto" and not (isinstance(penalty, (int, float))
                                      and math.isfinite(penalty) and penalty > 0):
            raise ValueError(f"penalty must be 'auto' or a number > 0, got {penalty!r}")
        self.tv = tv if tv is not None else TV()
        if self.tv.weight_k:
            raise ValueError("ADMM-TV is 2D: TV weight along k must be 0")
        conv = next(o for o in model.op.ops if isinstance(o, Conv2D))  # type: ignore[attr-defined]
        crop = next(o for o in model.op.ops if isinstance(o, Crop))  # type: ignore[attr-defined]
        self.model, self.conv, self.crop = model, conv, crop
        dt, dev = conv.dtype, conv.device
        self.b = b.to(dtype=dt, device=dev)
        check_finite(self.b, "the measurement", 0, "ADMM")
        self.tau, self.nonneg, self.max_iter, self.tol = float(tau), nonneg, int(max_iter), tol
        c = model.meas_shape[0]
        py, px = conv.pad
        hs, ws = model.scene_shape[-2:]
        grid = (c, 1, py, px)
        # diagonal data operator C^T C and C^T b on the padded grid
        m = model.mask if model.mask is not None else torch.ones(model.meas_shape[-2:])
        m = m.to(dtype=dt, device=dev).expand(model.meas_shape)
        self.ctc = torch.zeros(grid, dtype=dt, device=dev)
        self.ctb = torch.zeros(grid, dtype=dt, device=dev)
        sy, sx = crop.sl
        self.ctc[:, 0, sy, sx] = m
        self.ctb[:, 0, sy, sx] = m * self.b
        self.support = torch.zeros((py, px), dtype=dt, device=dev)
        self.support[:hs, :ws] = 1.0
        fy = torch.arange(py, dtype=dt, device=dev)[:, None]
        fx = torch.arange(px // 2 + 1, dtype=dt, device=dev)[None, :]
        self.psi2 = (2 - 2 * torch.cos(2 * math.pi * fy / py)) + (2 - 2 * torch.cos(
            2 * math.pi * fx / px))
        self.h2 = conv.hf.abs() ** 2
        self.hmax = float(self.h2.max())
        if self.hmax == 0:
            raise ValueError("the PSF's transfer function is zero")
        if penalty == "auto":
            b_max = float(self.b.abs().max())
            measured = None if model.mask is None else (model.mask > 0).cpu().numpy()
            scale = penalty_scale(self.tau, b_max, measured, math.sqrt(self.hmax))
            self.penalty_rule = "auto"
        else:
            scale, self.penalty_rule = float(penalty), "given"
        self.penalty = scale
        self.mu1, self.mu2, self.mu3 = scale, scale * rho * self.hmax, scale * rho * self.hmax
        # the penalties, their inverses, the denominator (up to 9 mu2) and the threshold
        # tau / mu2 must all be numbers of the dtype
        fi = torch.finfo(dt)
        if fi.tiny <= self.mu2 <= fi.max / 16 and not self.tau / self.mu2 <= fi.max:
            raise ValueError(  # the penalty is in range: tau is what is out of it
                f"tau {self.tau:g} over ADMM's penalty {self.mu2:.3g} is outside the range of "
                f"{dt}: give a tau of at most 1 (the measurement is scaled to max 1)")
        if not (fi.tiny <= self.mu2 <= fi.max / 16 and self.tau / self.mu2 <= fi.max):
            raise ValueError(
                f"rho {rho:g} (penalty scale {scale:g}) puts ADMM's penalty (scale x rho "
                f"max|H|^2 = {self.mu2:.3g}, TV threshold tau / penalty = "
                f"{self.tau / self.mu2:.3g}) outside the range of {dt}; use a rho nearer the "
                "default 0.01" + ("" if penalty == "auto" else " or --penalty auto"))
        self.xi = torch.zeros(grid, dtype=dt, device=dev)
        self.eta_s = torch.zeros((2, *grid), dtype=dt, device=dev)  # eta / mu2, stacked (y, x)
        self.rho_d = torch.zeros(grid, dtype=dt, device=dev)
        # constants of the closed-form updates, computed once
        self.inv_x = 1.0 / (self.ctc + self.mu1)
        self.ctb_x = self.ctb * self.inv_x
        # the same on the sensor window, compact (the step reads only these)
        self._inv_x_win = self.inv_x[..., sy, sx].clone()
        self._ctb_x_win = self.ctb_x[..., sy, sx].clone()
        self.inv_denom = 1.0 / (self.mu1 * self.h2 + self.mu2 * self.psi2 + self.mu3)
        self._g0 = self.conv.hf_conj * self.inv_denom  # conj(H) / denom, complex
        # mu2 / denom for each (real, imaginary) pair, stored at the pairs' full size: a
        # broadcast over the trailing pair axis ran several times slower (1 thread, CPU)
        g1 = (self.mu2 * self.inv_denom)[..., None]
        self._g1_ri = g1.expand(*g1.shape[:-1], 2).contiguous()
        self._thr = self.tau / self.mu2
        if self._thr < torch.finfo(dt).tiny:  # rounds to 0 in the dtype: 1 - thr / 0 was NaN
            self._thr = 0.0  # (--tau 1e-300); no shrink below the smallest normal number
        # work buffers, reused every step
        self.psi_v = torch.zeros((2, *grid), dtype=dt, device=dev)  # Psi v of the current v
        self._psi_next = torch.empty_like(self.psi_v)
        self._u = torch.empty_like(self.psi_v)
        self._rhs = torch.empty_like(self.psi_v)
        self._n = torch.empty((*grid[:2], hs - 1, ws - 1), dtype=dt, device=dev)
        self._edge = torch.empty((*grid[:2], max(hs, ws)), dtype=dt, device=dev)
        self._r = torch.empty(model.meas_shape, dtype=dt, device=dev)  # the data residual
        self._masked = model.mask is not None
        # the field's TV differences (last row / column stay 0) and their magnitudes
        self._tvg = [torch.zeros(model.scene_shape, dtype=dt, device=dev) for _ in range(2)]
        self._tvn = torch.empty(model.scene_shape, dtype=dt, device=dev)
        self._w = torch.zeros(grid, dtype=dt, device=dev)  # stays 0 outside the field
        self._one = torch.ones((), dtype=dt, device=dev)
        u = self._u
        self._shrink_views = (u[..., : hs - 1, : ws - 1], u[0][..., : hs - 1, : ws - 1],
                              u[1][..., : hs - 1, : ws - 1], u[0][..., : hs - 1, ws - 1],
                              u[1][..., hs - 1, : ws - 1])
        r1 = self._rhs[1]
        self._psi_t_views = (
            (u[0][..., :-1, :], u[0][..., 1:, :], r1[..., 1:, :]),
            (u[0][..., -1:, :], u[0][..., :1, :], r1[..., :1, :]),
            u[1], (r1[..., 1:], u[1][..., :-1]), (r1[..., :1], u[1][..., -1:]))
        self.v = torch.zeros(grid, dtype=dt, device=dev)
        self.mv = torch.zeros(grid, dtype=dt, device=dev)
        self.iteration, self._elapsed = 0, 0.0
        self.reason: StopReason | None = StopReason.MAX_ITER if self.max_iter == 0 else None
        self._b_norm = max(float(torch.linalg.vector_norm(self.b)), 1e-30)
        self.x = self._estimate()

    @property
    def params(self) -> dict[str, Any]:
        """Solver settings, for run records and metadata."""
        return {"method": "admm-tv", "tau": self.tau,
                "tv": {"isotropic": self.tv.isotropic, "weight_k": 0.0},
                "nonneg": self.nonneg, "max_iter": self.max_iter, "tol": self.tol,
                "mu": [self.mu1, self.mu2, self.mu3], "penalty": self.penalty,
                "penalty_rule": self.penalty_rule}

    def _replace_measurement(self, b: torch.Tensor) -> None:
        self.b = b
        sy, sx = self.crop.sl
        self.ctb[:, 0, sy, sx] = self.ctc[:, 0, sy, sx] * b
        torch.mul(self.ctb, self.inv_x, out=self.ctb_x)
        self._ctb_x_win.copy_(self.ctb_x[..., sy, sx])
        self._b_norm = max(float(torch.linalg.vector_norm(b)), 1e-30)

    def _psi_into(self, v: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
        """Set out = Psi v (circular forward differences along y, x), stacked (2, ...)."""
        torch.sub(v[..., 1:, :], v[..., :-1, :], out=out[0][..., :-1, :])
        torch.sub(v[..., :1, :], v[..., -1:, :], out=out[0][..., -1:, :])
        torch.sub(v[..., 1:], v[..., :-1], out=out[1][..., :-1])
        torch.sub(v[..., :1], v[..., -1:], out=out[1][..., -1:])
        return out

    def _psi_t_into_rhs1(self) -> torch.Tensor:
        """Set the second FFT input to Psi^T q, q being in u's buffer.

        Per direction, (q shifted by +1) - q, circular. The y part is written directly (one
        pass), the x part added (two); the views are made once (``_psi_t_views``).
        """
        out = self._rhs[1]
        (a1, b1, o1), (a2, b2, o2), q1, (o3, s3), (o4, s4) = self._psi_t_views
        torch.sub(a1, b1, out=o1)
        torch.sub(a2, b2, out=o2)
        out.sub_(q1)
        o3.add_(s3)
        o4.add_(s4)
        return out

    @staticmethod
    def _soft(z: torch.Tensor, thr: float, work: torch.Tensor) -> None:
        """Soft threshold in place: z - clip(z, -thr, thr) (``work``: a buffer of z's size)."""
        e = work.view(-1)[: z.numel()].view(z.shape)
        z.sub_(torch.clamp(z, -thr, thr, out=e))

    def _shrink_u(self) -> torch.Tensor:
        """Shrink the buffer u (stacked y, x) in place: the prox of thr times the field's TV.

        Only differences between two field pixels are penalised: the (y, x) pairs of the field
        without its last row and column (a group shrink when isotropic), the y differences of
        its last column and the x differences of its last row (scalar shrinks). Everything
        else (about 3/4 of the padded grid) passes unchanged, so it is not touched. The views
        are made once (``_shrink_views``), not every step.
        """
        z = self._u
        thr = self._thr
        if thr <= 0:
            return z
        pair, zy, zx, edge_y, edge_x = self._shrink_views
        if self.tv.isotropic:
            # z * (1 - thr / max(|z|, thr)): the group shrink without a division by zero
            n = torch.hypot(zy, zx, out=self._n).clamp_(min=thr)
            torch.addcdiv(self._one, self._one, n, value=-thr, out=n)
            pair.mul_(n)  # both directions at once
        else:
            self._soft(zy, thr, self._n)
            self._soft(zx, thr, self._n)
        self._soft(edge_y, thr, self._edge)
        self._soft(edge_x, thr, self._edge)
        return z

    def _tv_value(self, x: torch.Tensor) -> float:
        """TV(x) of the field, as :meth:`TV.value`, in preallocated buffers."""
        g = self.tv.grad(x, out=self._tvg)
        if self.tv.isotropic:
            return float(torch.hypot(g[0], g[1], out=self._tvn).sum())
        return float(torch.abs(g[0], out=self._tvn).sum() + torch.abs(g[1], out=self._tvn).sum())

    def _estimate(self) -> torch.Tensor:
        hs, ws = self.model.scene_shape[-2:]
        x = self.v[..., :hs, :ws]
        return x.clamp(min=0.0) if self.nonneg else x.clone()  # a new tensor either way

    def _dual_updates(self, mv_new: torch.Tensor, r0: torch.Tensor, v_new: torch.Tensor,
                      q: torch.Tensor, w: torch.Tensor, v_norm: float, *, measure: bool
                      ) -> float:
        """The three dual updates; with ``measure``, also the largest primal residual.

        xi + mu1 (M v - x) = mu1 M v - r0; eta / mu2 + Psi v - u = Psi v - q;
        rho + mu3 (v - w). The primal residuals M v - x, Psi v - u and v - w are the dual
        steps over their penalties: measured (``measure``), each new dual is made in the spent
        right-hand-side buffers and compared with the old one (two more passes per variable),
        and the result is the largest residual relative to ||M v|| (the first) or ||v|| (the
        others). Without ``measure`` the updates are in place and the result is 0.
        """
        mu1, mu3 = self.mu1, self.mu3
        hs, ws = self.model.scene_shape[-2:]
        primal = 0.0
        rhs = self._rhs  # both right-hand sides went into the FFTs: free, except r0 (rhs[0])
        xi_new = rhs[1] if measure else self.xi
        if mu1 == 1.0:
            torch.sub(mv_new, r0, out=xi_new)
        else:
            torch.sub(r0, mv_new, alpha=mu1, out=xi_new).neg_()
        if measure:
            mv_norm = max(float(torch.linalg.vector_norm(mv_new)), 1e-30)
            primal = float(torch.dist(xi_new, self.xi)) / mu1 / mv_norm
            self.xi.copy_(xi_new)
        psi_new = self._psi_into(v_new, self._psi_next)
        if measure:
            torch.sub(psi_new, q, out=rhs)  # r0 is spent now
            primal = max(primal, float(torch.dist(rhs, self.eta_s)) / max(v_norm, 1e-30))
            self.eta_s.copy_(rhs)
            # w is 0 off the field, where v should be 0 too
            primal = max(primal, float(torch.dist(v_new, w)) / max(v_norm, 1e-30))
        else:
            torch.sub(psi_new, q, out=self.eta_s)
        self.rho_d.add_(v_new, alpha=mu3)
        self.rho_d[..., :hs, :ws].sub_(w[..., :hs, :ws], alpha=mu3)  # w is 0 off the field
        return primal

    def step(self) -> SolverStep:
        """Do one iteration and report it (raises RunFinished once done).

        Two rfft2/irfft2 pairs (the two right-hand sides forward, v and M v back, one call
        each) and about twenty passes over the padded grid, into preallocated buffers where
        torch allows it; the duals eta and rho enter scaled so that no pass only rescales.
        """
        self._check_running()
        t0 = time.perf_counter()
        it = self.iteration + 1
        mu1, mu2, mu3 = self.mu1, self.mu2, self.mu3
        pad = self.conv.pad
        with torch.no_grad():
            # u = shrink(Psi v + eta / mu2); the scaled dual eta / mu2 is what is stored
            u = torch.add(self.psi_v, self.eta_s, out=self._u)
            self._shrink_u()
            q = u.sub_(self.eta_s)  # u - eta / mu2 = (mu2 u - eta) / mu2, in u's buffer
            # x = (C^T b + mu1 M v + xi) / (C^T C + mu1) is only needed as the first FFT input
            # mu1 x - xi (the xi update below reads that input back), so it goes straight there
            # Off the sensor window C^T C = 0, so there mu1 x - xi = mu1 M v: one pass over
            # the grid, and the full update only on the window (a quarter of it)
            rhs = self._rhs
            r0 = rhs[0].copy_(self.mv) if mu1 == 1.0 else torch.mul(self.mv, mu1, out=rhs[0])
            sy, sx = self.crop.sl
            rw, xiw = r0[..., sy, sx], self.xi[..., sy, sx]
            torch.add(xiw, self.mv[..., sy, sx], alpha=mu1, out=rw)
            torch.addcmul(self._ctb_x_win, rw, self._inv_x_win, out=rw)
            rw.sub_(xiw, alpha=1.0 / mu1)
            if mu1 != 1.0:
                rw.mul_(mu1)
            # w = P(v + rho / mu3): computed on the field, 0 outside (set once)
            w = self._w
            hs, ws = self.model.scene_shape[-2:]
            wf = torch.add(self.v[..., :hs, :ws], self.rho_d[..., :hs, :ws], alpha=1.0 / mu3,
                           out=w[..., :hs, :ws])
            if self.nonneg:
                wf.clamp_(min=0.0)
            # spatial right-hand side Psi^T (mu2 u - eta) + mu3 w - rho, over mu2 (the factor
            # goes back in Fourier space, for free): Psi^T q + (mu3 w - rho) / mu2
            r1 = self._psi_t_into_rhs1()  # Psi^T q
            r1.sub_(self.rho_d, alpha=1.0 / mu2)
            r1[..., :hs, :ws].add_(w[..., :hs, :ws], alpha=mu3 / mu2)  # w is 0 off the field
            # one rfft2 per right-hand side: a batched call over the stacked pair cost about
            # 1.9x two single ones (torch's batched pocketfft path, and above 32 MB a fresh
            # mmap per call), measured at 512^2 and 2048^2 padded
            f0 = torch.fft.rfft2(r0)
            f1 = torch.fft.rfft2(r1)
            # v^ = (conj(H) f0 + mu2 f1) / denom, with conj(H) / denom and mu2 / denom
            # precomputed: one complex multiply in place, one real multiply-add on the
            # (real, imaginary) pairs, no complex temporary
            f0.mul_(self._g0)
            torch.view_as_real(f0).addcmul_(torch.view_as_real(f1), self._g1_ri)
            torch.mul(f0, self.conv.hf, out=f1)  # (M v)^, into the spent f1
            v_new = torch.fft.irfft2(f0, s=pad)
            mv_new = torch.fft.irfft2(f1, s=pad)
            v_norm = float(torch.linalg.vector_norm(v_new))
            if not math.isfinite(v_norm):
                raise NumericalError(f"ADMM: NaN/inf values appeared in the v update at "
                                     f"iteration {it}")
            dv = float(torch.dist(v_new, self.v))
            rel = dv / max(v_norm, 1e-30)
            # the change alone is not convergence: with a fixed penalty v can move slowly while
            # a splitting is far from met (a huge tau: u = 0 on the field, Psi v not), so once
            # it is below tol the primal residuals are measured too (no cost before)
            primal = self._dual_updates(mv_new, r0, v_new, q, w, v_norm,
                                        measure=rel < self.tol and it > 1)
            self._psi_next, self.psi_v = self.psi_v, self._psi_next  # Psi v_new
            self.v, self.mv = v_new, mv_new
            self.x = self._estimate()
            r = torch.sub(self.mv[:, 0, sy, sx], self.b, out=self._r)
            if self._masked:
                r.mul_(self.ctc[:, 0, sy, sx])
            rf = r.view(-1)
            data = 0.5 * float(torch.dot(rf, rf))
            obj = data + (self.tau * self._tv_value(self.x) if self.tau > 0 else 0.0)
            if not math.isfinite(obj):
                raise NumericalError(f"ADMM: the objective is {obj} at iteration {it}")
        self.iteration = it
        self._elapsed += time.perf_counter() - t0
        if rel < self.tol and it > 1 and primal < self.tol:
            self.reason = StopReason.CONVERGED
        elif it >= self.max_iter:
            self.reason = StopReason.MAX_ITER
        return SolverStep(it, obj, data, math.sqrt(2 * data) / self._b_norm, rel, self._elapsed,
                          False)
