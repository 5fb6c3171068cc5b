"""The UDN video demo (benchmarks/udn_video.py) end to end on a tiny case."""

from __future__ import annotations

import argparse

import numpy as np

from benchmarks import udn_video as demo


def test_video_demo_pipeline_runs_and_beats_a_constant_image():
    psf, shutter, sims, timing = demo.make_cases(16, 8, (0.1, 0.2), 0.01, ["im408", "im65"],
                                                 size=(24, 32))
    assert psf.shape == (24, 32) and shutter.shape == (8, 24)
    assert timing["bin_lines"] * 8 == timing["readout_lines"] + timing["exposure_lines"]
    np.testing.assert_allclose(shutter.sum(axis=0).mean(), 1.0)
    for sim in sims.values():
        assert sim.truth.shape == (1, 8, 24, 32)
        steps = np.abs(np.diff(sim.truth, axis=1)).mean(axis=(0, 2, 3))
        assert (steps > 1e-3 * sim.truth.mean()).all()  # every frame differs from the last
    parser = argparse.ArgumentParser()
    demo.add_arguments(parser)
    args = parser.parse_args(["--channels", "16", "8", "--scales", "3", "3", "--patience", "1000"])
    fista = demo.run_fista(psf, shutter, sims, 100, taus=(1e-5, 1e-4))
    assert fista["tau"] in (1e-5, 1e-4)
    for name, sim in sims.items():
        floor = np.array(demo.constant_baseline(sim.truth))
        results = {"fista": fista["scenes"][name]}
        # the 3D net is ~4x slower; the smallest margin over the floor: 0.7 dB for both
        for variant, iters in (("frames", 200), ("3d", 100)):
            args.iters = iters
            results[variant] = demo.run_udn(psf, shutter, sim, variant, args, input_channels=8)
        for method, r in results.items():
            p = np.array(r["psnr"])
            assert p.shape == (8,) and np.isfinite(p).all()
            assert (p > floor).all(), (name, method, p - floor)
            assert r["iterations"] > 0 and r["wall"] > 0
