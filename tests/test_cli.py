"""The lenslesscam CLI end to end: simulate -> recon -> metrics, demo, and bad inputs."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tifffile

from recon.io import read_reconstruction
from tests.clirun import run_cli as _run


def test_simulate_recon_metrics_round_trip(tmp_path, capsys):
    sim = tmp_path / "sim"
    code, out, _ = _run(capsys, "simulate", "--psf", "sample:tutorial", "--scene", "sample:im740",
                        "--erasure", "0.5", "--noise", "0.01", "--seed", "3", "--downsample", "2",
                        "--out", str(sim))
    assert code == 0
    info = json.loads(out)
    assert info["shape"] == [1, 75, 100] and info["erased"] == round(0.5 * 75 * 100)
    meta = json.loads((sim / "simulation.json").read_text())
    assert meta["format"] == "lenslesscam.simulation" and meta["format_version"] >= 1
    rec = tmp_path / "rec.tif"
    code, out, _ = _run(capsys, "recon", "fista", "--psf", str(sim / "psf.npy"), "--meas",
                        str(sim / "meas.npy"), "--mask", str(sim / "mask.npy"), "--tau", "1e-4",
                        "--iters", "150", "--out", str(rec))
    assert code == 0
    x, meta = read_reconstruction(rec)
    assert x.shape == (1, 1, 75, 100)
    assert meta["method"] == "fista-tv" and meta["parameters"]["tau"] == 1e-4
    assert meta["input_hashes"]["meas"] and (tmp_path / "rec.png").exists()
    code, out, _ = _run(capsys, "metrics", "--ref", str(sim / "truth.npy"), "--est", str(rec),
                        "--gain-fit")
    assert code == 0
    report = json.loads(out)
    assert report["gain_fit"] is True and report["psnr"] > 15


def test_demo_reconstructs_the_bundled_hand(tmp_path, capsys):
    code, _out, _ = _run(capsys, "demo", "--out", str(tmp_path), "--iters", "60")
    assert code == 0
    x, meta = read_reconstruction(tmp_path / "hand.tif")
    assert x.shape == (1, 1, 150, 200) and np.isfinite(x).all() and x.max() > 0
    assert meta["source"].startswith("DiffuserCam-Tutorial")


def test_video_and_depth_models_from_the_cli(tmp_path, capsys):
    from drivers.timing import SensorTiming
    from recon.models import build_model
    from recon.simulate import synthetic_psf

    psf = synthetic_psf((24, 20), seed=1)
    timing = SensorTiming(rows=24, line_time_us=1, exposure_lines=6, pattern="outside-in")
    shutter = timing.shutter(3)
    frames = np.random.default_rng(0).random((1, shutter.shape[0], 24, 20))
    meas = build_model("video", psf, shutter=shutter).apply(
        __import__("torch").as_tensor(frames, dtype=__import__("torch").float32)).numpy()
    np.save(tmp_path / "psf.npy", psf)
    np.save(tmp_path / "shutter.npy", shutter)
    np.save(tmp_path / "meas.npy", meas[0])
    code, _, err = _run(capsys, "recon", "fista", "--model", "video", "--psf",
                        str(tmp_path / "psf.npy"), "--shutter", str(tmp_path / "shutter.npy"),
                        "--meas", str(tmp_path / "meas.npy"), "--iters", "20",
                        "--out", str(tmp_path / "video.tif"))
    assert code == 0, err
    x, meta = read_reconstruction(tmp_path / "video.tif")
    assert x.shape == (1, shutter.shape[0], 24, 20) and meta["kind"] == "video"
    assert (tmp_path / "video.gif").exists()
    stack = np.stack([synthetic_psf((24, 20), seed=s) for s in range(3)])
    tifffile.imwrite(tmp_path / "stack.tif", stack, photometric="minisblack")
    code, _, err = _run(capsys, "recon", "fista", "--model", "depth", "--psf-stack",
                        str(tmp_path / "stack.tif"), "--meas", str(tmp_path / "meas.npy"),
                        "--iters", "20", "--out", str(tmp_path / "depth.tif"))
    assert code == 0, err
    x, meta = read_reconstruction(tmp_path / "depth.tif")
    assert x.shape == (1, 3, 24, 20) and (tmp_path / "depth_mip.png").exists()


@pytest.fixture
def good_pair(tmp_path):
    rng = np.random.default_rng(0)
    psf = rng.random((16, 12)).astype(np.float32)
    meas = rng.random((16, 12)).astype(np.float32)
    np.save(tmp_path / "psf.npy", psf)
    np.save(tmp_path / "meas.npy", meas)
    return tmp_path


@pytest.mark.parametrize(
    ("make", "flag", "expect"),
    [
        (lambda d: np.save(d / "bad.npy", np.zeros((16, 12), np.float32)), "--psf", "all zero"),
        (lambda d: np.save(d / "bad.npy", np.full((16, 12), np.nan, np.float32)), "--psf", "NaN"),
        (  # a non-constant PSF of the wrong size (a constant one also warns)
            lambda d: np.save(d / "bad.npy", np.arange(120, dtype=np.float32).reshape(10, 12)),
            "--psf",
            "10, 12",
        ),
        (lambda d: np.save(d / "bad.npy", np.ones((2, 3, 16, 12), np.float32)), "--meas", "shape"),
        (lambda d: np.save(d / "bad.npy", np.ones((16, 12), np.complex64)), "--meas", "complex"),
        (lambda d: (d / "bad.npy").write_bytes(b"\x93NUMPY garbage"), "--meas", "bad.npy"),
        (lambda d: (d / "bad.tif").write_bytes(b"II*\x00broken"), "--psf", "bad.tif"),
        (lambda d: None, "--meas", "missing.npy: no such file"),
    ],
    ids=["zero-psf", "nan-psf", "size-mismatch", "wrong-ndim", "wrong-dtype", "corrupt-npy",
         "corrupt-tif", "missing-file"],
)
def test_bad_inputs_exit_nonzero_with_a_clear_message(good_pair, capsys, make, flag, expect):
    d = good_pair
    make(d)
    bad = next((p for p in (d / "bad.npy", d / "bad.tif") if p.exists()), d / "missing.npy")
    args = {"--psf": str(d / "psf.npy"), "--meas": str(d / "meas.npy")}
    args[flag] = str(bad)
    code, _, err = _run(capsys, "recon", "fista", "--psf", args["--psf"], "--meas",
                        args["--meas"], "--iters", "5", "--out", str(d / "out.tif"))
    assert code != 0
    assert err.startswith("lenslesscam recon: error:")
    import re

    assert re.search(expect, err), err
    assert not (d / "out.tif").exists()


def test_wrong_shutter_shape_is_refused(good_pair, capsys):
    np.save(good_pair / "sh.npy", np.ones((4, 7)))
    code, _, err = _run(capsys, "recon", "fista", "--model", "video", "--psf",
                        str(good_pair / "psf.npy"), "--meas", str(good_pair / "meas.npy"),
                        "--shutter", str(good_pair / "sh.npy"), "--out", str(good_pair / "o.tif"))
    assert code != 0 and "shutter function must be (K, 16)" in err


def test_downsampled_masked_measurement_is_not_biased_by_erased_pixels(tmp_path, capsys):
    """--downsample with --mask: at 90 % erasures the coarse pixels still carry the data."""
    code, _, _ = _run(capsys, "simulate", "--psf", "sample:tutorial", "--scene", "sample:im65",
                      "--erasure", "0.9", "--noise", "0.01", "--out", str(tmp_path / "s"))
    assert code == 0
    s = tmp_path / "s"
    args = ["recon", "fista", "--psf", str(s / "psf.npy"), "--meas", str(s / "meas.npy"),
            "--mask", str(s / "mask.npy"), "--tau", "3e-5", "--iters", "100"]
    assert _run(capsys, *args, "--downsample", "2", "--out", str(tmp_path / "d2.tif"))[0] == 0
    x, _meta = read_reconstruction(tmp_path / "d2.tif")
    assert x.shape == (1, 1, 75, 100)
    truth = np.load(s / "truth.npy")[0, 0].reshape(75, 2, 100, 2).mean(axis=(1, 3))
    from recon.metrics import gain_fit, psnr

    assert psnr(truth[None, None], gain_fit(truth[None, None], x)[0]) > 15


@pytest.mark.parametrize("model", ["video", "spectral"])
def test_simulate_video_and_spectral_then_score(tmp_path, capsys, model):
    """simulate --model video|spectral uses the solvers' forward models; metrics scores the
    result per band, with the spectral cosine for spectral results."""
    from recon.simulate import synthetic_psf

    rng = np.random.default_rng(4)
    np.save(tmp_path / "psf.npy", synthetic_psf((16, 20), seed=3))
    k = 3
    np.save(tmp_path / "scene.npy", rng.random((k, 16, 20)).astype(np.float32))
    if model == "video":
        m = np.zeros((k, 16))
        for i in range(k):
            m[i, max(0, 5 * i - 2): 5 * i + 8] = 1.0
        np.save(tmp_path / "aux.npy", m)
        flag = "--shutter"
    else:
        np.save(tmp_path / "aux.npy", rng.random((k, 16, 20)).astype(np.float32))
        flag = "--filters"
    sim = tmp_path / "sim"
    code, out, err = _run(capsys, "simulate", "--model", model, "--psf", str(tmp_path / "psf.npy"),
                          "--scene", str(tmp_path / "scene.npy"), flag, str(tmp_path / "aux.npy"),
                          "--noise", "0.001", "--out", str(sim))
    assert code == 0, err
    assert json.loads(out)["k"] == k
    meta = json.loads((sim / "simulation.json").read_text())
    assert meta["model"] == model and meta["params"]["model"] == model
    assert np.load(sim / "truth.npy").shape == (1, k, 16, 20)
    # the measurement is the forward model of the truth (noise 0.001 on a max-1 measurement)
    from recon.models import build_model

    aux = {"shutter" if model == "video" else "filters": np.load(sim / f"{flag[2:]}.npy")}
    fm = build_model(model, np.load(sim / "psf.npy"), **aux)
    import torch

    clean = fm.apply(torch.as_tensor(np.load(sim / "truth.npy"))).numpy() * meta["scale"]
    assert np.abs(clean - np.load(sim / "meas.npy")).max() < 0.01  # 10 sigma of the noise
    rec = tmp_path / "rec.tif"
    code, _, err = _run(capsys, "recon", "fista", "--model", model, "--psf", str(sim / "psf.npy"),
                        flag, str(sim / f"{flag[2:]}.npy"), "--meas", str(sim / "meas.npy"),
                        "--tau", "1e-4", "--iters", "30", "--out", str(rec))
    assert code == 0, err
    code, out, err = _run(capsys, "metrics", "--ref", str(sim / "truth.npy"), "--est", str(rec),
                          "--gain-fit")
    assert code == 0, err
    report = json.loads(out)
    assert report["shape"] == [1, k, 16, 20]
    if model == "spectral":
        assert 0 <= report["spectral_cosine_distance"] < 1
        assert 0 <= report["spectral_angle_deg"] < 90
    else:
        assert "spectral_cosine_distance" not in report


def test_readme_command_list_matches_the_parser():
    """The README's command block names every benchmark, and calibrate filters as it is."""
    import re
    from pathlib import Path

    from app.commands.bench import BENCHMARKS

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    line = re.search(r"^lenslesscam bench (\S+)", readme, re.M)
    assert line, "README lists no 'lenslesscam bench' line"
    assert set(line.group(1).split("|")) == set(BENCHMARKS)
    filters = re.search(r"^lenslesscam calibrate filters (.*)$", readme, re.M)
    assert filters and "--camera" not in filters.group(1) and "--source" not in filters.group(1)
    assert "--cube" in filters.group(1)


def test_metrics_reads_the_truth_like_the_reconstructions_measurement(tmp_path, capsys):
    """A pair in the dataset layout (BGR, upside-down, truth at sensor resolution): metrics
    prepares the truth as the reconstruction's metadata says its measurement was read (colour,
    channel order, row flip, downsample), so the score is the one recon.problem's truth gives,
    and says so; a flipped or channel-swapped truth would score far lower."""
    import numpy as np

    from recon.io import read_reconstruction
    from recon.metrics import gain_fit, psnr
    from recon.problem import ProblemSpec, load_problem
    from tests.scenes import dataset_layout_pair

    dataset_layout_pair(tmp_path)
    files = {k: str(tmp_path / f"{k}.npy") for k in ("psf", "meas", "truth")}
    rec = tmp_path / "rec.tif"
    layout = ["--rgb", "--channel-order", "bgr", "--flip-rows", "--downsample", "2"]
    code, _, err = _run(capsys, "recon", "fista", "--psf", files["psf"], "--meas", files["meas"],
                        *layout, "--out", str(rec))
    assert code == 0, err
    code, out, err = _run(capsys, "metrics", "--ref", files["truth"], "--est", str(rec),
                          "--gain-fit")
    assert code == 0, err
    report = json.loads(out)
    assert report["ref_prepared"] == {"color": "rgb", "channel_order": "bgr", "flip_rows": True,
                                      "downsample": 2}
    truth = load_problem(ProblemSpec(meas=files["meas"], psf=files["psf"], truth=files["truth"],
                                     color="rgb", channel_order="bgr", flip_rows=True,
                                     downsample=2)).truth
    x = read_reconstruction(rec)[0]
    assert report["psnr"] == pytest.approx(psnr(truth, gain_fit(truth, x)[0]), abs=1e-3)
    wrong = np.ascontiguousarray(truth[::-1, :, ::-1])  # channels swapped, upside-down
    assert report["psnr"] > psnr(wrong, gain_fit(wrong, x)[0]) + 3
    # as stored, the truth is at sensor resolution: refused on the shapes, never scored wrong
    code, _, err = _run(capsys, "metrics", "--ref", files["truth"], "--est", str(rec),
                        "--gain-fit", "--ref-as-is")
    assert code == 2 and "shapes differ" in err
    # a UDN job's results say how its inputs were read too: metrics agrees with the job's score
    run = tmp_path / "udn"
    code, _, err = _run(capsys, "recon", "udn", "--psf", files["psf"], "--meas", files["meas"],
                        "--truth", files["truth"], *layout, "--iters", "4", "--scales", "2",
                        "--net-channels", "4", "--input-channels", "4", "--threads", "1",
                        "--quiet", "--out", str(run))
    assert code == 0, err
    code, out, err = _run(capsys, "metrics", "--ref", files["truth"], "--est",
                          str(run / "final.tif"), "--gain-fit")
    assert code == 0, err
    report = json.loads(out)
    assert report["ref_prepared"]["flip_rows"] is True
    job = json.loads((run / "run.json").read_text())["results"]["scores"]["final"]
    assert report["psnr"] == pytest.approx(job["psnr"], abs=1e-3)
    # --key picks the truth's variable in an NPZ on the prepared path too
    stored = np.load(files["truth"])
    np.savez(tmp_path / "two.npz", scene=np.random.default_rng(0).random(stored.shape),
             gt=stored)
    code, out, err = _run(capsys, "metrics", "--ref", str(tmp_path / "two.npz"), "--key", "gt",
                          "--est", str(rec), "--gain-fit")
    assert code == 0, err
    assert json.loads(out)["psnr"] == pytest.approx(psnr(truth, gain_fit(truth, x)[0]), abs=1e-3)


def test_metrics_scores_a_recon_auto_result_on_its_plans_grid_and_region(tmp_path, capsys):
    """recon auto downsamples the loaded problem again and may cut a region of the field:
    metrics reads the truth the same way (it refused both: 'the scene field is 24x32')."""
    import numpy as np

    from recon.io import read_reconstruction
    from recon.metrics import gain_fit, psnr
    from recon.problem import ProblemSpec, load_problem
    from tests.scenes import dataset_layout_pair

    dataset_layout_pair(tmp_path, shape=(48, 64))
    files = {k: str(tmp_path / f"{k}.npy") for k in ("psf", "meas", "truth")}
    layout = ["--rgb", "--channel-order", "bgr", "--flip-rows"]
    truth2 = load_problem(ProblemSpec(meas=files["meas"], psf=files["psf"], truth=files["truth"],
                                      color="rgb", channel_order="bgr", flip_rows=True,
                                      downsample=2)).truth
    for name, region, crop in (("whole", [], np.s_[..., :, :]),
                               ("cut", ["--set", "region=[6,10,30,40]"],
                                np.s_[..., 3:18, 5:25])):
        rec = tmp_path / f"{name}.tif"
        code, _, err = _run(capsys, "recon", "auto", "--psf", files["psf"], "--meas",
                            files["meas"], *layout, "--set", "downsample=2", *region,
                            "--out", str(rec))
        assert code == 0, err
        code, out, err = _run(capsys, "metrics", "--ref", files["truth"], "--est", str(rec),
                              "--gain-fit")
        assert code == 0, err
        report = json.loads(out)
        assert report["ref_prepared"]["plan"]["downsample"] == 2
        x = read_reconstruction(rec)[0]
        ref = truth2[crop]
        assert ref.shape == x.shape
        assert report["psnr"] == pytest.approx(psnr(ref, gain_fit(ref, x)[0]), abs=1e-3)
        shifted = np.roll(truth2, (3, 4), axis=(-2, -1))[crop]  # the wrong place scores lower
        assert report["psnr"] > psnr(shifted, gain_fit(shifted, x)[0]) + 1


def test_metrics_scores_a_video_against_a_stack_of_frames(tmp_path, capsys):
    """A (K, H, W) truth stack for a K-frame result is read as stored (the prepared path is for
    images; it took the frames for colour channels)."""
    from recon.io import save_reconstruction

    rng = np.random.default_rng(0)
    truth = rng.random((6, 24, 20)).astype(np.float32)
    np.save(tmp_path / "t.npy", truth)
    est = truth * 2 + 0.01 * rng.random(truth.shape).astype(np.float32)
    save_reconstruction(tmp_path / "v.tif", est[None], {
        "preprocessing": {"color": "gray", "channel_order": "rgb", "flip_rows": False,
                          "downsample": 1}}, kind="video")
    code, out, err = _run(capsys, "metrics", "--ref", str(tmp_path / "t.npy"), "--est",
                          str(tmp_path / "v.tif"), "--gain-fit")
    assert code == 0, err
    report = json.loads(out)
    assert report["psnr"] > 40 and report["ref_prepared"] == {
        "color": "gray", "channel_order": "rgb", "flip_rows": False, "downsample": 1}


def test_simulate_reads_its_own_truth_and_refuses_scenes_that_are_not_light(tmp_path, capsys):
    """simulate's truth.npy (1, K, H, W) is a scene for another simulate; a negative or
    all-zero scene is refused (they gave a negative or all-zero measurement silently)."""
    first = tmp_path / "a"
    code, _, err = _run(capsys, "simulate", "--psf", "sample:tutorial", "--scene",
                        "sample:im65", "--downsample", "8", "--out", str(first))
    assert code == 0, err
    again = tmp_path / "b"
    code, _, err = _run(capsys, "simulate", "--psf", "sample:tutorial", "--scene",
                        str(first / "truth.npy"), "--downsample", "8", "--out", str(again))
    assert code == 0, err
    t0, t1 = np.load(first / "truth.npy"), np.load(again / "truth.npy")
    assert t0.shape == t1.shape and np.corrcoef(t0.ravel(), t1.ravel())[0, 1] > 0.999
    for name, arr, why in (("neg.npy", -np.ones((10, 12)), "negative values"),
                           ("zero.npy", np.zeros((10, 12)), "all zero")):
        np.save(tmp_path / name, arr)
        code, _, err = _run(capsys, "simulate", "--psf", "sample:tutorial", "--scene",
                            str(tmp_path / name), "--downsample", "8", "--out",
                            str(tmp_path / name[:-4]))
        assert code == 2 and why in err
        assert not (tmp_path / name[:-4]).exists()


def test_the_tau_search_is_reported_beside_the_reconstructions_time(tmp_path, capsys):
    """wall_time_s is the reconstruction alone (recon fista and demo alike: demo's included
    the search); the automatic tau's search is tau_search_s, None when tau was given."""
    import numpy as np

    from recon.simulate import synthetic_psf

    np.save(tmp_path / "psf.npy", synthetic_psf((24, 32), seed=2))
    np.save(tmp_path / "meas.npy", np.random.default_rng(0).random((24, 32)).astype(np.float32))
    base = ["recon", "fista", "--psf", str(tmp_path / "psf.npy"), "--meas",
            str(tmp_path / "meas.npy")]
    code, out, err = _run(capsys, *base, "--out", str(tmp_path / "a.tif"))
    assert code == 0, err
    auto = json.loads(out.splitlines()[-1])
    assert auto["tau_search_s"] > 0 and auto["wall_time_s"] >= 0
    code, out, err = _run(capsys, *base, "--tau", "1e-3", "--iters", "20",
                          "--out", str(tmp_path / "b.tif"))
    assert code == 0, err
    assert json.loads(out.splitlines()[-1])["tau_search_s"] is None
    code, out, err = _run(capsys, "demo", "--out", str(tmp_path / "demo"))
    assert code == 0, err
    demo = json.loads(out.splitlines()[-1])
    assert demo["tau_search_s"] > 0 and demo["tau_rule"] != "given"


def test_demo_runs_the_result_check_of_every_command(tmp_path, capsys):
    """recon fista/admm/auto checked their result against a flat image; demo did not."""
    code, _, err = _run(capsys, "demo", "--iters", "1", "--tau", "1e-4", "--out",
                        str(tmp_path / "d"))
    assert code == 0, err
    assert ("lenslesscam demo: warning: fista-tv: the result explains the measurement less "
            "well than a flat image") in err and "it needs more --iters" in err


def test_recon_udn_compile_takes_an_optional_mode():
    """--compile alone: torch.compile's default mode; --compile reduce-overhead: CUDA graphs
    (half the iteration time on a GPU); no --compile: eager. Into the spec the job runs."""
    from app.cli import build_parser
    from app.commands.recon_udn import build_spec

    parser = build_parser()
    base = ["recon", "udn", "--psf", "p.npy", "--meas", "m.npy"]
    for extra, compiled, mode in (([], False, "default"), (["--compile"], True, "default"),
                                  (["--compile", "reduce-overhead"], True, "reduce-overhead")):
        dev = build_spec(parser.parse_args([*base, *extra]))["device"]
        assert (dev["compile"], dev["compile_mode"]) == (compiled, mode), extra
    with pytest.raises(SystemExit):
        parser.parse_args([*base, "--compile", "fast"])
