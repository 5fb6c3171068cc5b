"""PSF capture end to end on the simulated camera + simulated point source (real PTY)."""

from __future__ import annotations

import math
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from calibration.psf import (
    PsfSettings,
    autocorrelation_fwhm,
    capture_depth_stack,
    capture_psf,
    centre_psf,
    centroid,
    crop_or_pad,
    psf_quality,
)
from calibration.workflow import CalibrationCancelled, CalibrationError, Workflow
from drivers.lightstate import LightMode
from recon.calibfile import load_calibration, load_psf_calibration
from recon.fista import Fista
from recon.io import load_psf
from recon.metrics import gain_fit, psnr
from recon.models import build_model
from recon.simulate import render_frames, simulate
from tests.calibration.conftest import COLS, ON_AXIS, ROWS, out_dir_files

FAST = PsfSettings(n_frames=8, n_darks=8, intensity=1.0, settle_frames=0, frame_timeout_s=2.0)


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    x = a.astype(np.float64).ravel() - a.mean()
    y = b.astype(np.float64).ravel() - b.mean()
    return float(x @ y / (np.linalg.norm(x) * np.linalg.norm(y)))


def _scene() -> np.ndarray:
    s = np.zeros((ROWS, COLS), dtype=np.float32)
    s[10:30, 12:30] = 1.0
    s[40:55, 45:70] = 0.6
    s[20:50, 55:60] = 0.8
    y, x = np.mgrid[0:ROWS, 0:COLS]
    s += 0.7 * np.exp(-((y - 45) ** 2 + (x - 20) ** 2) / 40.0).astype(np.float32)
    return s


def _fista_psnr(psf: np.ndarray, meas: np.ndarray, truth: np.ndarray) -> float:
    model = build_model("2d", psf)
    solver = Fista(model.op, torch.as_tensor(meas), tau=3e-4, max_iter=250, tol=0)
    est = solver.run().x.numpy()
    fitted, _ = gain_fit(truth, est)
    return psnr(truth, fitted)


def test_end_to_end_capture_matches_true_psf_and_reconstructs(
    make_camera, source, true_psf, tmp_path
):
    cam = make_camera(hot_pixel_fraction=0.003)
    out = tmp_path / "psf.tif"
    events = []
    wf = Workflow(capture_psf(cam, source, FAST, out=out), "PSF")
    for p in wf:
        events.append(p)
    cal = wf.result

    # the progress is a proper stepwise report
    fractions = [p.fraction for p in events]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    assert {"setup", "darks", "exposure", "frames", "quality", "save", "done"} <= {
        p.stage for p in events
    }
    assert source.status().mode is LightMode.OFF  # left off

    # the PSF is the simulator's
    assert cal.psf.dtype == np.float32 and cal.psf.shape == (ROWS, COLS)
    assert _ncc(cal.psf, true_psf) >= 0.99
    assert np.all(cal.psf >= 0)
    _, hot = cam.defect_maps
    assert hot.sum() > 0 and np.array_equal(cal.hot, hot)  # found and repaired

    # the quality report is right
    q = cal.quality
    assert q.saturated_pixels == 0
    assert 0.7 - 0.06 <= q.peak_fraction <= 0.8 + 0.02
    assert q.snr > 100
    ref = psf_quality(true_psf, noise_adu=1e-9, peak_fraction=0.75, saturated_pixels=0)
    assert abs(q.autocorr_fwhm_px[0] - ref.autocorr_fwhm_px[0]) < 0.2
    assert abs(q.autocorr_fwhm_px[1] - ref.autocorr_fwhm_px[1]) < 0.2
    assert abs(q.support_pixels - ref.support_pixels) <= 0.05 * ref.support_pixels
    assert np.allclose(q.centroid_px, ref.centroid_px, atol=0.3)
    # peak in ADU = flux * exposure * PSF peak * conversion gain
    expected_peak = 5e6 * cal.exposure_us / 1000 * true_psf.max() * cam.adu_per_electron
    assert q.peak_adu == pytest.approx(expected_peak, rel=0.03)

    # the file holds the PSF and its metadata, and recon's loaders read it
    psf_file, meta = load_psf_calibration(out)
    assert np.array_equal(psf_file, cal.psf)
    assert meta["format"] == "lenslesscam.psf-calibration"
    assert meta["exposure_us"] == cal.exposure_us and meta["frames_averaged"] == FAST.n_frames
    assert meta["camera"]["backend"] == "sim" and meta["timing"]["rows"] == ROWS
    assert meta["quality"]["saturated_pixels"] == 0
    assert meta["source"].startswith("LENSLESSCAM")
    assert load_psf(out).shape == (1, ROWS, COLS)
    assert out_dir_files(tmp_path) == sorted(["psf.tif", "light-state.json"])

    # FISTA with the captured PSF is as good as with the true one
    truth = _scene()
    sim = simulate(build_model("2d", true_psf), truth[None, None], noise=0.005, seed=1)
    p_true = _fista_psnr(true_psf, sim.meas, truth[None, None])
    p_cap = _fista_psnr(cal.normalised(), sim.meas, truth[None, None])
    assert p_true > 20
    assert abs(p_cap - p_true) <= 0.5, (p_cap, p_true)


def test_saturated_source_is_refused_and_nothing_saved(make_camera, source, tmp_path):
    cam = make_camera(point_flux_e_per_ms=1e13)  # saturates even at the shortest exposure
    out = tmp_path / "psf.tif"
    with pytest.raises(CalibrationError, match="saturated") as info:
        Workflow(capture_psf(cam, source, FAST, out=out)).run()
    assert "intensity" in str(info.value)  # says what to change
    assert info.value.stage == "exposure"
    assert not out.exists() and out_dir_files(tmp_path) == ["light-state.json"]
    assert source.status().mode is LightMode.OFF


def test_no_point_source_is_said_and_nothing_saved(make_camera, tmp_path):
    """The app's point source disconnected between the wizard's pages reached the capture as
    None: "'NoneType' object has no attribute 'identify'"; now the one-line calibration error
    that says to connect it."""
    from calibration.shutter import ShutterSettings, measure_shutter

    out = tmp_path / "psf.tif"
    with pytest.raises(CalibrationError, match=r"no point source is connected.*Connect the "
                                               r"point source") as info:
        Workflow(capture_psf(make_camera(), None, FAST, out=out)).run()
    assert info.value.stage and not out.exists()
    with pytest.raises(CalibrationError, match="no point source is connected"):
        Workflow(measure_shutter(make_camera(), None, ShutterSettings())).run()


def test_saturated_psf_at_fixed_exposure_is_refused(make_camera, source, tmp_path):
    cam = make_camera(point_flux_e_per_ms=5e7)
    settings = PsfSettings(
        n_frames=4,
        n_darks=4,
        intensity=1.0,
        auto_exposure=False,
        exposure_us=2000.0,
        settle_frames=0,
    )
    out = tmp_path / "psf.tif"
    with pytest.raises(CalibrationError, match=r"PSF is saturated: \d+ pixels"):
        Workflow(capture_psf(cam, source, settings, out=out)).run()
    assert out_dir_files(tmp_path) == ["light-state.json"]


def test_source_that_never_turns_on_is_refused(make_camera, source, tmp_path):
    # the camera looks at another bench: it never sees this source's light
    cam = make_camera(light_state=tmp_path / "elsewhere.json")
    before = cam.exposure_us
    out = tmp_path / "psf.tif"
    settings = PsfSettings(
        n_frames=4, n_darks=4, intensity=1.0, max_exposure_us=5000.0, settle_frames=0
    )
    with pytest.raises(CalibrationError, match="no light from the point source") as info:
        Workflow(capture_psf(cam, source, settings, out=out)).run()
    assert "switched on" in str(info.value) and "5000 us" in str(info.value)
    assert out_dir_files(tmp_path) == ["light-state.json"]
    assert source.status().mode is LightMode.OFF
    # auto-exposure went to its limit looking for light: the camera gets its exposure back
    assert cam.exposure_us == before != 5000.0


def test_camera_timeout_mid_capture_stops_cleanly(make_camera, source, true_psf, tmp_path):
    render = render_frames(true_psf)
    cams = []
    calls = [0]

    def unplug_after_some_lit_frames(frames, shutter):
        calls[0] += 1
        if calls[0] == 4:  # the camera dies in the middle of the PSF frames
            cams[0].simulate_unplug()
        return render(frames, shutter)

    cam = make_camera(renderer=unplug_after_some_lit_frames)
    cams.append(cam)
    settings = PsfSettings(
        n_frames=8,
        n_darks=4,
        intensity=1.0,
        auto_exposure=False,
        exposure_us=500.0,
        settle_frames=0,
        frame_timeout_s=0.3,
    )
    out = tmp_path / "psf.tif"
    stages = []
    with pytest.raises(CalibrationError, match=r"camera failed at PSF frame \d+ of 8") as info:
        for p in Workflow(capture_psf(cam, source, settings, out=out)):
            stages.append(p.stage)
    assert "frames" in stages and "no frame within" in str(info.value)
    assert "nothing was saved" in str(info.value)
    assert out_dir_files(tmp_path) == ["light-state.json"]
    assert source.status().mode is LightMode.OFF


def test_off_centre_source_is_refused(make_camera, source, tmp_path):
    cam = make_camera(point_position=(ON_AXIS[0], ON_AXIS[1] + 30))  # 30 columns aside
    settings = PsfSettings(
        n_frames=4, n_darks=4, intensity=1.0, settle_frames=0, max_offcentre=0.15
    )
    with pytest.raises(CalibrationError, match="off-centre") as info:
        Workflow(capture_psf(cam, source, settings, out=tmp_path / "psf.tif")).run()
    assert "Move the point source" in str(info.value)
    assert out_dir_files(tmp_path) == ["light-state.json"]


def test_cancel_leaves_no_file_and_light_off(make_camera, source, tmp_path):
    cam = make_camera()
    wf = Workflow(capture_psf(cam, source, FAST, out=tmp_path / "psf.tif"), "PSF")
    with pytest.raises(CalibrationCancelled, match="during frames"):
        for p in wf:
            if p.stage == "frames":
                wf.cancel()
    assert out_dir_files(tmp_path) == ["light-state.json"]
    assert source.status().mode is LightMode.OFF


def test_depth_stack_follows_the_moving_source(make_camera, source, tmp_path):
    cam = make_camera()
    shifts = {"near": 0, "mid": 4, "far": -6}

    def move(index: int, position: str) -> None:  # the "user" moves the source sideways
        cam.point_position = (ON_AXIS[0], ON_AXIS[1] + shifts[position])

    out = tmp_path / "stack.tif"
    settings = PsfSettings(n_frames=4, n_darks=4, intensity=1.0, settle_frames=0)
    wf = Workflow(
        capture_depth_stack(cam, source, list(shifts), prompt=move, settings=settings, out=out)
    )
    moves = [p.data["position"] for p in wf if p.stage == "move"]
    stack = wf.result
    assert moves == list(shifts)
    assert stack.stack.shape == (3, ROWS, COLS)
    for k, dx in enumerate(shifts.values()):
        cx = centroid(stack.stack[k])[1]
        assert cx - centroid(stack.stack[0])[1] == pytest.approx(dx, abs=0.3)
    cal = load_calibration(out, expect="psf-stack")
    assert cal.metadata["positions"] == list(shifts)
    assert len(cal.metadata["planes"]) == 3
    assert np.array_equal(cal.data, stack.stack)


def test_autocorrelation_width_of_a_gaussian():
    sigma = 2.0
    expected = 2 * math.sqrt(2 * math.log(2)) * sigma * math.sqrt(2)
    y, x = np.mgrid[0:128, 0:128]
    g = np.exp(-((y - 64.0) ** 2 + (x - 64.0) ** 2) / (2 * sigma**2))
    fy, fx = autocorrelation_fwhm(g)
    assert fy == pytest.approx(expected, rel=0.05) and fx == pytest.approx(expected, rel=0.05)
    # on a frame only 8x the peak's width, removing the envelope (sigma = 1/8 of the frame)
    # takes some of the peak's tails with it: narrower, by less than 15 %
    small = autocorrelation_fwhm(g[32:96, 32:96])
    assert all(0.85 * expected < f < expected for f in small)


def test_centring_and_crop_pad():
    img = np.zeros((20, 30))
    img[3:6, 4:7] = 1.0  # centroid (4, 5)
    out, shift = centre_psf(img, "centroid")
    assert shift == (6, 10) and centroid(out) == pytest.approx((10.0, 15.0))
    out, shift = centre_psf(img, (4.0, 5.0), shape=(10, 40))
    assert out.shape == (10, 40) and out.sum() == pytest.approx(9.0)
    assert centroid(out) == pytest.approx((5.0, 20.0))
    assert crop_or_pad(np.ones((4, 4)), (2, 6)).sum() == pytest.approx(8.0)
    with pytest.raises(ValueError, match="outside"):
        centre_psf(img, (25.0, 1.0))


def test_settings_are_validated():
    with pytest.raises(ValueError, match="target peak"):
        PsfSettings(target_peak=0.98, peak_tolerance=0.05)
    with pytest.raises(ValueError, match="centre"):
        PsfSettings(centre="middle")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="n_frames"):
        PsfSettings(n_frames=0)


def test_quality_report_flags_no_signal(tmp_path: Path):
    rng = np.random.default_rng(0)
    noise_only = np.maximum(rng.normal(0, 1, (ROWS, COLS)), 0)
    q = psf_quality(noise_only, noise_adu=1.0, peak_fraction=0.03, saturated_pixels=0)
    from calibration.psf import check_quality

    with pytest.raises(CalibrationError, match="no PSF signal above the dark noise"):
        check_quality(q, PsfSettings(), exposure_us=100.0)


def test_source_killed_mid_capture_stops_within_one_frame(
    make_camera, source, firmware, true_psf, tmp_path
):
    """The firmware dies while the light must stay on: the very next frame ends the capture."""
    render = render_frames(true_psf)
    lit_frames = [0]

    def kill_after_two_lit_frames(frames, shutter):
        out = render(frames, shutter)
        if source.is_on:
            lit_frames[0] += 1
            if lit_frames[0] == 2:
                firmware.kill()
        return out

    cam = make_camera(renderer=kill_after_two_lit_frames)
    settings = PsfSettings(
        n_frames=20,
        n_darks=2,
        intensity=1.0,
        auto_exposure=False,
        exposure_us=500.0,
        settle_frames=0,
        frame_timeout_s=2.0,
    )
    out = tmp_path / "psf.tif"
    taken = []  # PSF frames the capture took (one progress event each)
    with pytest.raises(CalibrationError, match="point source failed to report its state") as info:
        for p in Workflow(capture_psf(cam, source, settings, out=out)):
            if p.stage == "frames":
                taken.append(p)
    # the kill happens while the camera renders the 2nd lit frame: the check after the next
    # frame taken stops the capture (the camera may have rendered ahead into its queue, which
    # is why frames taken, not frames rendered, are counted); before the per-frame check all
    # 20 were taken and the error came only at switch-off
    assert lit_frames[0] >= 2 and len(taken) <= 2, (lit_frames, len(taken))
    assert "port vanished" in str(info.value) and "nothing was saved" in str(info.value)
    assert not out.exists()
    assert not source.is_open  # the driver dropped the dead port


def test_an_unreachable_snr_target_is_not_blamed_on_the_light(make_camera, source, tmp_path):
    """--min-snr 100000: auto-exposure went round between "no light" (one test frame below
    the target) and "saturated" until it gave up: "did not converge ... Check that the light
    is stable". The light is there; the averaging cannot reach the target."""
    cam = make_camera()
    settings = replace(FAST, min_snr=1e5)
    out = tmp_path / "psf.tif"
    with pytest.raises(CalibrationError) as info:
        Workflow(capture_psf(cam, source, settings, out=out)).run()
    text = str(info.value)
    assert info.value.stage == "quality" and "\n" not in text
    assert "stable" not in text and "no PSF signal" not in text
    m = re.search(r"PSF SNR (\S+) is below the SNR target 100000: the light is there", text)
    assert m and 1e3 < float(m.group(1)) < 1e5, text
    assert "8 PSF and 8 dark frames" in text and "lower the SNR target" in text
    # the number of frames it names would reach the target (SNR ~ sqrt(frames))
    n = int(re.search(r"about (\d+) PSF and \d+ dark frames reach it", text).group(1))
    assert float(m.group(1)) * math.sqrt(n / 8) >= 1e5 > float(m.group(1)) * math.sqrt(
        (n - 1) / 8)
    assert out_dir_files(tmp_path) == ["light-state.json"]


@pytest.mark.parametrize("target", [1e100, 1e200])
def test_an_absurd_snr_target_is_out_of_reach_not_a_crash(make_camera, source, tmp_path,
                                                          target):
    """--min-snr 1e200 ended in OverflowError after the whole capture; 1e100 advised
    averaging a 190-digit number of frames."""
    cam = make_camera()
    with pytest.raises(CalibrationError) as info:
        Workflow(capture_psf(cam, source, replace(FAST, min_snr=target),
                             out=tmp_path / "psf.tif")).run()
    text = str(info.value)
    assert "more than 1,000,000 PSF and dark frames each would be needed: the target is out " \
           "of reach" in text, text
    assert not (tmp_path / "psf.tif").exists()


def test_quality_check_tells_no_signal_from_an_unreachable_target():
    from calibration.psf import check_quality

    peak = np.zeros((ROWS, COLS))
    peak[30:34, 38:42] = 50.0  # 50 x the noise: light
    q = psf_quality(peak, noise_adu=1.0, peak_fraction=0.3, saturated_pixels=0)
    with pytest.raises(CalibrationError, match="below the SNR target 100") as info:
        check_quality(q, PsfSettings(min_snr=100), exposure_us=1000.0)
    # the peak is below the target peak: a longer exposure helps too
    assert "a longer exposure or a brighter source" in str(info.value)
    check_quality(q, PsfSettings(min_snr=40), exposure_us=1000.0)  # reached: no refusal
    weak = psf_quality(peak / 10, noise_adu=1.0, peak_fraction=0.03, saturated_pixels=0)
    with pytest.raises(CalibrationError, match="no PSF signal above the dark noise"):
        check_quality(weak, PsfSettings(min_snr=100), exposure_us=1000.0)


def test_the_report_describes_the_saved_cropped_psf(make_camera, source, tmp_path):
    """--shape 32x40 printed the report of the 64x80 capture (its peak, support, centroid)
    and said nothing of the two thirds of the light the crop cut off."""
    cam = make_camera()
    out = tmp_path / "psf.tif"
    cal = Workflow(capture_psf(cam, source, replace(FAST, shape=(32, 40)), out=out)).run()
    saved, meta = load_psf_calibration(out)
    q = cal.quality
    assert saved.shape == (32, 40)
    assert q.peak_adu == pytest.approx(float(saved.max())) and q.total_adu == pytest.approx(
        float(saved.sum(dtype=np.float64)), rel=1e-6)
    assert q.support_fraction == pytest.approx(q.support_pixels / (32 * 40))
    assert cal.captured_quality is not None and cal.captured_quality.peak_adu > q.peak_adu
    assert meta["quality"] == q.to_dict()
    assert meta["quality_as_captured"] == cal.captured_quality.to_dict()
    # the crop cut off about half of the light: warned, one line, and kept in the file
    kept = meta["processing"]["light_kept"]
    assert 0.2 < kept < 0.8
    assert len(cal.warnings) == 1 and "\n" not in cal.warnings[0]
    assert (f"crop to 32x40 of the 64x80 capture leaves out {100 * (1 - kept):.0f}% of the "
            "PSF's light") in cal.warnings[0]
    assert meta["warnings"] == list(cal.warnings)
    from app.gui.calibration_wizard import psf_report  # the wizard's report says it too

    assert f"warning         {cal.warnings[0]}" in psf_report(cal).splitlines()
    # padding loses nothing: no warning, the same peak
    padded = Workflow(capture_psf(cam, source, replace(FAST, shape=(80, 96)))).run()
    assert padded.warnings == () and padded.metadata["processing"]["light_kept"] == 1.0
    assert padded.quality.peak_adu == pytest.approx(padded.captured_quality.peak_adu)


def test_pixel_maps_of_another_size_are_refused_naming_both_sizes(make_camera, source):
    """The bad-pixel map of another sensor size was a numpy broadcast error."""
    cam = make_camera()
    bad = np.zeros((32, 40), dtype=bool)
    with pytest.raises(CalibrationError) as info:
        Workflow(capture_psf(cam, source, FAST, bad_pixels=bad,
                             bad_pixels_from="--pixel-maps small.npz")).run()
    text = str(info.value)
    assert text.startswith("--pixel-maps small.npz is 32x40 (rows x columns) and the camera's "
                           "frames are 64x80")
    assert "broadcast" not in text and "\n" not in text
    assert source.status().mode is LightMode.OFF


def test_one_dark_frame_leaves_the_psf_dark_noise_unknown(make_camera, source):
    cam = make_camera()
    cal = Workflow(capture_psf(cam, source, replace(FAST, n_darks=1))).run()
    assert cal.metadata["darks_averaged"] == 1 and cal.metadata["dark_noise_adu"] is None
    assert Workflow(capture_psf(cam, source, FAST)).run().metadata["dark_noise_adu"] > 0


def test_source_switched_off_mid_capture_is_refused(make_camera, source, firmware, true_psf,
                                                    tmp_path):
    """The light went off during the frames (a firmware restart comes back off; another
    program on the port): the source still answered, so the average of lit and dark frames
    was saved as the PSF (peak at 26 % of full scale against 74 %), exit 0."""
    render = render_frames(true_psf)
    lit_frames = [0]

    def off_after_three_lit_frames(frames, shutter):
        out = render(frames, shutter)
        if source.is_on:
            lit_frames[0] += 1
            if lit_frames[0] == 3:
                source.off()  # as a restart or another program would leave it
        return out

    cam = make_camera(renderer=off_after_three_lit_frames)
    settings = PsfSettings(n_frames=20, n_darks=2, intensity=1.0, auto_exposure=False,
                           exposure_us=500.0, settle_frames=0, frame_timeout_s=2.0)
    out = tmp_path / "psf.tif"
    with pytest.raises(CalibrationError, match=r"frames: the point source changed while its "
                                               r"frames were taken \(mode on -> off") as info:
        for _ in Workflow(capture_psf(cam, source, settings, out=out)):
            pass
    assert "nothing was saved" in str(info.value)
    assert not out.exists()


def test_a_crop_that_leaves_out_nearly_all_light_is_refused(make_camera, source, tmp_path):
    """--shape 1x1 warned that it left out 100 % of the light, then saved a 1x1 PSF
    ("resolution nan"), exit 0."""
    cam = make_camera()
    out = tmp_path / "psf.tif"
    with pytest.raises(CalibrationError, match=r"crop to 1x1 of the 64x80 capture leaves out "
                                               r"100% of the PSF's light") as info:
        Workflow(capture_psf(cam, source, replace(FAST, shape=(1, 1)), out=out)).run()
    assert "nothing was saved" in str(info.value) and not out.exists()


def test_auto_exposure_stopped_at_its_limit_is_said(make_camera, source, tmp_path):
    """A dim source: auto-exposure ended at its longest exposure with the peak far below the
    target (18 % against 75 %), and the PSF was saved without a word."""
    cam = make_camera()
    settings = replace(FAST, intensity=0.02, max_exposure_us=2000.0)
    cal = Workflow(capture_psf(cam, source, settings, out=tmp_path / "psf.tif")).run()
    said = [w for w in cal.warnings if w.startswith("auto-exposure stopped at the longest "
                                                    "exposure allowed (2000 us)")]
    assert len(said) == 1 and "not the target 75 +/- 5%" in said[0], cal.warnings
    assert cal.metadata["warnings"] == list(cal.warnings)
    # a source bright enough for the target: nothing said
    ok = Workflow(capture_psf(cam, source, FAST)).run()
    assert not [w for w in ok.warnings if "auto-exposure" in w]
