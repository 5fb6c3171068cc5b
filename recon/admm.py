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

from recon.fista import NumericalError, SolverStep, StepwiseSolver, StopReason, _check_finite
from recon.models import ForwardModel, ModelKind
from recon.operators import Conv2D, Crop, _irfft2, _rfft2
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
        _check_finite(self.b, "the measurement", 0, "ADMM")
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
        self.v = torch.zeros(grid, dtype=dt, device=dev)
        self.mv = torch.zeros(grid, dtype=dt, device=dev)
        self.xi = torch.zeros(grid, dtype=dt, device=dev)
        self.eta = [torch.zeros(grid, dtype=dt, device=dev) for _ in range(2)]
        self.rho_d = torch.zeros(grid, dtype=dt, device=dev)
        self.iteration, self.reason, self._elapsed = 0, None, 0.0
        self._b_norm = max(float(torch.linalg.vector_norm(self.b)), 1e-30)
        self.x = self._estimate()

    @property
    def params(self) -> dict[str, Any]:
        """Solver settings, for run records and metadata."""
        return {"method": "admm-tv", "tau": self.tau,
                "tv": {"isotropic": self.tv.isotropic, "weight_k": 0.0},
                "nonneg": self.nonneg, "max_iter": self.max_iter, "tol": self.tol,
                "mu": [self.mu1, self.mu2, self.mu3]}

    def _psi(self, v: torch.Tensor) -> list[torch.Tensor]:
        return [torch.roll(v, -1, dims=-2) - v, torch.roll(v, -1, dims=-1) - v]

    def _psi_t(self, u: list[torch.Tensor]) -> torch.Tensor:
        return (torch.roll(u[0], 1, dims=-2) - u[0]) + (torch.roll(u[1], 1, dims=-1) - u[1])

    def _shrink(self, z: list[torch.Tensor], thr: float) -> list[torch.Tensor]:
        ty, tx = thr * self.tv_y, thr * self.tv_x
        if self.tv.isotropic:
            # group shrink where both differences are penalised, scalar shrink elsewhere
            both = self.tv_y * self.tv_x
            n = torch.sqrt(z[0] * z[0] + z[1] * z[1]).clamp(min=1e-30)
            g = (1 - thr / n).clamp(min=0.0)
            sy = torch.sign(z[0]) * (z[0].abs() - ty).clamp(min=0.0)
            sx = torch.sign(z[1]) * (z[1].abs() - tx).clamp(min=0.0)
            return [torch.where(both > 0, g * z[0], sy), torch.where(both > 0, g * z[1], sx)]
        return [torch.sign(z[0]) * (z[0].abs() - ty).clamp(min=0.0),
                torch.sign(z[1]) * (z[1].abs() - tx).clamp(min=0.0)]

    def _estimate(self) -> torch.Tensor:
        hs, ws = self.model.scene_shape[-2:]
        x = self.v[..., :hs, :ws]
        return (x.clamp(min=0.0) if self.nonneg else x).clone()

    def step(self) -> SolverStep:
        """Do one iteration and report it."""
        t0 = time.perf_counter()
        it = self.iteration + 1
        mu1, mu2, mu3 = self.mu1, self.mu2, self.mu3
        with torch.no_grad():
            psi_v = self._psi(self.v)
            u = self._shrink([p + e / mu2 for p, e in zip(psi_v, self.eta, strict=True)],
                             self.tau / mu2)
            x = (self.ctb + mu1 * self.mv + self.xi) / (self.ctc + mu1)
            w = self.v + self.rho_d / mu3
            if self.nonneg:
                w = w.clamp(min=0.0)
            w = w * self.support
            rhs_space = self._psi_t([mu2 * ui - e for ui, e in zip(u, self.eta, strict=True)])
            rhs_space += mu3 * w - self.rho_d
            rhs_f = self.conv.hf_conj * _rfft2(mu1 * x - self.xi) + _rfft2(rhs_space)
            v_f = rhs_f / (mu1 * self.h2 + mu2 * self.psi2 + mu3)
            v_new = _irfft2(v_f, self.conv.pad)
            mv_new = _irfft2(self.conv.hf * v_f, self.conv.pad)
            psi_new = self._psi(v_new)
            self.xi += mu1 * (mv_new - x)
            for e, p, ui in zip(self.eta, psi_new, u, strict=True):
                e += mu2 * (p - ui)
            self.rho_d += mu3 * (v_new - w)
            if not bool(torch.isfinite(v_new).all()):
                raise NumericalError(f"ADMM: NaN/inf values appeared in the v update at "
                                     f"iteration {it}")
            dv = float(torch.linalg.vector_norm(v_new - self.v))
            rel = dv / max(float(torch.linalg.vector_norm(v_new)), 1e-30)
            self.v, self.mv = v_new, mv_new
            self.x = self._estimate()
            sy, sx = self.crop.sl
            r = self.ctc[:, 0, sy, sx] * self.mv[:, 0, sy, sx] - self.ctc[:, 0, sy, sx] * self.b
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
