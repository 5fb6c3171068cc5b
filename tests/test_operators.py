"""Adjointness (dot-product) and autograd checks for every operator and forward model."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from recon.catalogue import OPERATOR_FACTORIES, make_operator
from recon.models import build_model
from recon.operators import Conv2D, Crop, fast_fft_size, power_norm

TOL = {torch.float32: 1e-4, torch.float64: 1e-10}
NAMES = sorted(OPERATOR_FACTORIES)


def _rand(shape, dtype, seed):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(shape, generator=g, dtype=torch.float64).to(dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
@pytest.mark.parametrize("name", NAMES)
def test_dot_product(name, dtype):
    op = make_operator(name, dtype)
    for seed in range(3):
        x = _rand(op.in_shape, dtype, seed)
        y = _rand(op.out_shape, dtype, seed + 100)
        ax = op.apply(x)
        aty = op.adjoint(y)
        assert tuple(ax.shape) == op.out_shape and tuple(aty.shape) == op.in_shape
        assert ax.dtype == dtype and aty.dtype == dtype
        lhs = float(torch.sum(ax.double() * y.double()))
        rhs = float(torch.sum(x.double() * aty.double()))
        scale = float(torch.linalg.vector_norm(ax.double()) * torch.linalg.vector_norm(y.double()))
        assert abs(lhs - rhs) <= TOL[dtype] * scale, (name, lhs, rhs)


@pytest.mark.parametrize("name", NAMES)
def test_adjoint_matches_autograd(name):
    op = make_operator(name, torch.float64)
    x = _rand(op.in_shape, torch.float64, 7).requires_grad_(True)
    y = _rand(op.out_shape, torch.float64, 8)
    (vjp,) = torch.autograd.grad(op.apply(x), x, grad_outputs=y)
    torch.testing.assert_close(op.adjoint(y), vjp, rtol=1e-10, atol=1e-12)


def test_catalogue_covers_every_model_kind():
    kinds = {n.split("_")[1] for n in NAMES if n.startswith("model_")}
    assert {"2d", "video", "spectral", "depth"} <= kinds


def test_on_axis_point_reproduces_psf():
    rng = np.random.default_rng(0)
    psf = rng.random((9, 12))
    for field in [None, (9, 12), (18, 24), (7, 5)]:
        m = build_model("2d", psf, field=field, dtype=torch.float64)
        x = torch.zeros(m.scene_shape, dtype=torch.float64)
        hs, ws = m.scene_shape[-2:]
        x[0, 0, hs // 2, ws // 2] = 1.0
        torch.testing.assert_close(m.apply(x)[0], torch.as_tensor(psf))


def test_convolution_is_linear_not_circular():
    """A point far off-axis must not wrap around: compare with a direct convolution."""
    from scipy.signal import convolve2d

    rng = np.random.default_rng(1)
    psf = rng.random((8, 10))
    scene = rng.random((8, 10))
    m = build_model("2d", psf, dtype=torch.float64)
    full = convolve2d(scene, psf, mode="full")
    expected = full[4:12, 5:15]
    got = m.apply(torch.as_tensor(scene)[None, None])[0].numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-12)


def test_video_model_matches_direct_sum():
    from scipy.signal import convolve2d

    from drivers.timing import SensorTiming

    rng = np.random.default_rng(2)
    psf = rng.random((8, 6))
    t = SensorTiming(rows=8, line_time_us=1.0, exposure_lines=3, pattern="outside-in")
    shutter = t.shutter(bin_lines=1)
    k = shutter.shape[0]
    frames = rng.random((k, 8, 6))
    m = build_model("video", psf, shutter=shutter, dtype=torch.float64)
    got = m.apply(torch.as_tensor(frames)[None])[0].numpy()
    expected = sum(
        shutter[i][:, None] * convolve2d(frames[i], psf, mode="full")[4:12, 3:9] for i in range(k)
    )
    np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-12)


def test_rgb_channels_are_independent():
    rng = np.random.default_rng(3)
    psf = rng.random((3, 6, 7))
    m = build_model("2d", psf, dtype=torch.float64)
    x = torch.as_tensor(rng.random(m.scene_shape))
    y = m.apply(x)
    for c in range(3):
        mc = build_model("2d", psf[c], dtype=torch.float64)
        torch.testing.assert_close(y[c], mc.apply(x[c : c + 1])[0])


def test_power_norm_matches_svd_and_is_cached():
    op = make_operator("model_2d_erasures", torch.float64)
    n = int(np.prod(op.in_shape))
    eye = torch.eye(n, dtype=torch.float64).reshape(n, *op.in_shape)
    mat = torch.stack([op.apply(e).reshape(-1) for e in eye], dim=1)
    sigma = float(torch.linalg.matrix_norm(mat, ord=2))
    est = power_norm(op, iters=500, tol=1e-12)
    assert abs(est - sigma) / sigma < 1e-3
    first = op.norm()
    op.apply = None  # a cached norm must not touch the operator again
    assert op.norm() == first


def test_fast_fft_size():
    assert fast_fft_size(1) == 1
    assert fast_fft_size(299) == 300
    assert fast_fft_size(511) == 512
    assert fast_fft_size(1201) == 1215
    for n in range(1, 400):
        m = fast_fft_size(n)
        assert m >= n
        r = m
        for p in (2, 3, 5):
            while r % p == 0:
                r //= p
        assert r == 1


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"kind": "2d", "psf": np.zeros((4, 4))}, "all zeros"),
        ({"kind": "2d", "psf": np.full((4, 4), np.nan)}, "NaN"),
        ({"kind": "video", "psf": np.ones((4, 4))}, "shutter"),
        ({"kind": "video", "psf": np.ones((4, 4)), "shutter": np.ones((3, 5))}, r"\(K, 4\)"),
        ({"kind": "spectral", "psf": np.ones((4, 4)), "filters": np.ones((3, 4, 5))}, "filter"),
        ({"kind": "depth", "psf": np.ones((4, 4))}, "stack"),
        ({"kind": "2d", "psf": np.ones((4, 4)), "mask": np.ones((5, 4))}, "mask"),
    ],
)
def test_bad_model_inputs(kwargs, match):
    kind = kwargs.pop("kind")
    psf = kwargs.pop("psf")
    with pytest.raises(ValueError, match=match):
        build_model(kind, psf, **kwargs)


def test_shape_errors_name_the_problem():
    with pytest.raises(ValueError, match="outside"):
        Crop((1, 1, 4, 4), (5, 2), (0, 0))
    with pytest.raises(ValueError, match="does not match"):
        Conv2D(np.ones((2, 4, 4)), (1, 3, 4, 4))


def _operator_classes(cls: type) -> set[type]:
    out: set[type] = set()
    for sub in cls.__subclasses__():
        out |= {sub} | _operator_classes(sub)
    return out


def _classes_in(op) -> set[type]:
    """Every operator class inside ``op`` (compositions, adjoints and fused steps walked)."""
    found = {type(op)}
    for child in [*getattr(op, "ops", []), *getattr(op, "_steps", []),
                  getattr(op, "op", None), getattr(op, "crop", None), getattr(op, "conv", None)]:
        if child is not None and hasattr(child, "apply"):
            found |= _classes_in(child)
    return found


def test_catalogue_covers_every_operator_class():
    """The dot-product and autograd tests reach every LinearOperator subclass of recon.

    Enumerated from the class hierarchy, not a hand list: a new operator without a catalogue
    entry fails here.
    """
    from recon.operators import LinearOperator

    real = {c for c in _operator_classes(LinearOperator) if c.__module__.startswith("recon.")}
    covered: set[type] = set()
    for name in NAMES:
        op = make_operator(name, torch.float64)
        covered |= _classes_in(op) | _classes_in(op.T if hasattr(op, "T") else op)
    missing = sorted(c.__qualname__ for c in real - covered)
    assert len(real) >= 8, f"too few operator classes enumerated: {real}"
    assert not missing, f"operators without a catalogue entry: {missing}"
