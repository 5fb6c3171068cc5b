"""Dark frames and hot/dead pixel maps on the simulated camera; pixel repair."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from calibration.darks import (
    calibrate_pixel_maps,
    capture_darks,
    dark_noise_rms,
    pixel_maps,
    repair_pixels,
)
from calibration.frames import acquire_frames
from calibration.workflow import CalibrationError, Workflow
from drivers.lightstate import LightMode
from drivers.simcam import SimulatedCamera
from recon.calibfile import load_calibration, load_pixel_mask
from recon.fista import Fista
from recon.models import build_model
from recon.simulate import simulate
from tests.calibration.conftest import COLS, ROWS


def test_hot_and_dead_maps_match_the_sensor_and_serve_as_erasure_mask(source, true_psf, tmp_path):
    cam = SimulatedCamera(
        COLS,
        ROWS,
        dead_pixel_fraction=0.01,
        hot_pixel_fraction=0.01,
        exposure_us=1000.0,
        pacing=False,
        seed=5,
    )
    flat = np.full((ROWS, COLS), 5000.0, dtype=np.float32)  # e-/ms through the default renderer

    def light_the_flat_field() -> None:
        cam.scene = flat

    out = tmp_path / "darks.npz"
    with cam:
        wf = Workflow(
            calibrate_pixel_maps(
                cam,
                source=source,
                n_darks=8,
                n_flats=8,
                prepare_flats=light_the_flat_field,
                settle=0,
                out=out,
            )
        )
        stages = [p.stage for p in wf]
        maps = wf.result
    assert {"darks", "flats", "maps", "save"} <= set(stages)
    assert source.status().mode is LightMode.OFF
    dead, hot = cam.defect_maps
    assert np.array_equal(maps.hot, hot) and np.array_equal(maps.dead, dead)
    assert np.array_equal(maps.mask, (~(dead | hot)).astype(np.float32))

    cal = load_calibration(out, expect="pixel-maps")
    assert cal.metadata["hot_pixels"] == hot.sum() and cal.metadata["dead_pixels"] == dead.sum()
    mask = load_pixel_mask(out)
    assert np.array_equal(mask, maps.mask)

    # the mask is the erasure mask of the 2D model: reconstruct through it
    truth = np.zeros((1, 1, ROWS, COLS), dtype=np.float32)
    truth[..., 20:40, 25:50] = 1.0
    sim = simulate(build_model("2d", true_psf), truth, seed=0)
    meas = sim.meas * mask
    model = build_model("2d", true_psf, mask=mask)
    x = Fista(model.op, torch.as_tensor(meas), tau=1e-4, max_iter=60).run().x.numpy()
    assert float(np.corrcoef(x.ravel(), truth.ravel())[0, 1]) > 0.8


def test_darks_without_flats_have_no_dead_pixels(make_camera, source):
    cam = make_camera(hot_pixel_fraction=0.005, exposure_us=2000.0)
    darks = Workflow(capture_darks(cam, 6, source=source, settle=0)).run()
    maps = pixel_maps(darks)
    assert np.array_equal(maps.hot, cam.defect_maps[1]) and not maps.dead.any()
    assert darks.n == 6 and darks.exposure_us == 2000.0


@pytest.mark.parametrize("read_noise_e", [2.0, 20.0])
def test_dark_noise_is_not_fooled_by_quantisation(read_noise_e):
    """The noise was the median per-pixel std: 0 on the simulated camera, whose read noise
    (2 e-, 0.27 ADU) moved most pixels by less than one code in a few frames."""
    cam = SimulatedCamera(COLS, ROWS, read_noise_e=read_noise_e, exposure_us=100.0,
                          hot_pixel_fraction=0.01, hot_pixel_e_per_ms=10_000.0, pacing=False,
                          seed=3)
    configured = read_noise_e * cam.adu_per_electron
    with cam:
        darks = Workflow(capture_darks(cam, 16, settle=0)).run()
    maps = pixel_maps(darks)
    noise = maps.dark_noise_adu
    assert noise > 0 and maps.metadata()["dark_noise_adu"] == noise
    assert configured / 2 < noise < 2 * configured
    if read_noise_e > 5:  # well above one code: the read noise plus the quantisation step
        assert noise == pytest.approx(np.hypot(configured, 1 / np.sqrt(12)), rel=0.1)
    # the hot pixels' dark-current shot noise is not the sensor's read noise: left out
    assert np.array_equal(maps.hot, cam.defect_maps[1]) and maps.hot.any()
    assert dark_noise_rms(maps.dark_std) > noise == dark_noise_rms(maps.dark_std, maps.hot)


def test_dark_noise_rms_where_most_pixels_never_change_code():
    """Frames of a read noise well below one code: most pixels show one code throughout
    (std 0), a few flip once. The median std is 0; the RMS is the noise the codes carry."""
    std = np.zeros((40, 50))
    std.flat[::7] = np.std([0, 0, 0, 1])  # one flip in four frames: 0.433
    assert float(np.median(std)) == 0.0
    rms = dark_noise_rms(std)
    assert rms == pytest.approx(0.433 / np.sqrt(7), rel=0.01)
    hot = np.zeros_like(std, dtype=bool)
    hot.flat[::7] = True
    assert dark_noise_rms(std, hot) == 0.0  # only the excluded pixels moved


def test_bad_flats_are_refused():
    cam = SimulatedCamera(COLS, ROWS, exposure_us=1000.0, pacing=False, seed=1)
    with cam:
        darks = Workflow(acquire_frames(cam, 4, stage="darks", what="dark")).run()
        cam.scene = np.full((ROWS, COLS), 0.001, dtype=np.float32)
        dim = Workflow(acquire_frames(cam, 4, stage="flats", what="flat")).run()
        cam.scene = np.full((ROWS, COLS), 1e6, dtype=np.float32)
        bright = Workflow(acquire_frames(cam, 4, stage="flats", what="flat")).run()
    with pytest.raises(CalibrationError, match="too dark"):
        pixel_maps(darks, dim)
    with pytest.raises(CalibrationError, match="saturated"):
        pixel_maps(darks, bright)


def test_repair_pixels():
    img = np.arange(49, dtype=float).reshape(7, 7)
    bad = np.zeros((7, 7), dtype=bool)
    bad[3, 3] = True  # isolated
    bad[0:3, 0:3] = True  # a cluster: its centre pixel has no good 3x3 neighbour
    out = repair_pixels(np.where(bad, 1e6, img), bad)
    # median of the good neighbours ((2, 2) is bad): 17, 18, 23, 25, 30, 31, 32
    assert out[3, 3] == pytest.approx(25.0)
    assert np.all(out[bad] < 100)
    assert np.array_equal(out[~bad], img[~bad])
    with pytest.raises(ValueError, match="does not match"):
        repair_pixels(img, bad[:3])


def test_darks_at_full_scale_are_refused(tmp_path):
    """A Mono8 camera whose dark frames sat at 255 (the sensor saturated) was calibrated:
    dark level 255, noise 0, no hot pixel, a file written."""
    cam = SimulatedCamera(COLS, ROWS, pixel_format="Mono8", dark_offset_adu=300.0,
                          exposure_us=100.0, pacing=False, seed=2)
    out = tmp_path / "darks.npz"
    with cam, pytest.raises(CalibrationError) as info:
        Workflow(calibrate_pixel_maps(cam, n_darks=4, settle=0, out=out)).run()
    text = str(info.value)
    assert "dark frames are at full scale (255, Mono8) in 100.0% of the pixels" in text
    assert "Close the shutter" in text and "lower the exposure" in text and "\n" not in text
    assert info.value.stage == "darks"
    assert not out.exists() and list(tmp_path.iterdir()) == []
    with cam:  # the pure function refuses them too
        darks = Workflow(acquire_frames(cam, 2, stage="darks", what="dark")).run()
    with pytest.raises(CalibrationError, match="at full scale"):
        pixel_maps(darks)


def test_one_dark_frame_leaves_the_noise_unknown(tmp_path):
    """One frame has no temporal noise: it reported (and saved) "noise 0"."""
    cam = SimulatedCamera(COLS, ROWS, exposure_us=100.0, pacing=False, seed=4)
    out = tmp_path / "darks.npz"
    with cam:
        maps = Workflow(calibrate_pixel_maps(cam, n_darks=1, settle=0, out=out)).run()
    assert maps.frames_averaged == 1 and maps.dark_noise_adu is None
    meta = load_calibration(out, expect="pixel-maps").metadata
    assert meta["dark_noise_adu"] is None and meta["dark_noise_median_std_adu"] is None
    assert meta["frames_averaged"] == 1
    with cam:  # two frames measure it
        two = Workflow(calibrate_pixel_maps(cam, n_darks=2, settle=0)).run()
    assert two.dark_noise_adu is not None and two.dark_noise_adu > 0
