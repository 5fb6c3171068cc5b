"""Region and coarse-grid forward models are exact restrictions of the full model."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from recon.io import box_downsample
from recon.models import build_model
from recon.plan.coarse import coarse_psf
from recon.plan.roi import Region, build_region_model, embed_region
from recon.simulate import synthetic_psf

PSF = synthetic_psf((20, 24), seed=1)
RNG = np.random.default_rng(0)
SHUTTER = RNG.random((3, 20))


def _psf(kind):
    return np.stack([PSF, np.roll(PSF, 3, axis=0)]) if kind == "depth" else PSF


def _kw(kind, shutter=SHUTTER):
    return {"shutter": shutter} if kind == "video" else {}


def _regions(field):
    fh, fw = field
    return [(0, 0, 5, 7), (fh - 9, fw - 11, 8, 9), (fh - 6, fw - 5, 6, 5), (2, 3, fh - 2, fw - 3)]


@pytest.mark.parametrize("kind", ["2d", "video", "depth"])
@pytest.mark.parametrize("field", [(20, 24), (40, 48), (13, 17)])
def test_region_model_is_the_full_model_on_a_zero_padded_scene(kind, field):
    rng = np.random.default_rng(1)
    full = build_model(kind, _psf(kind), field=field, dtype=torch.float64, **_kw(kind))
    for reg in _regions(field):
        r = Region(*reg, *field)
        m = build_region_model(kind, _psf(kind), r, dtype=torch.float64, **_kw(kind))
        x = rng.random(m.scene_shape)
        y_full = full.apply(torch.as_tensor(embed_region(x, r)))
        np.testing.assert_allclose(m.apply(torch.as_tensor(x)).numpy(), y_full.numpy(),
                                   atol=1e-12)
        y = torch.as_tensor(rng.random(m.meas_shape))
        adj_full = full.adjoint(y).numpy()[..., r.top:r.top + r.height, r.left:r.left + r.width]
        np.testing.assert_allclose(m.adjoint(y).numpy(), adj_full, atol=1e-12)


@pytest.mark.parametrize("kind", ["2d", "video", "depth"])
@pytest.mark.parametrize("d", [1, 2, 3])
def test_region_model_adjoint_dot_product(kind, d):
    rng = np.random.default_rng(2)
    r = Region(7, 2, 9, 13, 30, 36)
    m = build_region_model(kind, _psf(kind), r, downsample=d, dtype=torch.float64, **_kw(kind))
    x = torch.as_tensor(rng.random(m.scene_shape))
    y = torch.as_tensor(rng.random(m.meas_shape))
    lhs = float((m.apply(x) * y).sum())
    rhs = float((x * m.adjoint(y)).sum())
    assert abs(lhs - rhs) <= 1e-10 * max(abs(lhs), 1.0)


@pytest.mark.parametrize("a", [2, 3])
@pytest.mark.parametrize("kind", ["2d", "video", "depth"])
def test_coarse_model_is_exact_for_block_constant_scenes(a, kind):
    """box_downsample(A_fine(upsampled x)) == A_coarse(x), any field and region."""
    rng = np.random.default_rng(3)
    blocks = np.repeat(rng.random((3, -(-20 // a))), a, axis=1)[:, :20]  # constant per block
    for field in [(20, 24), (40, 48), (26, 31)]:
        for reg in [(0, 0, *field), (3, 5, 9, 12), (field[0] - 9, field[1] - 11, 9, 11)]:
            r = Region(*reg, *field)
            rc = r.scaled(a)
            fine = Region(rc.top * a, rc.left * a, rc.height * a, rc.width * a, *field)
            mc = build_region_model(kind, _psf(kind), r, downsample=a, dtype=torch.float64,
                                    **_kw(kind, blocks))
            mf = build_region_model(kind, _psf(kind), fine, dtype=torch.float64,
                                    **_kw(kind, blocks))
            x = rng.random(mc.scene_shape)
            xf = torch.as_tensor(np.kron(x, np.ones((a, a))))
            want = box_downsample(mf.apply(xf).numpy(), a)
            got = mc.apply(torch.as_tensor(x)).numpy()
            assert np.abs(got - want).max() <= 1e-6 * np.abs(want).max()


def test_box_downsampled_psf_is_a_worse_coarse_model():
    """The reason for coarse_psf: box-downsampling the PSF leaves a percent-level error."""
    rng = np.random.default_rng(4)
    psf = synthetic_psf((48, 64), seed=1)
    v = rng.random((24, 32))
    fine = build_model("2d", psf, dtype=torch.float64)
    want = box_downsample(fine.apply(torch.as_tensor(np.kron(v, np.ones((2, 2))))[None, None])
                          .numpy(), 2)
    exact = build_region_model("2d", psf, Region.whole((48, 64)), downsample=2,
                               dtype=torch.float64).apply(torch.as_tensor(v)[None, None]).numpy()
    boxed = build_model("2d", box_downsample(psf, 2), dtype=torch.float64).apply(
        torch.as_tensor(v)[None, None]).numpy()
    g = float((want * boxed).sum() / (boxed * boxed).sum())  # best gain for the box model
    err_box = np.abs(g * boxed - want).max() / want.max()
    err_exact = np.abs(exact - want).max() / want.max()
    assert err_exact < 1e-6 < 0.01 < err_box


def test_coarse_psf_scale_and_identity():
    k, origin = coarse_psf(PSF, 1, (20, 24))
    assert origin == (0, 0) and np.array_equal(k, PSF)
    k2, _ = coarse_psf(PSF, 2, (20, 24))
    assert k2.sum() == pytest.approx(PSF.sum(), rel=1e-5)


def test_region_validation_and_scaling():
    with pytest.raises(ValueError, match="outside"):
        Region(10, 0, 12, 5, 20, 24)
    with pytest.raises(ValueError, match="empty"):
        Region(0, 0, 0, 5, 20, 24)
    r = Region(3, 5, 7, 9, 20, 24).scaled(2)
    assert (r.top, r.left, r.height, r.width, r.field_h, r.field_w) == (1, 2, 4, 5, 10, 12)
    assert Region.whole((20, 24)).is_whole
    with pytest.raises(ValueError, match="region"):
        embed_region(np.zeros((1, 1, 3, 3)), Region(0, 0, 4, 4, 8, 8))
