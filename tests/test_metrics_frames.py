"""``lenslesscam metrics`` prepares the truth of frames, bands and planes like their result.

It read the truth like the reconstruction's measurement (row flip, downsampling, field, plan)
only for K = 1 results: a video reconstructed with --flip-rows was scored against the unflipped
truth without a word (9.04 dB instead of 12.98), and --downsample, --field full or a recon auto
plan that merged shutter bins stopped on a bare "shapes differ". Every expected reference here
is built by hand (flip, block means, zeros around, frame means), not by the code under test.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.clirun import run_cli as _run

H, W = 24, 32


def _rolling_shutter(bins: int) -> np.ndarray:
    """(bins, H): row r integrates during 2 consecutive bins, later rows later."""
    m = np.zeros((bins, H), np.float32)
    for r in range(H):
        start = r * (bins - 1) // H
        m[start:start + 2, r] = 1.0
    return m


def _moving(k: int, seed: int = 1) -> np.ndarray:
    from tests.scenes import blocks_scene

    s = blocks_scene(H, W, seed=seed).astype(np.float32)
    return np.stack([np.roll(s, (j, 2 * j), axis=(0, 1)) for j in range(k)])[None]  # (1,K,H,W)


def _video(folder, bins: int = 6):
    import torch

    from recon.models import build_model
    from recon.simulate import synthetic_psf

    psf = synthetic_psf((H, W), seed=2)
    shutter = _rolling_shutter(bins)
    truth = _moving(bins)
    b = build_model("video", psf, shutter=shutter).apply(torch.as_tensor(truth)).numpy()[0]
    np.save(folder / "psf.npy", psf)
    np.save(folder / "shutter.npy", shutter)
    np.save(folder / "meas.npy", b)
    np.save(folder / "truth.npy", truth)         # (1, K, H, W), as simulate writes it
    np.save(folder / "stack.npy", truth[0])      # (K, H, W)
    return truth.astype(np.float64)


def _fista(capsys, d, out, *extra, model="video", iters="100"):
    aux = ["--shutter", d / "shutter.npy"] if model == "video" else []
    code, _, err = _run(capsys, "recon", "fista", "--model", model, "--psf", d / "psf.npy",
                        *aux, "--meas", d / "meas.npy", "--tau", "1e-4", "--iters", iters,
                        *extra, "--out", d / out)
    assert code == 0, err
    return d / out


def _score(capsys, ref, est, *extra):
    code, out, err = _run(capsys, "metrics", "--ref", ref, "--est", est, "--gain-fit", *extra)
    assert code == 0, err
    return json.loads(out)


def _psnr_vs(ref, est_path):
    from recon.io import read_reconstruction
    from recon.metrics import gain_fit, psnr

    x = read_reconstruction(est_path)[0].astype(np.float64)
    assert ref.shape == x.shape
    return psnr(ref, gain_fit(ref, x)[0])


def _blocks(a, d):
    """d x d block means of the last two axes, a remainder dropped (by hand)."""
    h, w = a.shape[-2] // d, a.shape[-1] // d
    return a[..., :h * d, :w * d].reshape(*a.shape[:-2], h, d, w, d).mean(axis=(-3, -1))


def _refused(capsys, *argv):
    code, out, err = _run(capsys, "metrics", *argv)
    assert code == 2 and out == ""
    line = err.strip()
    assert "\n" not in line and "shapes differ" not in line
    return line


def test_a_video_reconstructed_with_flipped_rows_is_scored_against_the_flipped_truth(
        tmp_path, capsys):
    """The reported case: the rows (axis 2 of (C, K, H, W)) of every frame are flipped, for a
    (1, K, H, W) truth and a (K, H, W) stack alike, and ref_prepared says so."""
    truth = _video(tmp_path)
    rec = _fista(capsys, tmp_path, "flip.tif", "--flip-rows")
    flipped = np.ascontiguousarray(truth[:, :, ::-1])
    right, wrong = _psnr_vs(flipped, rec), _psnr_vs(truth, rec)
    assert right > wrong + 3  # the test can tell them apart
    for ref in ("truth.npy", "stack.npy"):
        report = _score(capsys, tmp_path / ref, rec)
        assert report["ref_prepared"] == {"color": "gray", "channel_order": "rgb",
                                          "flip_rows": True, "downsample": 1}
        assert report["psnr"] == pytest.approx(right, abs=1e-6)
        assert report["shape"] == [1, 6, H, W]


@pytest.mark.parametrize(("extra", "scene", "offset"), [
    (["--downsample", "2"], (12, 16), None),
    (["--field", "full"], (48, 64), (12, 16)),  # 48 // 2 - 24 // 2, 64 // 2 - 32 // 2
    # the loader's grid: sensor 12x16; the truth 24x32 -> 12x16 at 20 // 2 - 6, 28 // 2 - 8
    (["--field", "20x28", "--downsample", "2", "--flip-rows"], (20, 28), (4, 6)),
])
def test_video_frames_are_downsampled_and_placed_in_the_scene_field(tmp_path, capsys, extra,
                                                                   scene, offset):
    """A truth at sensor resolution on the sensor's field: box-downsampled like the
    measurement, placed where the forward model puts the sensor in a larger scene field and
    scored there only (the scene outside the truth's field is unknown, not dark); these
    stopped on "shapes differ"."""
    from recon.io import read_reconstruction
    from recon.metrics import gain_fit, psnr

    truth = _video(tmp_path)
    rec = _fista(capsys, tmp_path, "r.tif", *extra, iters="60")
    ds = 2 if "--downsample" in extra else 1
    t = truth[:, :, ::-1] if "--flip-rows" in extra else truth
    t = _blocks(t, ds) if ds > 1 else t
    x = read_reconstruction(rec)[0].astype(np.float64)
    assert x.shape == (1, 6, *scene)
    oy, ox = offset or (0, 0)
    window = x[..., oy:oy + t.shape[2], ox:ox + t.shape[3]]
    report = _score(capsys, tmp_path / "truth.npy", rec)
    assert report["shape"] == list(t.shape)
    assert report["psnr"] == pytest.approx(psnr(t, gain_fit(t, window)[0]), abs=1e-6)
    prep = report["ref_prepared"]
    assert prep["downsample"] == ds and prep["flip_rows"] == ("--flip-rows" in extra)
    if offset is None:
        assert "field" not in prep and "scored_window" not in prep
    else:
        assert prep["field"]["truth"] == [H // ds, W // ds]
        assert prep["field"]["scene"] == list(scene) and prep["field"]["offset"] == list(offset)
        assert "scored on the truth's field only" in prep["field"]["how"]
        assert prep["scored_window"] == [oy, oy + t.shape[2], ox, ox + t.shape[3]]
        # the place is the right one: the window a pixel off scores lower
        off = x[..., oy:oy + t.shape[2], ox + 1:ox + 1 + t.shape[3]]
        assert report["psnr"] > psnr(t, gain_fit(t, off)[0])


def test_a_recon_auto_video_is_scored_against_the_truth_merged_like_its_shutter_bins(
        tmp_path, capsys):
    """A plan of K = 3 frames from 5 shutter bins merges them 2 at a time (the last group
    holds one bin): the truth's frames are merged the same way, each the mean of its bins."""
    truth = _video(tmp_path, bins=5)
    code, _, err = _run(capsys, "recon", "auto", "--psf", tmp_path / "psf.npy", "--shutter",
                        tmp_path / "shutter.npy", "--meas", tmp_path / "meas.npy", "--tau",
                        "1e-4", "--set", "model=video", "--set", "k=3", "--set",
                        "downsample=1", "--set", f"region=[0,0,{H},{W}]", "--set",
                        "iterations=60", "--quiet", "--out", tmp_path / "auto.tif")
    assert code == 0, err
    merged = np.stack([truth[:, 0:2].mean(1), truth[:, 2:4].mean(1), truth[:, 4]], axis=1)
    report = _score(capsys, tmp_path / "truth.npy", tmp_path / "auto.tif")
    assert report["shape"] == [1, 3, H, W]
    assert report["psnr"] == pytest.approx(_psnr_vs(merged, tmp_path / "auto.tif"), abs=1e-6)
    frames = report["ref_prepared"]["frames"]
    assert (frames["from"], frames["bin_factor"], frames["to"]) == (5, 2, 3)
    assert report["ref_prepared"]["plan"]["base_bins"] == 5


def _planned(folder, x, plan):
    """A recon auto result x (C, K, 8, 10) with this plan, saved as lenslesscam writes it."""
    from recon.io import save_reconstruction

    pre = {"downsample": 1, "color": "gray", "channel_order": "rgb", "flip_rows": False,
           "field": [8, 10], "sensor": [8, 10]}
    kind = {"video": "video", "depth": "depth"}.get(plan["model"], "image")
    save_reconstruction(folder / "est.tif", x.astype(np.float32), {
        "preprocessing": pre, "region_on_grid": [0, 0, 8, 10],
        "plan": {"field": [8, 10], "downsample": 1, **plan}}, kind=kind)
    return folder / "est.tif"


@pytest.mark.parametrize(("plan", "values"), [
    ({"model": "video", "k": 3, "base_bins": 5, "bin_factor": 2}, [1.5, 3.5, 5.0]),
    ({"model": "video", "k": 2, "base_bins": 5, "bin_factor": 3}, [2.0, 4.5]),
    # no motion found: a 2D plan of a video measurement is one image of all the bins
    ({"model": "2d", "k": 1, "base_bins": 5, "bin_factor": None}, [3.0]),
])
def test_merged_frames_are_the_mean_of_the_bins_they_hold(tmp_path, capsys, plan, values):
    """Frame j of the truth is (j + 1) p: a merged frame is the mean of its bins, a partial
    last group too (its shutter row carries the smaller exposure, recon.preprocess.bin_time;
    the scene it sees is as bright: a still scene gives equal frames, not a dim last one)."""
    p = np.random.default_rng(0).random((8, 10)) + 0.5
    np.save(tmp_path / "t.npy", np.stack([(j + 1) * p for j in range(5)]))
    est = np.stack([v * p for v in values])[None] * 2.0
    report = _score(capsys, tmp_path / "t.npy", _planned(tmp_path, est, plan))
    assert report["psnr"] == "inf" or report["psnr"] > 100
    assert report["ref_prepared"]["frames"]["to"] == len(values)
    # a truth of another number of frames than the plan's shutter bins: refused, saying why
    np.save(tmp_path / "t4.npy", np.stack([(j + 1) * p for j in range(4)]))
    line = _refused(capsys, "--ref", tmp_path / "t4.npy", "--est", tmp_path / "est.tif")
    assert "has 4 frames" in line and "5 bins" in line


def test_a_depth_plan_keeps_the_truths_planes_it_reconstructs(tmp_path, capsys):
    """recon auto of a PSF stack keeps the planes the scene is in: the truth of every plane of
    the stack is cut to them."""
    import torch

    from recon.io import read_reconstruction
    from recon.models import build_model
    from recon.simulate import synthetic_psf
    from tests.scenes import blocks_scene

    stack = np.stack([synthetic_psf((H, W), seed=s) for s in range(5)]).astype(np.float32)
    scene = np.zeros((1, 5, H, W), np.float32)
    for k in (1, 2):
        scene[0, k] = blocks_scene(H, W, seed=k)
    b = build_model("depth", stack).apply(torch.as_tensor(scene)).numpy()[0]
    np.save(tmp_path / "stack.npy", stack)
    np.save(tmp_path / "meas.npy", b)
    np.save(tmp_path / "truth.npy", scene[0])  # (K, H, W): one plane per PSF plane
    code, _, err = _run(capsys, "recon", "auto", "--psf-stack", tmp_path / "stack.npy",
                        "--meas", tmp_path / "meas.npy", "--tau", "1e-4", "--set",
                        "downsample=1", "--set", f"region=[0,0,{H},{W}]", "--set",
                        "iterations=60", "--quiet", "--out", tmp_path / "d.tif")
    assert code == 0, err
    first, last = read_reconstruction(tmp_path / "d.tif")[1]["plan"]["planes"]
    assert last - first < 5  # the plan dropped planes: the case under test
    report = _score(capsys, tmp_path / "truth.npy", tmp_path / "d.tif")
    assert report["ref_prepared"]["planes"] == {"from": 5, "kept": [first, last]}
    kept = scene[:, first:last].astype(np.float64)
    assert report["psnr"] == pytest.approx(_psnr_vs(kept, tmp_path / "d.tif"), abs=1e-6)


def test_spectral_bands_are_flipped_and_downsampled(tmp_path, capsys):
    import torch

    from recon.models import build_model
    from recon.simulate import synthetic_psf

    rng = np.random.default_rng(4)
    psf = synthetic_psf((H, W), seed=2)
    filters = rng.random((4, H, W)).astype(np.float32)
    truth = np.concatenate([_moving(1) * (0.5 + 0.2 * k) for k in range(4)], axis=1)
    b = build_model("spectral", psf, filters=filters).apply(torch.as_tensor(truth)).numpy()[0]
    for name, arr in (("psf", psf), ("filters", filters), ("meas", b), ("truth", truth)):
        np.save(tmp_path / f"{name}.npy", arr)
    rec = _fista(capsys, tmp_path, "s.tif", "--filters", tmp_path / "filters.npy",
                 "--flip-rows", "--downsample", "2", model="spectral", iters="60")
    report = _score(capsys, tmp_path / "truth.npy", rec)
    ref = _blocks(truth.astype(np.float64)[:, :, ::-1], 2)
    assert report["shape"] == [1, 4, 12, 16] and "spectral_angle_deg" in report
    assert report["psnr"] == pytest.approx(_psnr_vs(ref, rec), abs=1e-6)
    assert report["ref_prepared"]["flip_rows"] is True


def test_a_truth_that_cannot_be_prepared_is_refused_saying_why(tmp_path, capsys):
    truth = _video(tmp_path)
    rec = _fista(capsys, tmp_path, "r.tif", iters="5")
    np.save(tmp_path / "five.npy", truth[:, :5])
    line = _refused(capsys, "--ref", tmp_path / "five.npy", "--est", rec)
    assert "has 5 frames; the video result has 6 frames" in line
    np.save(tmp_path / "small.npy", truth[..., :20, :30])
    line = _refused(capsys, "--ref", tmp_path / "small.npy", "--est", rec)
    assert "is 20x30" in line and "24x32 (the scene field)" in line
    # a 2x field at downsample 2 is 24x32 on the grid, as the sensor's field at sensor
    # resolution: which one the truth covers is not guessed; on the grid it is unambiguous
    full = _fista(capsys, tmp_path, "full.tif", "--field", "full", "--downsample", "2",
                  iters="5")
    line = _refused(capsys, "--ref", tmp_path / "truth.npy", "--est", full)
    assert "cannot tell which" in line and "12x16 for the sensor's field" in line
    assert "48x64 for the scene field" in line  # the 2x field's one unambiguous size
    np.save(tmp_path / "grid.npy", _blocks(truth, 2))
    report = _score(capsys, tmp_path / "grid.npy", full)
    assert report["ref_prepared"]["field"]["offset"] == [6, 8]
    # as stored on request: compared as stored, so the shapes are what differs
    code, _, err = _run(capsys, "metrics", "--ref", tmp_path / "five.npy", "--est", rec,
                        "--ref-as-is")
    assert code == 2 and "shapes differ" in err


def test_a_three_slice_stack_is_frames_for_a_three_frame_result(tmp_path, capsys):
    """A (3, H, W) file is RGB for an image, but three frames for a gray 3-frame result (it
    was turned to gray and refused as one image), flipped like them."""
    from recon.io import save_reconstruction

    t = np.random.default_rng(1).random((3, 8, 10))
    np.save(tmp_path / "t.npy", t)
    pre = {"downsample": 1, "color": "gray", "channel_order": "rgb", "flip_rows": True,
           "field": [8, 10], "sensor": [8, 10]}
    save_reconstruction(tmp_path / "v.tif", (2 * t[None, :, ::-1]).astype(np.float32),
                        {"preprocessing": pre}, kind="video")
    report = _score(capsys, tmp_path / "t.npy", tmp_path / "v.tif")
    assert report["psnr"] == "inf" or report["psnr"] > 100
    assert report["ref_prepared"]["flip_rows"] is True
