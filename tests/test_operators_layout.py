"""The operators' layout-matched Fourier factors and the one-plane SumK: same values as before.

The pruned transforms return their spectra column-major; the operators multiply them by a copy
of the transfer function in that layout (recon.operators._in_layout). These tests check the
maps against a dense reference, the cache, and that no output aliases an input.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from recon.operators import Compose, Conv2D, Crop, StackConvSum, SumK, _in_layout


def _reference_conv(x: torch.Tensor, h: torch.Tensor, pad: tuple[int, int]) -> torch.Tensor:
    """Linear convolution on the padded grid by plain rfft2/irfft2 (row-major throughout)."""
    hh = h.reshape((1,) * (4 - h.ndim) + tuple(h.shape))
    return torch.fft.irfft2(torch.fft.rfft2(x, s=pad) * torch.fft.rfft2(hh, s=pad), s=pad)


def test_in_layout_matches_strides_and_values_and_caches() -> None:
    f = torch.randn(1, 1, 12, 7, dtype=torch.complex128)
    like = torch.fft.fft(torch.fft.rfft(torch.randn(2, 3, 5, 12, dtype=torch.float64), dim=-1),
                         n=12, dim=-2)
    assert like.stride(-2) == 1  # the case the helper is for: a column-major spectrum
    cache: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}
    g = _in_layout(f, like, cache, "f")
    assert g.stride(-2) == 1 and g.stride(-1) == 12
    assert torch.equal(g, f)
    assert _in_layout(f, like, cache, "f") is g  # cached
    f2 = f * 2
    g2 = _in_layout(f2, like, cache, "f")  # a replaced factor is copied anew
    assert g2 is not g and torch.equal(g2, f2)
    row_major = torch.empty(2, 3, 12, 7, dtype=torch.complex128)
    assert _in_layout(f, row_major, cache, "f") is f


@pytest.mark.parametrize("psf_shape,scene", [
    ((6, 7), (1, 1, 5, 6)),
    ((3, 6, 7), (2, 3, 5, 6)),
    ((2, 1, 6, 7), (2, 3, 5, 6)),
])
def test_conv_and_cropconv_match_dense_reference(psf_shape: tuple[int, ...],
                                                 scene: tuple[int, ...]) -> None:
    rng = np.random.default_rng(1)
    h = torch.as_tensor(rng.random(psf_shape))
    x = torch.as_tensor(rng.standard_normal(scene))
    conv = Conv2D(h, scene, dtype=torch.float64)
    ref = _reference_conv(x, h, conv.pad)
    torch.testing.assert_close(conv.apply(x), ref, rtol=1e-10, atol=1e-12)
    crop = Crop(conv.out_shape, (4, 5), (2, 3), dtype=torch.float64)
    op = Compose([crop, conv])
    for _ in range(2):  # the second call reads the cached factors
        torch.testing.assert_close(op.apply(x), ref[..., 2:6, 3:8], rtol=1e-10, atol=1e-12)
    y = torch.as_tensor(rng.standard_normal(op.out_shape))
    # the adjoint by autograd of the dense reference
    xr = torch.zeros(scene, dtype=torch.float64, requires_grad=True)
    (_reference_conv(xr, h, conv.pad)[..., 2:6, 3:8] * y).sum().backward()
    assert xr.grad is not None
    for _ in range(2):
        torch.testing.assert_close(op.adjoint(y), xr.grad, rtol=1e-10, atol=1e-12)
    yy = torch.as_tensor(rng.standard_normal(conv.out_shape))
    torch.testing.assert_close(conv.adjoint(yy), crop_adjoint_ref(conv, h, yy),
                               rtol=1e-10, atol=1e-12)


def crop_adjoint_ref(conv: Conv2D, h: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    xr = torch.zeros(conv.in_shape, dtype=torch.float64, requires_grad=True)
    (_reference_conv(xr, h, conv.pad) * y).sum().backward()
    assert xr.grad is not None
    return xr.grad


def test_stack_conv_sum_matches_sum_of_convolutions() -> None:
    rng = np.random.default_rng(2)
    h = torch.as_tensor(rng.random((3, 6, 7)))
    x = torch.as_tensor(rng.standard_normal((2, 3, 5, 6)))
    op = StackConvSum(h, x.shape, dtype=torch.float64)
    torch.testing.assert_close(op.apply(x), _reference_conv(x, h, op.conv.pad).sum(dim=1),
                               rtol=1e-10, atol=1e-12)


def test_autograd_through_compose_with_cached_factors() -> None:
    rng = np.random.default_rng(3)
    h = torch.as_tensor(rng.random((6, 7)))
    conv = Conv2D(h, (1, 1, 5, 6), dtype=torch.float64)
    op = Compose([SumK((1, 1, 4, 5), dtype=torch.float64),
                  Crop(conv.out_shape, (4, 5), (2, 3), dtype=torch.float64), conv])
    op.apply(torch.zeros(op.in_shape, dtype=torch.float64))  # fill the factor caches
    x = torch.as_tensor(rng.standard_normal(op.in_shape)).requires_grad_(True)
    assert torch.autograd.gradcheck(op.apply, (x,))
    y = torch.as_tensor(rng.standard_normal(op.out_shape)).requires_grad_(True)
    assert torch.autograd.gradcheck(op.adjoint, (y,))


def test_sumk_one_plane_is_a_new_contiguous_tensor() -> None:
    s = SumK((2, 1, 4, 5), dtype=torch.float64)
    big = torch.randn(2, 1, 4, 9, dtype=torch.float64)
    x = big[..., 2:7]  # strided, like the cropped convolution's output
    out = s.apply(x)
    assert out.shape == (2, 4, 5) and out.is_contiguous()
    torch.testing.assert_close(out, x.sum(dim=1), rtol=0, atol=0)
    xc = x.contiguous()
    out2 = s.apply(xc)
    xc.zero_()
    assert out2.abs().sum() > 0  # no alias of the input
    assert torch.equal(out2, out)
