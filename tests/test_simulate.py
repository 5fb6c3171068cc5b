"""Simulation: exact erasure counts, noise/saturation flags, and the camera renderer."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from drivers.timing import SensorTiming
from recon.models import build_model
from recon.simulate import erasure_mask, render_frames, simulate, synthetic_psf


@pytest.mark.parametrize("fraction", [0.0, 0.5, 0.9, 0.99, 0.999, 1.0])
def test_erasure_count_is_exact(fraction):
    m = erasure_mask((150, 200), fraction, seed=4)
    assert int((m == 0).sum()) == round(fraction * 150 * 200)
    assert m.dtype == np.float32


def test_simulation_scales_adds_noise_and_flags_saturation():
    psf = synthetic_psf((20, 24), seed=3)
    model = build_model("2d", psf)
    scene = np.random.default_rng(0).random(model.scene_shape)
    clean = simulate(model, scene)
    assert clean.meas.max() == pytest.approx(1.0)
    noisy = simulate(model, scene, noise=0.05, seed=1)
    assert 0.04 < float(np.std(noisy.meas - clean.meas)) < 0.06
    sat = simulate(model, scene, saturation=0.8, bits=8)
    assert sat.saturated > 0 and sat.meas.max() <= 0.8 + 1e-6
    assert len(np.unique(sat.meas)) <= 256
    er = simulate(model, scene, erasure=0.5, seed=2)
    assert np.all(er.meas[0][er.mask == 0] == 0)
    with pytest.raises(ValueError, match="shape"):
        simulate(model, scene[:, :, :3])


def test_camera_renderer_equals_the_video_forward_model():
    psf = synthetic_psf((24, 20), seed=5)
    timing = SensorTiming(rows=24, line_time_us=3.0, exposure_lines=7, pattern="outside-in")
    shutter = timing.shutter(bin_lines=2)
    frames = np.random.default_rng(1).random((shutter.shape[0], 24, 20))
    got = render_frames(psf)(frames, shutter)
    model = build_model("video", psf, shutter=shutter, dtype=torch.float64)
    expected = model.apply(torch.as_tensor(frames)[None])[0].numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-14)
    with pytest.raises(ValueError, match="rows"):
        render_frames(psf)(frames, shutter[:, :10])
