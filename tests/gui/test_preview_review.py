"""The live preview against the CLI, from a hostile review of the video model and the ROI.

- A video preview of a frame whose PSF was calibrated at a ROI took the shutter function's
  top sensor rows, not the ROI's: on the lower half of a sensor the bins' times were wrong
  (reversed on an outside-in sensor), with no word.
- The automatic tau of the video model was chosen for plain TV while the solver weighs time
  differences by half: a tau for another objective (3.2e-4 against the CLI rule's 1e-4).
- A memory refusal in the automatic-tau thread (a ``MemoryError``) killed it and left
  "tau auto: estimating" in the footer for good.
- A ROI not aligned to the downsampling kept a coarse pixel only when all its sensor pixels
  were measured, where every command keeps it when any is (``recon.preprocess.downsample_mask``):
  5.9 % off ``recon fista --mask`` on the same frame.
- 32 video bins asked showed 25 with no word; more bins than rows ran (the CLI refuses them);
  a global shutter showed K identical panels with no word.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from app.gui.preview_engine import PreviewEngine, PreviewError, PreviewSettings
from drivers.timing import SensorTiming, shutter_function
from recon.simulate import synthetic_psf


@pytest.fixture
def psf() -> np.ndarray:
    return synthetic_psf((48, 64), n_points=20, seed=1)


def _codes(psf: np.ndarray, seed: int = 0) -> np.ndarray:
    from recon.models import build_model

    rng = np.random.default_rng(seed)
    scene = np.zeros((1, 1, *psf.shape), dtype=np.float32)
    scene[0, 0, 12:36, 14:50] = rng.random((24, 36), dtype=np.float32)
    with torch.no_grad():
        b = build_model("2d", psf).apply(torch.as_tensor(scene)).numpy().reshape(psf.shape)
    return (100 + 3000 * b / b.max()).round().astype(np.uint16)


def _settings(**kw: object) -> PreviewSettings:
    base = {"tau": 1e-4, "tau_auto": False, "iters_per_frame": 1, "target_fps": 0.0,
            "dark": 100.0}
    base.update(kw)
    return PreviewSettings(**base)


def test_a_roi_psfs_video_model_takes_the_rois_rows(psf: np.ndarray) -> None:
    h, w = psf.shape
    timing = SensorTiming(rows=2 * h, line_time_us=10.0, exposure_lines=8)  # 96-row sensor
    eng = PreviewEngine(psf, _settings(model="video", video_bins=4, downsample=1))
    frame = _codes(psf)
    eng.process(frame, roi=(0, h, w, h), sensor=(2 * h, w), timing=timing)  # the lower half
    used = eng._build_args[1]["shutter"]
    factor = -(-timing.frame_lines // 4)
    full = shutter_function(timing, factor)
    np.testing.assert_allclose(used, full[:, h : 2 * h], rtol=0, atol=1e-6)
    assert not np.allclose(used, full[:, :h])  # the top rows it took before


def test_the_automatic_tau_is_chosen_for_the_solvers_tv(psf: np.ndarray,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    import recon.autotau as at

    seen: list[object] = []
    real = at.choose_tau

    def spy(model: object, b: object, **kw: object) -> object:
        seen.append(kw.get("tv"))
        return real(model, b, **kw)

    monkeypatch.setattr(at, "choose_tau", spy)
    timing = SensorTiming(rows=psf.shape[0], line_time_us=10.0, exposure_lines=8)
    eng = PreviewEngine(psf, _settings(model="video", video_bins=3, downsample=2,
                                       tau_auto=True))
    frame = _codes(psf)
    eng.process(frame, timing=timing)
    assert eng.wait_auto(120)
    eng.process(frame, timing=timing)
    assert seen and seen[0] is not None
    assert seen[0].weight_k == pytest.approx(eng._solver.tv.weight_k) == pytest.approx(0.5)


def test_a_failed_automatic_tau_says_so(psf: np.ndarray, monkeypatch: pytest.MonkeyPatch) -> None:
    import recon.autotau as at

    def refuse(*_a: object, **_k: object) -> object:
        raise MemoryError("the estimate's model needs 9 GB, 1 GB available")

    monkeypatch.setattr(at, "choose_tau", refuse)
    eng = PreviewEngine(psf, _settings(tau_auto=True, tau=3e-4))
    frame = _codes(psf)
    eng.process(frame)
    assert eng.wait_auto(60)
    r = eng.process(frame)
    assert r.tau == 3e-4
    assert r.tau_note.startswith("tau auto failed (the estimate's model needs 9 GB")
    assert not eng.auto_pending


def test_an_unaligned_roi_is_downsampled_as_the_cli_does(psf: np.ndarray,
                                                          tmp_path: object) -> None:
    import tifffile

    from app.cli import main
    from recon.preprocess import downsample_mask

    h, w = psf.shape
    codes = _codes(psf)
    x, y, rw, rh = 3, 5, 41, 30  # not on the 4-pixel blocks
    eng = PreviewEngine(psf, _settings(downsample=4, iters_per_frame=60, prox_iters=3))
    r = eng.process(codes[y : y + rh, x : x + rw], roi=(x, y, rw, rh), sensor=(h, w))
    sensor_mask = np.zeros((h, w), np.float32)
    sensor_mask[y : y + rh, x : x + rw] = 1
    np.testing.assert_array_equal(eng._mask, downsample_mask(sensor_mask, 4))
    meas = np.zeros((h, w), np.uint16)
    meas[y : y + rh, x : x + rw] = codes[y : y + rh, x : x + rw]
    d = tmp_path  # type: ignore[assignment]
    np.save(d / "meas.npy", meas)
    np.save(d / "mask.npy", sensor_mask)
    np.save(d / "psf.npy", psf)
    assert main(["--threads", "1", "recon", "fista", "--psf", str(d / "psf.npy"), "--psf-dark",
                 "0", "--meas", str(d / "meas.npy"), "--mask", str(d / "mask.npy"), "--dark",
                 "100", "--downsample", "4", "--tau", "1e-4", "--iters", "60", "--prox-iters",
                 "3", "--precondition", "off", "--tol", "0", "--out", str(d / "rec.tif")]) == 0
    cli = tifffile.imread(d / "rec.tif").astype(np.float32).reshape(r.image.shape)
    # the same FISTA-TV on the same data; float32 sums in another order (5.9 % before)
    rel = float(np.linalg.norm(cli - r.image) / np.linalg.norm(cli))
    assert rel < 1e-3, rel


def test_video_bins_are_said_and_checked(psf: np.ndarray) -> None:
    frame = _codes(psf)
    eng = PreviewEngine(psf, _settings(model="video", video_bins=32, downsample=1))
    r = eng.process(frame, timing=SensorTiming(rows=48, line_time_us=10.0, exposure_lines=26))
    k = eng._build_args[1]["shutter"].shape[0]
    assert k < 32 and r.model_note.startswith(f"{k} bins of ") and "(32 asked)" in r.model_note
    # more bins than the rows of the grid: the CLI's refusal, in the preview's words
    eng = PreviewEngine(psf, _settings(model="video", video_bins=32, downsample=8))
    with pytest.raises(PreviewError, match=r"time bins for 6 rows.*the preview's video bins"):
        eng.process(frame, timing=SensorTiming(rows=48, line_time_us=10.0, exposure_lines=26))
    # a global shutter: every bin the same, said
    eng = PreviewEngine(psf, _settings(model="video", video_bins=4, downsample=1))
    r = eng.process(frame, timing=SensorTiming(rows=48, line_time_us=10.0, exposure_lines=20,
                                               pattern="global"))
    assert "global shutter" in r.model_note and "2D model" in r.model_note
    # an exposure the bins do not divide (the last bin partial) is said alike
    eng = PreviewEngine(psf, _settings(model="video", video_bins=4, downsample=1))
    r = eng.process(frame, timing=SensorTiming(rows=48, line_time_us=10.0, exposure_lines=22,
                                               pattern="global"))
    assert "global shutter" in r.model_note, r.model_note
    r2 = PreviewEngine(psf, _settings()).process(frame)
    assert r2.model_note == ""


def test_the_video_models_norm_is_a_cancellation_point(psf: np.ndarray,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """The power iteration of a video model's Lipschitz constant ran to its end after a cancel
    (17 s at 512x512 with 32 bins: closing the window detached the thread)."""
    import recon.operators as ops
    from app.gui.preview_engine import PreviewCancelled

    eng = PreviewEngine(psf, _settings(model="video", video_bins=4, downsample=1))
    ran: list[int] = []
    real = ops.power_norm

    def cancel_then_run(op: object, *a: object, step: object = None, **k: object) -> float:
        eng.cancel()  # as the GUI does from another thread while the model is built

        def counted() -> None:
            ran.append(1)
            step()  # type: ignore[operator]

        return real(op, *a, step=counted, **k)

    monkeypatch.setattr(ops, "power_norm", cancel_then_run)
    with pytest.raises(PreviewCancelled):
        eng.process(_codes(psf), timing=SensorTiming(rows=48, line_time_us=10.0,
                                                     exposure_lines=8))
    assert ran == [1]  # stopped at the first power iteration, not after 50
    monkeypatch.setattr(ops, "power_norm", real)
    eng.resume()
    r = eng.process(_codes(psf), timing=SensorTiming(rows=48, line_time_us=10.0,
                                                     exposure_lines=8))
    assert r.shape[0] == 48 and np.isfinite(r.image).all()  # built whole the next time
