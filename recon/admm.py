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

Penalties: mu1 = 1 (x = M v), mu2 = mu3 = ``rho`` * max|H|^2 (u = Psi v, w = v), fixed.
(Residual balancing was tried and converged worse on the simulation protocol.)
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

__all__ = ["Admm"]


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
        self.tv_y = torch.zeros((py, px), dtype=dt, device=dev)
        self.tv_y[: hs - 1, :ws] = 1.0  # vertical differences inside the field
        self.tv_x = torch.zeros((py, px), dtype=dt, device=dev)
        self.tv_x[:hs, : ws - 1] = 1.0
        fy = torch.arange(py, dtype=dt, device=dev)[:, None]
        fx = torch.arange(px // 2 + 1, dtype=dt, device=dev)[None, :]
        self.psi2 = (2 - 2 * torch.cos(2 * math.pi * fy / py)) + (2 - 2 * torch.cos(
            2 * math.pi * fx / px))
        self.h2 = conv.hf.abs() ** 2
        self.hmax = float(self.h2.max())
        if self.hmax == 0:
            raise ValueError("the PSF's transfer function is zero")
        self.mu1, self.mu2, self.mu3 = 1.0, rho * self.hmax, rho * self.hmax
        self.xi = torch.zeros(grid, dtype=dt, device=dev)
        self.eta = torch.zeros((2, *grid), dtype=dt, device=dev)  # stacked (y, x)
        self.rho_d = torch.zeros(grid, dtype=dt, device=dev)
        # constants of the closed-form updates, computed once
        self.inv_x = 1.0 / (self.ctc + self.mu1)
        self.ctb_x = self.ctb * self.inv_x
        self.inv_denom = 1.0 / (self.mu1 * self.h2 + self.mu2 * self.psi2 + self.mu3)
        self._inv_denom_ri = self.inv_denom[..., None]  # over (real, imaginary) pairs
        self._thr = self.tau / self.mu2
        # work buffers, reused every step
        self.psi_v = torch.zeros((2, *grid), dtype=dt, device=dev)  # Psi v of the current v
        self._psi_next = torch.empty_like(self.psi_v)
        self._u = torch.empty_like(self.psi_v)
        self._q = torch.empty_like(self.psi_v)
        self._rhs = torch.empty_like(self.psi_v)
        self._n = torch.empty((*grid[:2], hs - 1, ws - 1), dtype=dt, device=dev)
        self._edge = torch.empty((*grid[:2], max(hs, ws)), dtype=dt, device=dev)
        self._x = torch.empty(grid, dtype=dt, device=dev)
        self._w = torch.zeros(grid, dtype=dt, device=dev)  # stays 0 outside the field
        self._vf = torch.empty((2, *grid[:-1], px // 2 + 1), dtype=conv.hf.dtype, device=dev)
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
                "mu": [self.mu1, self.mu2, self.mu3]}

    def _replace_measurement(self, b: torch.Tensor) -> None:
        self.b = b
        sy, sx = self.crop.sl
        self.ctb[:, 0, sy, sx] = self.ctc[:, 0, sy, sx] * b
        torch.mul(self.ctb, self.inv_x, out=self.ctb_x)
        self._b_norm = max(float(torch.linalg.vector_norm(b)), 1e-30)

    def _psi_into(self, v: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
        """Set out = Psi v (circular forward differences along y, x), stacked (2, ...)."""
        torch.sub(v[..., 1:, :], v[..., :-1, :], out=out[0][..., :-1, :])
        torch.sub(v[..., :1, :], v[..., -1:, :], out=out[0][..., -1:, :])
        torch.sub(v[..., 1:], v[..., :-1], out=out[1][..., :-1])
        torch.sub(v[..., :1], v[..., -1:], out=out[1][..., -1:])
        return out

    def _psi_t_add(self, q: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
        """Add Psi^T q to out: per direction, (q shifted by +1) - q, circular."""
        out.sub_(q[0]).sub_(q[1])
        out[..., 1:, :].add_(q[0][..., :-1, :])
        out[..., :1, :].add_(q[0][..., -1:, :])
        out[..., 1:].add_(q[1][..., :-1])
        out[..., :1].add_(q[1][..., -1:])
        return out

    @staticmethod
    def _soft(z: torch.Tensor, thr: float, work: torch.Tensor) -> None:
        """Soft threshold in place: z - clip(z, -thr, thr) (``work``: a buffer of z's size)."""
        e = work.view(-1)[: z.numel()].view(z.shape)
        z.sub_(torch.clamp(z, -thr, thr, out=e))

    def _shrink_into(self, z: torch.Tensor) -> torch.Tensor:
        """Shrink z (stacked y, x) in place: the prox of thr times the field's TV term.

        Only differences between two field pixels are penalised: the (y, x) pairs of the field
        without its last row and column (a group shrink when isotropic), the y differences of
        its last column and the x differences of its last row (scalar shrinks). Everything
        else (about 3/4 of the padded grid) passes unchanged, so it is not touched.
        """
        thr = self._thr
        if thr <= 0:
            return z
        hs, ws = self.model.scene_shape[-2:]
        zy, zx = z[0][..., : hs - 1, : ws - 1], z[1][..., : hs - 1, : ws - 1]
        if self.tv.isotropic:
            # z * (1 - thr / max(|z|, thr)): the group shrink without a division by zero
            n = torch.hypot(zy, zx, out=self._n).clamp_(min=thr)
            n.reciprocal_().mul_(-thr).add_(1.0)
            zy.mul_(n)
            zx.mul_(n)
        else:
            self._soft(zy, thr, self._n)
            self._soft(zx, thr, self._n)
        # last field column: y differences only; last field row: x differences only
        self._soft(z[0][..., : hs - 1, ws - 1], thr, self._edge)
        self._soft(z[1][..., hs - 1, : ws - 1], thr, self._edge)
        return z

    def _estimate(self) -> torch.Tensor:
        hs, ws = self.model.scene_shape[-2:]
        x = self.v[..., :hs, :ws]
        return x.clamp(min=0.0) if self.nonneg else x.clone()  # a new tensor either way

    def step(self) -> SolverStep:
        """Do one iteration and report it (raises RunFinished once done).

        Two batched FFT pairs (forward of the two right-hand sides at once, inverse of v and
        M v at once) and about thirty elementwise passes, all into preallocated buffers.
        """
        self._check_running()
        t0 = time.perf_counter()
        it = self.iteration + 1
        mu1, mu2, mu3 = self.mu1, self.mu2, self.mu3
        pad = self.conv.pad
        with torch.no_grad():
            u = torch.add(self.psi_v, self.eta, alpha=1.0 / mu2, out=self._u)
            self._shrink_into(u)
            # x = (C^T b + mu1 M v + xi) / (C^T C + mu1), and the first FFT input mu1 x - xi
            x = torch.add(self.xi, self.mv, alpha=mu1, out=self._x)
            torch.addcmul(self.ctb_x, x, self.inv_x, out=x)
            rhs = self._rhs
            torch.sub(x, self.xi, alpha=1.0 / mu1, out=rhs[0])
            if mu1 != 1.0:
                rhs[0].mul_(mu1)
            # w = P(v + rho / mu3): computed on the field, 0 outside (set once)
            w = self._w
            hs, ws = self.model.scene_shape[-2:]
            wf = torch.add(self.v[..., :hs, :ws], self.rho_d[..., :hs, :ws], alpha=1.0 / mu3,
                           out=w[..., :hs, :ws])
            if self.nonneg:
                wf.clamp_(min=0.0)
            # spatial right-hand side Psi^T (mu2 u - eta) + mu3 w - rho, over mu2 (the factor
            # goes back in Fourier space, for free): Psi^T q + (mu3 w - rho) / mu2
            q = torch.sub(u, self.eta, alpha=1.0 / mu2, out=self._q)  # (mu2 u - eta) / mu2
            r1 = torch.mul(self.rho_d, -1.0 / mu2, out=rhs[1])
            r1[..., :hs, :ws].add_(w[..., :hs, :ws], alpha=mu3 / mu2)  # w is 0 off the field
            self._psi_t_add(q, r1)
            # both at once: (2, C, 1, Py, Px//2+1) (an out= buffer would only add a copy)
            f = torch.fft.rfft2(rhs)
            f[0].mul_(self.conv.hf_conj)
            vf = self._vf
            torch.add(f[0], f[1], alpha=mu2, out=vf[0])
            torch.view_as_real(vf[0]).mul_(self._inv_denom_ri)  # real factor, no complex copy
            torch.mul(vf[0], self.conv.hf, out=vf[1])
            out = torch.fft.irfft2(vf, s=pad)  # v and M v at once
            v_new, mv_new = out[0], out[1]
            v_norm = float(torch.linalg.vector_norm(v_new))
            if not math.isfinite(v_norm):
                raise NumericalError(f"ADMM: NaN/inf values appeared in the v update at "
                                     f"iteration {it}")
            # dual updates
            self.xi.add_(mv_new, alpha=mu1).sub_(x, alpha=mu1)
            psi_new = self._psi_into(v_new, self._psi_next)
            self.eta.add_(psi_new, alpha=mu2).sub_(u, alpha=mu2)
            self.rho_d.add_(v_new, alpha=mu3)
            self.rho_d[..., :hs, :ws].sub_(w[..., :hs, :ws], alpha=mu3)  # w is 0 off the field
            dv = float(torch.linalg.vector_norm(torch.sub(v_new, self.v, out=self._x)))
            rel = dv / max(v_norm, 1e-30)
            self._psi_next, self.psi_v = self.psi_v, psi_new
            self.v, self.mv = v_new, mv_new
            self.x = self._estimate()
            sy, sx = self.crop.sl
            r = self.ctc[:, 0, sy, sx] * (self.mv[:, 0, sy, sx] - self.b)
            data = 0.5 * float(torch.sum(r * r))
            obj = data + (self.tau * self.tv.value(self.x) if self.tau > 0 else 0.0)
            if not math.isfinite(obj):
                raise NumericalError(f"ADMM: the objective is {obj} at iteration {it}")
        self.iteration = it
        self._elapsed += time.perf_counter() - t0
        if rel < self.tol and it > 1:
            self.reason = StopReason.CONVERGED
        elif it >= self.max_iter:
            self.reason = StopReason.MAX_ITER
        return SolverStep(it, obj, data, math.sqrt(2 * data) / self._b_norm, rel, self._elapsed,
                          False)
