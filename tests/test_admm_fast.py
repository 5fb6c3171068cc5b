"""ADMM-TV's optimised step against a plain transcription of the same iteration (issue #18).

The step keeps scaled duals, fills the first right-hand side off the sensor window with
mu1 M v only, and runs one FFT per right-hand side with precombined Fourier factors. These
tests run a literal version of the DiffuserCam splitting (whole-grid formulas, unscaled duals,
torch.roll for the circular differences, masks for the penalised differences) side by side in
float64 and require the iterates, the duals' effect and the reported numbers to agree to
rounding.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from recon.admm import Admm
from recon.models import build_model
from recon.simulate import synthetic_psf
from recon.tv import TV


def _psi(v: torch.Tensor) -> torch.Tensor:
    return torch.stack([torch.roll(v, -1, dims=-2) - v, torch.roll(v, -1, dims=-1) - v])


def _psi_t(q: torch.Tensor) -> torch.Tensor:
    return (torch.roll(q[0], 1, dims=-2) - q[0]) + (torch.roll(q[1], 1, dims=-1) - q[1])


class _Reference:
    """The iteration written out directly, from the solver's constants (not its buffers)."""

    def __init__(self, s: Admm, isotropic: bool) -> None:
        self.s, self.iso = s, isotropic
        grid = s.v.shape
        py, px = s.conv.pad
        hs, ws = s.model.scene_shape[-2:]
        self.field = torch.zeros(py, px, dtype=s.v.dtype)
        self.field[:hs, :ws] = 1
        self.my = torch.zeros(py, px, dtype=s.v.dtype)
        self.my[: hs - 1, :ws] = 1
        self.mx = torch.zeros(py, px, dtype=s.v.dtype)
        self.mx[:hs, : ws - 1] = 1
        self.v = torch.zeros(grid, dtype=s.v.dtype)
        self.mv = torch.zeros_like(self.v)
        self.xi = torch.zeros_like(self.v)
        self.rho = torch.zeros_like(self.v)
        self.eta = torch.zeros((2, *grid), dtype=s.v.dtype)

    def _shrink(self, z: torch.Tensor, thr: float) -> torch.Tensor:
        soft = lambda t: torch.sign(t) * torch.clamp(t.abs() - thr, min=0)  # noqa: E731
        zy, zx = z[0], z[1]
        if self.iso:
            both = self.my * self.mx
            n = torch.hypot(zy, zx)
            g = torch.clamp(1 - thr / torch.clamp(n, min=1e-300), min=0)
            uy = torch.where(both > 0, zy * g, torch.where(self.my > 0, soft(zy), zy))
            ux = torch.where(both > 0, zx * g, torch.where(self.mx > 0, soft(zx), zx))
        else:
            uy = torch.where(self.my > 0, soft(zy), zy)
            ux = torch.where(self.mx > 0, soft(zx), zx)
        return torch.stack([uy, ux])

    def step(self) -> tuple[float, float]:
        s = self.s
        mu1, mu2, mu3 = s.mu1, s.mu2, s.mu3
        pad = s.conv.pad
        u = self._shrink(_psi(self.v) + self.eta / mu2, s.tau / mu2)
        x = (s.ctb + mu1 * self.mv + self.xi) / (s.ctc + mu1)
        w = (self.v + self.rho / mu3) * self.field
        if s.nonneg:
            w = w.clamp(min=0)
        rhs = (s.conv.hf_conj * torch.fft.rfft2(mu1 * x - self.xi)
               + torch.fft.rfft2(_psi_t(mu2 * u - self.eta) + mu3 * w - self.rho))
        vf = rhs / (mu1 * s.h2 + mu2 * s.psi2 + mu3)
        v = torch.fft.irfft2(vf, s=pad)
        mv = torch.fft.irfft2(vf * s.conv.hf, s=pad)
        self.xi = self.xi + mu1 * (mv - x)
        self.eta = self.eta + mu2 * (_psi(v) - u)
        self.rho = self.rho + mu3 * (v - w)
        rel = float(torch.linalg.vector_norm(v - self.v) / torch.linalg.vector_norm(v))
        self.v, self.mv = v, mv
        return rel, float(torch.linalg.vector_norm(v))


@pytest.mark.parametrize("isotropic", [True, False])
@pytest.mark.parametrize("erasure", [False, True])
def test_optimised_step_matches_the_literal_iteration(isotropic, erasure):
    n = 24
    psf = synthetic_psf((n, n), n_points=30, seed=3)
    mask = (np.random.default_rng(2).random((n, n)) > 0.25).astype(np.float64) if erasure else None
    model = build_model("2d", psf, mask=mask, dtype=torch.float64)
    b = torch.as_tensor(np.random.default_rng(1).random(model.meas_shape))
    tau = 3e-2
    s = Admm(model, b, tau=tau, tv=TV(isotropic=isotropic), max_iter=60, tol=0.0)
    ref = _Reference(s, isotropic)
    hs, ws = model.scene_shape[-2:]
    sy, sx = s.crop.sl
    m = torch.ones(n, n, dtype=torch.float64) if mask is None else torch.as_tensor(mask)
    for _ in range(60):
        got = s.step()
        rel, vnorm = ref.step()
        scale = max(vnorm, 1.0)
        assert float((s.v - ref.v).abs().max()) <= 1e-9 * scale
        assert float((s.mv - ref.mv).abs().max()) <= 1e-9 * scale
        assert got.rel_change == pytest.approx(rel, rel=1e-7, abs=1e-12)
        # the reported numbers: data term of M v on the sensor, TV of the returned estimate
        r = m * (ref.mv[:, 0, sy, sx] - b)
        data = 0.5 * float((r * r).sum())
        x = ref.v[..., :hs, :ws].clamp(min=0)
        assert got.data_term == pytest.approx(data, rel=1e-9)
        assert got.objective == pytest.approx(data + tau * TV(isotropic=isotropic).value(x),
                                              rel=1e-9)
        assert torch.equal(s.x, s.v[..., :hs, :ws].clamp(min=0))
    assert math.isfinite(got.objective) and got.rel_change < 1.0


def test_iterate_returned_earlier_is_not_overwritten():
    """The step reuses buffers; the estimate it handed out before must stay as it was."""
    n = 16
    model = build_model("2d", synthetic_psf((n, n), n_points=20, seed=0))
    b = torch.as_tensor(np.random.default_rng(0).random(model.meas_shape, dtype=np.float32))
    s = Admm(model, b, tau=1e-2, max_iter=10, tol=0.0)
    s.step()
    first = s.x
    kept = first.clone()
    v_first = s.v
    v_kept = v_first.clone()
    for _ in range(3):
        s.step()
    assert torch.equal(first, kept)
    assert torch.equal(v_first, v_kept)
    assert not torch.equal(s.x, kept)
