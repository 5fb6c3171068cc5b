"""The simulated camera renders through the same forward model that recon inverts (issue 4 #4)."""

from __future__ import annotations

import numpy as np
import torch

from drivers.simcam import MovingScene, SimulatedCamera
from drivers.timing import SensorTiming
from recon.models import build_model
from recon.simulate import render_frames, synthetic_psf


def test_dual_rolling_shutter_frame_equals_video_forward_model():
    h, w, period, line_us = 32, 40, 4, 10.0
    psf = synthetic_psf((h, w), seed=7)
    rng = np.random.default_rng(3)
    frames = 200.0 * rng.random((12, h, w))  # electrons per ms per pixel
    cam = SimulatedCamera(
        width=w, height=h, renderer=render_frames(psf),
        scene=MovingScene(frames, frame_period_lines=period, loop=False),
        readout_pattern="outside-in", line_time_us=line_us, exposure_us=13 * line_us,
        pixel_format="Mono16", dark_offset_adu=0.0, noise=False, pacing=False,
        full_well_e=2000.0, seed=0,
    )
    with cam:
        frame = cam.snap(timeout_s=5.0)
        adu_per_e = cam.adu_per_electron
    timing = SensorTiming(rows=h, line_time_us=line_us, exposure_lines=13, pattern="outside-in")
    assert frame.timing == timing
    shutter = timing.shutter(bin_lines=period)  # M_k on the scene's frame grid
    k = shutter.shape[0]
    model = build_model("video", psf, shutter=shutter, dtype=torch.float64)
    electrons = model.apply(torch.as_tensor(frames[:k])[None])[0].numpy()
    electrons *= period * line_us / 1000.0  # the scene is a flux per millisecond
    expected = electrons * adu_per_e
    got = np.asarray(frame.pixels, dtype=np.float64)
    assert expected.max() > 100  # a signal well above the quantisation step
    # noise-free: only rounding to integer codes (and the float32 shutter) separate them
    np.testing.assert_allclose(got, expected, atol=0.5 + 1e-5 * expected.max())
    # and the dual rolling shutter matters: a global-shutter rendering differs
    glob = build_model("2d", psf, dtype=torch.float64).apply(
        torch.as_tensor(frames[:k].mean(0))[None, None])[0].numpy()
    glob *= electrons.sum() / glob.sum() * adu_per_e
    assert np.abs(glob - expected).max() > 10
