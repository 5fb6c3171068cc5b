"""The camera's black level is the automatic dark level, where the camera reports one.

The app's automatic dark level was the frame's 1st percentile, which on a lensless frame is
scene light: 152 codes on the simulated bench, whose black level is 100 (every pixel of a
caustic sees some light). The preview subtracted 52 codes of the scene: 28.2 against 29.3 dB
(gain-fitted, tau 1e-4, 300 iterations), and with the automatic tau, which the clipped frame
also misled (1e-4 against 3e-5), 28.2 against 30.7 dB. The jobs launched from the app and the
trade panel took the same level, and ``--dark auto`` on the same frame took another estimate
(the corner patch's mean, 330: 23.9 dB). A frame now carries the camera's black level
(``Frame.black_level``: the simulated camera's dark offset; GenICam and V4L2 report none), and
*auto* on a measurement is one rule in the app and the CLI: that level, else the frame's 1st
percentile (``recon.preprocess.measurement_dark_level``); a PSF's stays its corner patch.
"""

from __future__ import annotations

import numpy as np
import pytest

from app.gui.devices import SimConfig, make_sim_camera, sim_psf
from app.gui.preview_engine import PreviewEngine, PreviewSettings, frame_dark_level
from drivers.camera import FRAME_FORMAT, Frame, Roi, read_frame_metadata
from recon import readers
from recon.readers import load_measurement, recorded_black_level


def _psnr_gain_fitted(img: np.ndarray, truth: np.ndarray) -> float:
    x, t = img.astype(np.float64), truth.astype(np.float64)
    g = float((x * t).sum() / (x * x).sum())
    return float(10 * np.log10(t.max() ** 2 / np.mean((g * x - t) ** 2)))


@pytest.fixture(scope="module")
def bench():
    """The app's simulated bench (no pacing), one frame of its default scene."""
    cfg = SimConfig(pacing=False)
    cam = make_sim_camera(cfg, seed=3)
    cam.open()
    try:
        frame = cam.snap()
    finally:
        cam.close()
    return cfg, cam, frame


def test_a_simulated_frame_carries_its_black_level(bench):
    _, cam, frame = bench
    assert frame.black_level == cam.dark_offset_adu == 100.0
    assert frame.metadata()["black_level"] == 100.0
    # an estimate from the frame sits far above it on a lensless frame
    assert frame_dark_level(frame.pixels, None) > 140.0
    assert frame_dark_level(frame.pixels, None, frame.black_level) == 100.0
    assert frame_dark_level(frame.pixels, 80.0, frame.black_level) == 80.0  # typed: the user's


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf"), "dark", True])
def test_a_black_level_must_be_a_code(bad):
    with pytest.raises(ValueError, match="black level must be a finite number >= 0"):
        Frame(pixels=np.zeros((4, 4), np.uint16), frame_id=0, timestamp=0.0, exposure_us=None,
              gain=None, roi=Roi(0, 0, 4, 4), binning=1, pixel_format="Mono16", bit_depth=16,
              timing=None, backend="sim", camera_id="x", black_level=bad)


def test_the_preview_subtracts_the_cameras_level_and_sees_the_scene_better(bench):
    cfg, cam, frame = bench
    truth = np.asarray(cam.scene.image)
    low = float(np.percentile(np.asarray(frame.pixels), 1, method="lower"))
    psnr = {}
    for label, black in (("camera", frame.black_level), ("estimate", None)):
        # a fixed tau and no display rate: the automatic tau is chosen in the background and
        # the rate cuts iterations, both at the machine's pace
        eng = PreviewEngine(sim_psf(cfg), PreviewSettings(
            iters_per_frame=50, downsample=1, tau_auto=False, tau=1e-4, target_fps=0))
        for _ in range(6):
            res = eng.process(frame.pixels, black_level=black)
        assert res.shape == truth.shape
        psnr[label] = _psnr_gain_fitted(res.image, truth)
        if black is not None:
            assert res.dark == 100.0 and res.dark_note == "dark 100 (camera)"
        else:  # --dark auto's estimate, not a second one of the app's
            assert res.dark == pytest.approx(low, rel=1e-6) and low > 140.0
            assert res.dark_note.endswith("(1st percentile)")
    # 29.3 against 28.2 dB (300 iterations; the corner patch's 330: 23.9 dB); the margin
    # leaves room for other BLAS kernels (the noise draws are seeded)
    assert psnr["camera"] > psnr["estimate"] + 0.5, psnr


def test_the_app_and_the_cli_take_one_estimate_without_a_black_level(bench, tmp_path):
    """The app took the 1st percentile (152 on the bench's frame) and ``--dark auto`` the corner
    patch (330): one frame, two dark levels. A measurement's estimate is now the percentile in
    both (a PSF's stays the corner patch, unlit around its caustic)."""
    import tifffile

    from recon.readers import load_psf

    pixels = np.asarray(bench[2].pixels)
    p = tmp_path / "plain.tif"
    tifffile.imwrite(p, pixels)
    app_level = frame_dark_level(pixels, None, None)
    assert 140.0 < app_level < 160.0  # the bench's black level is 100: scene light on top
    cli = load_measurement(p, dark="auto", normalise=None)
    np.testing.assert_allclose(cli[0], np.clip(pixels.astype(np.float32) - app_level, 0, None),
                               rtol=0, atol=1e-3)
    # erased pixels (0 in the file, outside the mask) do not pull the estimate to 0
    erased = pixels.copy()
    erased[:, : pixels.shape[1] // 4] = 0
    mask = np.ones(pixels.shape, np.float32)
    mask[:, : pixels.shape[1] // 4] = 0
    tifffile.imwrite(tmp_path / "erased.tif", erased)
    got = load_measurement(tmp_path / "erased.tif", dark="auto", normalise=None, measured=mask)
    assert float(got[0][mask > 0].min()) == 0.0 and float(got[0].max()) < float(pixels.max())
    from recon.preprocess import measurement_dark_level

    level = float(measurement_dark_level(erased, mask).item())
    assert level > 100.0  # of the measured pixels, not the erased zeros
    # a PSF's auto is its corner patch, as the DiffuserCam tutorial's
    psf = np.round(50 + 5 * np.random.default_rng(2).standard_normal((40, 48))).astype(np.uint16)
    psf[20, 24] = 4000
    tifffile.imwrite(tmp_path / "psf.tif", psf)
    corner = float(psf[5:15, 5:15].astype(np.float64).mean())
    from recon.psfcheck import PsfWarning

    with pytest.warns(PsfWarning, match="noise around 0"):  # its floor's noise, clipped
        got = load_psf(tmp_path / "psf.tif", dark="auto", normalise=None)
    assert float(got[0, 20, 24]) == pytest.approx(4000 - corner, abs=1e-3)  # not 4000 - 38


def test_frame_keywords_hand_the_level_to_the_preview(bench):
    from app.gui.preview_engine import frame_keywords

    assert frame_keywords(bench[2])["black_level"] == 100.0


def test_the_frame_formats_of_drivers_and_recon_agree():
    assert readers.FRAME_FORMAT == FRAME_FORMAT  # recon cannot import drivers: kept equal here


def test_dark_auto_on_a_saved_frame_takes_the_recorded_level(bench, tmp_path):
    from app.gui.snapshots import save_frame

    frame = bench[2]
    tif = save_frame(frame, tmp_path / "snap.tif")[0]
    assert read_frame_metadata(tif)["black_level"] == 100.0
    assert recorded_black_level(tif) == 100.0
    auto = load_measurement(tif, dark="auto", normalise=None)
    typed = load_measurement(tif, dark=100.0, normalise=None)
    np.testing.assert_array_equal(auto, typed)
    # a plain image of the same pixels (no metadata) gets the estimate from its pixels
    import tifffile

    plain = tmp_path / "plain.tif"
    tifffile.imwrite(plain, np.asarray(frame.pixels))
    assert recorded_black_level(plain) is None
    est = load_measurement(plain, dark="auto", normalise=None)
    assert not np.array_equal(est, typed)  # 152: the darkest pixels of a lensless frame


def test_a_damaged_recorded_level_is_not_used(bench, tmp_path):
    import json

    import tifffile

    from recon.checks import MeasurementWarning

    meta = bench[2].metadata()
    for bad in (-5, "100", None, float("nan")):
        meta["black_level"] = bad
        p = tmp_path / f"bad-{bad}.tif"
        tifffile.imwrite(p, np.asarray(bench[2].pixels),
                         description=json.dumps(meta, default=str))
        if bad is None:  # not recorded: nothing to say
            assert recorded_black_level(p) is None
            continue
        with pytest.warns(MeasurementWarning, match=r"records black_level .* not used"):
            assert recorded_black_level(p) is None
    p = tmp_path / "neg.tif"
    meta["black_level"] = -5
    tifffile.imwrite(p, np.asarray(bench[2].pixels), description=json.dumps(meta))
    with pytest.raises(ValueError, match=r"neg\.tif: black level must be"):
        read_frame_metadata(p)


def test_the_cli_recon_with_dark_auto_uses_it(bench, tmp_path):
    import tifffile

    from app.cli import main
    from app.gui.snapshots import save_frame

    cfg = bench[0]
    tif = save_frame(bench[2], tmp_path / "snap.tif")[0]
    psf = tmp_path / "psf.npy"
    np.save(psf, sim_psf(cfg))
    outs = {}
    for dark in ("auto", "100"):
        out = tmp_path / f"r-{dark}.tif"
        assert main(["recon", "fista", "--psf", str(psf), "--meas", str(tif), "--dark", dark,
                     "--psf-dark", "0", "--tau", "1e-3", "--iters", "20", "--out", str(out)]) == 0
        outs[dark] = tifffile.imread(out)
    np.testing.assert_array_equal(outs["auto"], outs["100"])
