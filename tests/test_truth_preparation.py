"""One preparation of a truth (recon.truth): a run's scores and ``metrics`` agree.

The problem loader (``--truth``, a job spec's ``data.truth``: the scores in run.json, ``jobs
combine``'s, a batch item's) prepared the truth its own way: it could not read a (K, H, W)
stack of frames (a flipped video job failed: "6 channels"), took the 2x field at downsample 2
for the sensor's field at sensor resolution without a word, and refused a truth of the sensor's
field in a larger scene with "the scene field is 48x64". ``metrics`` did all of that right.
Expected numbers are built by hand (flip, block means), not by the code under test.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.clirun import run_cli as _run
from tests.udn.conftest import TINY_NET

H, W = 24, 32
BINS = 6


@pytest.fixture(autouse=True)
def _one_thread():
    import torch

    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def _video(folder: Path) -> np.ndarray:
    """A rolling-shutter video measurement of a moving scene; the truth as a (K, H, W) stack.

    Saved upside down (as the DiffuserCam data is stored): read with flip_rows, the problem
    is the simulated one; the truth a run is scored against is the stored one flipped.
    """
    import torch

    from recon.models import build_model
    from recon.simulate import synthetic_psf
    from tests.scenes import blocks_scene

    psf = synthetic_psf((H, W), seed=2)
    shutter = np.zeros((BINS, H), np.float32)
    for r in range(H):
        start = r * (BINS - 1) // H
        shutter[start:start + 2, r] = 1.0
    s = blocks_scene(H, W, seed=1).astype(np.float32)
    truth = np.stack([np.roll(s, (j, 2 * j), axis=(0, 1)) for j in range(BINS)])  # (K, H, W)
    b = build_model("video", psf, shutter=shutter).apply(torch.as_tensor(truth[None]))
    for name, arr in (("psf", psf), ("shutter", shutter), ("meas", b.numpy()[0]),
                      ("stack", truth)):
        np.save(folder / f"{name}.npy", np.ascontiguousarray(arr[..., ::-1, :]))
    return truth[None].astype(np.float64)  # (1, K, H, W), the right way up


def _spec(folder: Path, name: str = "job.toml", **data: object) -> Path:
    import tomli_w

    spec = {"job": {"name": "truth"},
            "data": {"model": "video", "psf": "psf.npy", "measurement": "meas.npy",
                     "shutter": "shutter.npy", "truth": "stack.npy", "flip_rows": True,
                     **data},
            "network": dict(TINY_NET),
            "stopping": {"max_iter": 12, "patience": 1000},
            "device": {"threads": 1},
            "output": {"checkpoint_every": 1000, "preview_every": 0, "status_seconds": 0.0}}
    spec["data"] = {k: v for k, v in spec["data"].items() if v is not None}
    p = folder / name
    p.write_text(tomli_w.dumps(spec), encoding="utf-8")
    return p


def _metrics(capsys, ref: Path, est: Path) -> dict:
    code, out, err = _run(capsys, "metrics", "--ref", ref, "--est", est, "--gain-fit")
    assert code == 0, err
    return json.loads(out)


def _psnr_vs(ref: np.ndarray, est: Path) -> float:
    from recon.io import read_reconstruction
    from recon.metrics import gain_fit, psnr

    x = read_reconstruction(est)[0].astype(np.float64)
    assert x.shape == ref.shape
    return psnr(ref, gain_fit(ref, x)[0])


def _blocks(a: np.ndarray, d: int) -> np.ndarray:
    """d x d block means of the last two axes (by hand)."""
    h, w = a.shape[-2] // d, a.shape[-1] // d
    return a[..., :h * d, :w * d].reshape(*a.shape[:-2], h, d, w, d).mean(axis=(-3, -1))


def test_a_flipped_video_job_with_a_stack_scores_as_metrics_does(tmp_path, capsys):
    """run.json's scores, ``jobs combine``'s and ``metrics`` on the written results: the same
    PSNR, against the truth flipped like the measurement (the job failed at its start)."""
    from recon.udn.ensemble import combine_runs
    from recon.udn.jobs import run_job

    truth = _video(tmp_path)
    spec = _spec(tmp_path)
    runs = [tmp_path / f"s{s}" for s in range(2)]
    for s, run in enumerate(runs):
        assert run_job(spec, run, seed=s).finish_reason == "completed"
    rec = json.loads((runs[0] / "run.json").read_text())
    assert rec["inputs"]["truth"]["shape"] == [1, BINS, H, W]
    for which in ("final", "best"):
        est = runs[0] / f"{which}.tif"
        scored = rec["results"]["scores"][which]["psnr"]
        report = _metrics(capsys, tmp_path / "stack.npy", est)
        assert report["ref_prepared"]["flip_rows"] is True
        assert scored == pytest.approx(report["psnr"], abs=1e-4)
        assert scored == pytest.approx(_psnr_vs(truth, est), abs=1e-4)
    ens = combine_runs(runs, tmp_path / "ens.tif")
    assert ens.scores is not None
    assert ens.scores["psnr"] == pytest.approx(
        _metrics(capsys, tmp_path / "stack.npy", tmp_path / "ens.tif")["psnr"], abs=1e-4)
    assert ens.scores["psnr"] == pytest.approx(_psnr_vs(truth, tmp_path / "ens.tif"), abs=1e-4)


def test_a_batch_items_score_of_a_flipped_video_is_metrics_score(tmp_path, capsys):
    """A batch scores a fista item's result with the loader's truth: as ``metrics`` does."""
    from app.batch.manifest import Item
    from app.batch.task import _metrics as batch_metrics

    truth = _video(tmp_path)
    argv = ("--model", "video", "--psf", str(tmp_path / "psf.npy"), "--shutter",
            str(tmp_path / "shutter.npy"), "--meas", str(tmp_path / "meas.npy"), "--flip-rows",
            "--downsample", "2", "--tau", "1e-4", "--iters", "40")
    out = tmp_path / "v.tif"
    code, _, err = _run(capsys, "recon", "fista", *argv, "--out", out)
    assert code == 0, err
    item = Item(id="v", method="fista", argv=argv, source="test", truth=str(tmp_path / "stack.npy"))
    scored = batch_metrics(item, out)["psnr"]
    assert scored == pytest.approx(_metrics(capsys, tmp_path / "stack.npy", out)["psnr"], abs=1e-4)
    assert scored == pytest.approx(_psnr_vs(_blocks(truth, 2), out), abs=1e-4)


def test_a_batch_scores_a_recon_auto_result_on_its_plans_grid(tmp_path, capsys):
    """A batch scored a ``recon auto`` item with the problem loader's truth, which knows
    nothing of the plan: a plan that downsampled or cut to a region was refused or compared
    other pixels. It scores as ``metrics`` does, from the result's metadata."""
    from app.batch.manifest import Item
    from app.batch.task import _metrics as batch_metrics

    _image(tmp_path)
    argv = ("--psf", str(tmp_path / "psf.npy"), "--meas", str(tmp_path / "meas.npy"),
            "--tau", "1e-3", "--set", "downsample=2", "--quiet")
    out = tmp_path / "auto.tif"
    code, _, err = _run(capsys, "recon", "auto", *argv, "--out", out)
    assert code == 0, err
    report = _metrics(capsys, tmp_path / "truth.npy", out)
    assert report["ref_prepared"]["plan"]["downsample"] == 2
    item = Item(id="a", method="auto", argv=argv, source="test", truth=str(tmp_path / "truth.npy"))
    assert batch_metrics(item, out)["psnr"] == pytest.approx(report["psnr"], abs=1e-4)


def _image(folder: Path) -> None:
    """A 2D measurement of a 24x32 sensor and its truth (the sensor's field), saved."""
    import torch

    from recon.models import build_model
    from recon.simulate import synthetic_psf
    from tests.scenes import blocks_scene

    psf = synthetic_psf((H, W), seed=2)
    truth = blocks_scene(H, W, seed=3).astype(np.float32)
    b = build_model("2d", psf).apply(torch.as_tensor(truth[None, None])).numpy()[0]
    for name, arr in (("psf", psf), ("meas", b), ("truth", truth)):
        np.save(folder / f"{name}.npy", arr)


def test_a_truth_of_the_sensors_field_in_a_larger_scene(tmp_path, capsys):
    """--field full: ``metrics`` scores the truth's window; the loader (whose scores compare
    whole arrays) refuses it saying why and where it is scored, in one line."""
    from recon.problem import ProblemSpec, load_problem

    _image(tmp_path)
    files = {k: str(tmp_path / f"{k}.npy") for k in ("psf", "meas", "truth")}
    code, _, err = _run(capsys, "recon", "fista", "--psf", files["psf"], "--meas",
                        files["meas"], "--field", "full", "--iters", "30", "--out",
                        tmp_path / "full.tif")
    assert code == 0, err
    report = _metrics(capsys, tmp_path / "truth.npy", tmp_path / "full.tif")
    assert report["ref_prepared"]["scored_window"] == [12, 36, 16, 48]
    with pytest.raises(ValueError) as exc:
        load_problem(ProblemSpec(meas=files["meas"], psf=files["psf"], truth=files["truth"],
                                 field="full"))
    line = str(exc.value)
    assert "\n" not in line and "covers 24x32" in line and "scene field 48x64" in line
    assert "lenslesscam metrics" in line
    # the same words from a job
    spec = _spec(tmp_path, "full.toml", model="2d", shutter=None, truth="truth.npy",
                 flip_rows=False, field="full")
    code, _, err = _run(capsys, "jobs", "run", spec, "--out", tmp_path / "run")
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "covers 24x32" in err and "lenslesscam metrics" in err


def test_the_2x_field_at_downsample_2_is_not_taken_for_the_sensors_field(tmp_path, capsys):
    """A 24x32 truth for a 24x32-sensor measurement at --field full --downsample 2 is the
    sensor's field at sensor resolution, or the 2x field on the grid: the loader took it for
    the latter without a word; now both refuse it alike, and a truth at an unambiguous size
    is prepared alike."""
    from recon.problem import ProblemSpec, load_problem

    _image(tmp_path)
    files = {k: str(tmp_path / f"{k}.npy") for k in ("psf", "meas", "truth")}
    spec = ProblemSpec(meas=files["meas"], psf=files["psf"], truth=files["truth"],
                       field="full", downsample=2)
    with pytest.raises(ValueError, match="cannot tell which"):
        load_problem(spec)
    code, _, err = _run(capsys, "recon", "fista", "--psf", files["psf"], "--meas",
                        files["meas"], "--field", "full", "--downsample", "2", "--iters", "5",
                        "--out", tmp_path / "f.tif")
    assert code == 0, err
    code, _, err = _run(capsys, "metrics", "--ref", files["truth"], "--est", tmp_path / "f.tif")
    assert code == 2 and "cannot tell which" in err
    # the 2x field at sensor resolution: the one size that means it
    scene = np.random.default_rng(0).random((2 * H, 2 * W)).astype(np.float32)
    np.save(tmp_path / "scene.npy", scene)
    prob = load_problem(spec.with_changes(truth=str(tmp_path / "scene.npy")))
    assert prob.truth is not None
    np.testing.assert_array_equal(prob.truth[0, 0],
                                  _blocks(scene.astype(np.float64), 2).astype(np.float32))
    report = _metrics(capsys, tmp_path / "scene.npy", tmp_path / "f.tif")
    assert "scored_window" not in report["ref_prepared"]
    assert report["psnr"] == pytest.approx(_psnr_vs(prob.truth.astype(np.float64),
                                                    tmp_path / "f.tif"), abs=1e-6)


def test_a_sensor_field_image_truth_is_prepared_as_before(tmp_path):
    """K = 1, the sensor's field, at sensor resolution: colour, channel order, row flip and
    block means in float32, bit for bit as the loader always prepared it."""
    from recon.preprocess import box_downsample
    from recon.problem import prepare_truth

    rgb = np.random.default_rng(1).random((H, W, 3)).astype(np.float32)
    np.save(tmp_path / "t.npy", rgb)
    t = prepare_truth(tmp_path / "t.npy", (3, 1, H // 2, W // 2), color="rgb",
                      channel_order="bgr", flip_rows=True, downsample=2)
    old = box_downsample(np.ascontiguousarray(
        np.moveaxis(rgb, -1, 0)[::-1, None, ::-1]), 2)
    assert t.dtype == np.float32 and old.dtype == np.float32
    np.testing.assert_array_equal(t, old)


def test_an_explicit_field_smaller_than_the_sensor_cuts_the_truth_alike(tmp_path, capsys):
    """--field 20x28 of a 24x32 sensor: the truth of the sensor's field is cut to the scene's
    centre by the loader (as ``jobs combine`` and a batch call it: the sensor's size from the
    measurement file) as by ``metrics`` (the loader refused it: "the scene field is 20x28");
    a field larger than the sensor's leaves a window the loader refuses."""
    from recon.io import read_reconstruction
    from recon.metrics import metrics_report
    from recon.problem import ProblemSpec, load_truth

    _image(tmp_path)
    files = {k: str(tmp_path / f"{k}.npy") for k in ("psf", "meas", "truth")}
    code, _, err = _run(capsys, "recon", "fista", "--psf", files["psf"], "--meas",
                        files["meas"], "--field", "20x28", "--iters", "30", "--out",
                        tmp_path / "cut.tif")
    assert code == 0, err
    x = read_reconstruction(tmp_path / "cut.tif")[0]
    spec = ProblemSpec(meas=files["meas"], psf=files["psf"], truth=files["truth"],
                       field=(20, 28))
    t = load_truth(spec, x.shape)
    # offset 20 // 2 - 24 // 2, 28 // 2 - 32 // 2 = (-2, -2): rows 2:22, columns 2:30
    np.testing.assert_array_equal(t[0, 0], np.load(files["truth"])[2:22, 2:30])
    report = _metrics(capsys, tmp_path / "truth.npy", tmp_path / "cut.tif")
    assert report["ref_prepared"]["field"]["offset"] == [-2, -2]
    assert "scored_window" not in report["ref_prepared"]
    assert metrics_report(t, x, gain_fit=True)["psnr"] == pytest.approx(report["psnr"], abs=1e-4)
    with pytest.raises(ValueError, match=r"covers 24x32 .* part of the scene field 30x40"):
        load_truth(spec.with_changes(field=(30, 40)), (1, 1, 30, 40))


def test_a_three_plane_truth_of_a_depth_result_is_a_stack_not_colour(tmp_path):
    """A recon auto depth result of 3 planes (the plan's planes: a stack of unknown size) read
    a (3, H, W) truth as RGB and refused it ('1 planes'); depth has no colour."""
    from recon.truth import _read

    planes = np.random.default_rng(0).random((3, 12, 16)).astype(np.float32)
    np.save(tmp_path / "t.npy", planes)
    layout = {"color": "gray", "channel_order": "rgb", "flip_rows": False, "downsample": 1}
    t = _read(tmp_path / "t.npy", (1, 3, 12, 16), layout, None, True, None, np.float32,
              gray_only=True)
    assert t.shape == (1, 3, 12, 16) and np.array_equal(t[0], planes)
    luma = _read(tmp_path / "t.npy", (1, 3, 12, 16), layout, None, True, None, np.float32)
    assert luma.shape[1] == 1  # without gray_only (a colour result) a 3-slice file is colour


def test_a_three_frame_truth_of_a_one_frame_gray_video_is_frames_not_colour(tmp_path):
    """A (3, H, W) truth against a gray video result of K = 1 was read as R, G, B, taken to
    luma and scored, silently; it is 3 frames, which one frame cannot be scored against. A
    colour image (H, W, 3) is still colour, taken to luma for the gray result."""
    from recon.truth import prepare_truth_like

    rng = np.random.default_rng(0)
    layout = {"color": "gray", "channel_order": "rgb", "flip_rows": False, "downsample": 1}
    np.save(tmp_path / "frames.npy", rng.random((3, 12, 16)).astype(np.float32))
    with pytest.raises(ValueError, match=r"has 3 frames; the video result is one image \(a "
                                         r"colour truth of a gray result: give it as an "
                                         r"\(H, W, 3\) image"):
        prepare_truth_like(tmp_path / "frames.npy", (1, 1, 12, 16), layout, kind="video")
    rgb = rng.random((12, 16, 3)).astype(np.float32)
    np.save(tmp_path / "rgb.npy", rgb)
    t, _ = prepare_truth_like(tmp_path / "rgb.npy", (1, 1, 12, 16), layout, kind="video")
    np.testing.assert_allclose(t[0, 0], rgb @ np.array([0.299, 0.587, 0.114]), rtol=1e-5)
    # three frames against a 3-frame result: a stack, as before
    t, _ = prepare_truth_like(tmp_path / "frames.npy", (1, 3, 12, 16), layout, kind="video")
    np.testing.assert_array_equal(t[0], np.load(tmp_path / "frames.npy"))
