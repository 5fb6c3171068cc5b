"""The DIP encoder-decoder: shapes for every variant and odd sizes, gain, checkpointing, seeds."""

from __future__ import annotations

import pytest
import torch

from recon.udn.network import (
    Generator,
    NetworkConfig,
    axis_halvings,
    padded_grid,
    parameter_count,
)

SMALL = {"scales": 3, "channels": 8, "skip_channels": 4, "input_channels": 4}


@pytest.mark.parametrize(
    ("variant", "shape"),
    [
        ("2d", (1, 1, 16, 16)),
        ("2d", (1, 1, 17, 23)),  # odd sizes, not multiples of 2**scales
        ("2d", (3, 1, 19, 30)),  # RGB: 3 output channels
        ("2d", (1, 1, 5, 7)),  # too small to halve 3 times
        ("2d", (1, 1, 1, 32)),  # one row: computed on 2 (reflection padding needs 2 samples)
        ("2d", (3, 1, 24, 1)),  # one column
        ("2d", (1, 1, 1, 1)),
        ("frames", (1, 4, 18, 21)),
        ("frames", (3, 2, 16, 20)),
        ("3d", (1, 5, 17, 19)),
        ("3d", (2, 1, 16, 16)),  # K = 1: depth kernel 1, depth never halved
        ("3d", (1, 3, 1, 20)),
        ("3d", (1, 16, 16, 16)),
    ],
)
@pytest.mark.parametrize("skip", [0, 4])
def test_output_shape_every_variant(variant, shape, skip):
    cfg = NetworkConfig(variant=variant, **{**SMALL, "skip_channels": skip})
    g = Generator(cfg, shape, seed=1)
    x = g(noise_std=0.05, generator=torch.Generator().manual_seed(0))
    assert tuple(x.shape) == shape
    assert x.dtype == torch.float32
    assert torch.isfinite(x).all()
    x.mean().backward()
    assert g.log_gain.grad is not None and float(g.log_gain.grad) != 0.0
    assert g.parameter_count() == parameter_count(cfg, shape)
    # every level's output is used: each conv weight receives a gradient
    for name, p in g.named_parameters():
        assert p.grad is not None, name


def test_padded_grid_and_halvings():
    assert axis_halvings(150, 5) == 5
    assert axis_halvings(16, 5) == 3  # 16 -> 2 at the coarsest level
    assert axis_halvings(3, 5) == 0
    g = Generator(NetworkConfig(scales=5, channels=4, input_channels=2), (1, 1, 150, 200))
    assert g.padded == (160, 224)
    assert tuple(g.z.shape) == (1, 2, 160, 224)
    # a 1-row or 1-column scene failed in torch's reflection padding ("Padding size should be
    # less than the corresponding input dimension"): its grid has at least 2 along y and x
    assert padded_grid(NetworkConfig(scales=5), (1, 1, 1, 32)) == ((2, 32), [0, 4])
    assert padded_grid(NetworkConfig(variant="3d", scales=5), (1, 1, 24, 1))[0] == (1, 24, 2)


def test_output_gain_reaches_beyond_the_sigmoid():
    g = Generator(NetworkConfig(**SMALL), (1, 1, 16, 16), gain=4.0)
    with torch.no_grad():
        x = g()
    assert float(x.max()) > 1.0  # a bare sigmoid could not
    assert g.gain == pytest.approx(4.0)
    assert any(n == "log_gain" for n, _ in g.named_parameters())


def test_gradient_checkpointing_gives_the_same_gradients():
    shape = (1, 3, 16, 20)
    grads = []
    for ckpt in (False, True):
        torch.manual_seed(0)
        cfg = NetworkConfig(variant="3d", gradient_checkpointing=ckpt, **SMALL)
        g = Generator(cfg, shape, seed=0)
        g(0.0).square().mean().backward()
        grads.append([p.grad.clone() for p in g.parameters()])
    for a, b in zip(*grads, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7)


def test_2d_variant_refuses_frames():
    with pytest.raises(ValueError, match="'frames' or '3d'"):
        Generator(NetworkConfig(variant="2d", **SMALL), (1, 4, 16, 16))


def test_input_is_seeded():
    cfg = NetworkConfig(**SMALL)
    a, b, c = (Generator(cfg, (1, 1, 16, 16), seed=s).z for s in (3, 3, 4))
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert float(a.min()) >= 0.0 and float(a.max()) < 0.1


@pytest.mark.parametrize("bad", [{"scales": 0}, {"channels": 2.5}, {"variant": "4d"},
                                 {"skip_channels": -1}])
def test_config_validation(bad):
    with pytest.raises(ValueError, match="network"):
        NetworkConfig(**bad)
