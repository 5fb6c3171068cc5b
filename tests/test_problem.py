"""One problem loader (recon.problem): every command loads, downsamples and checks inputs alike.

- plan, recon auto, recon udn and recon fista succeed on `simulate` output with masks at 50, 90
  and 99 % erasures and downsampling 2, 4, 6, and all use the SAME coarse mask (the "any
  sensor pixel measured" rule, checked against an independent computation);
- recon udn and jobs run read the shutter file that `calibrate shutter` writes;
- the DiffuserCam MirFlickr layout (BGR, PSF on the padded grid) loads through the CLI with
  --rgb, and a FISTA reconstruction correlates with its truth while a row-flipped truth does
  not;
- bad inputs give one-line errors naming the file at fault.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from app.cli import main
from recon.formats import array_hash
from recon.io import read_reconstruction
from recon.problem import ProblemSpec, load_problem
from recon.samples import shared_data_dir

_SHARED = shared_data_dir()
DLMD = (_SHARED / "dlmd") if _SHARED is not None else Path("/nonexistent/dlmd")


def _run(capsys, *argv):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    assert code == 0, out.err
    return out.out


def _any_rule(mask, ds):
    """Independent spelling of the mask rule: measured when any sensor pixel under it is."""
    h, w = mask.shape[0] // ds, mask.shape[1] // ds
    return mask[: h * ds, : w * ds].reshape(h, ds, w, ds).astype(bool).any(axis=(1, 3))


@pytest.fixture(scope="module")
def sims(tmp_path_factory):
    """`lenslesscam simulate` output (50x66) at 50, 90 and 99 % erasures."""
    root = tmp_path_factory.mktemp("sims")
    out = {}
    for er in (0.5, 0.9, 0.99):
        d = root / f"e{er}"
        assert main(["simulate", "--psf", "sample:tutorial", "--scene", "sample:im408",
                     "--erasure", str(er), "--noise", "0.01", "--downsample", "3",
                     "--out", str(d)]) == 0
        out[er] = d
    return out


@pytest.mark.parametrize("erasure", [0.5, 0.9, 0.99])
# 50x66 at 4x and 6x drops a remainder, which each command says (a warning, not an error)
@pytest.mark.filterwarnings("default::recon.checks.MeasurementWarning")
def test_every_command_uses_the_same_coarse_mask(sims, erasure, tmp_path, capsys):
    sim = sims[erasure]
    files = ["--psf", sim / "psf.npy", "--meas", sim / "meas.npy", "--mask", sim / "mask.npy"]
    mask = np.load(sim / "mask.npy")
    for ds in (2, 4, 6):
        expected = _any_rule(mask, ds)
        assert expected.any()
        want = array_hash(expected.astype(np.float32))
        # recon fista
        fista = tmp_path / f"f{ds}.tif"
        _run(capsys, "recon", "fista", *files, "--downsample", ds, "--tau", "1e-3",
             "--iters", "5", "--out", fista)
        x, meta = read_reconstruction(fista)
        assert x.shape[-2:] == expected.shape
        assert meta["preprocessing"]["mask_hash"] == want
        # plan, then recon auto running that plan at this downsampling
        plan = tmp_path / f"p{ds}.json"
        _run(capsys, "plan", *files, "--no-probe", "--set", f"downsample={ds}",
             "--set", "iterations=5", "--out", plan)
        auto = tmp_path / f"a{ds}.tif"
        _run(capsys, "recon", "auto", *files, "--plan", plan, "--quiet", "--out", auto)
        xa, meta_a = read_reconstruction(auto)
        assert xa.shape[-2:] == expected.shape and meta_a["mask_hash"] == want
        # recon udn (a few iterations of a tiny network)
        run = tmp_path / f"u{ds}"
        _run(capsys, "recon", "udn", *files, "--downsample", ds, "--iters", "2", "--scales",
             "2", "--net-channels", "4", "--skip-channels", "2", "--input-channels", "4",
             "--device", "cpu", "--quiet", "--out", run)
        rec = json.loads((run / "run.json").read_text())
        assert rec["inputs"]["mask"]["array_hash"] == want
    # the rule the planner and the UDN jobs used before lost every pixel here
    if erasure == 0.5:
        h, w = mask.shape[0] // 6, mask.shape[1] // 6
        all_rule = mask[: h * 6, : w * 6].reshape(h, 6, w, 6).all(axis=(1, 3))
        assert not all_rule.any()


def _video_case(tmp_path, capsys):
    """A video measurement for the sensor of `calibrate shutter --camera sim` (32x40)."""
    import torch

    from recon.models import build_model

    sh = tmp_path / "shutter.npz"
    _run(capsys, "calibrate", "shutter", "--camera", "sim", "--sim-size", "32x40",
         "--bin-lines", "8", "--out", sh)
    z = np.load(sh)
    assert "metadata" in z.files and z["shutter"].shape[1] == 32
    m = np.asarray(z["shutter"], dtype=np.float64)
    rng = np.random.default_rng(0)
    psf = rng.random((32, 40)).astype(np.float32) ** 8
    psf /= psf.sum()
    model = build_model("video", psf, shutter=m)
    scene = torch.as_tensor(rng.random(model.scene_shape), dtype=torch.float32)
    meas = model.apply(scene).numpy()
    np.save(tmp_path / "psf.npy", psf)
    np.save(tmp_path / "meas.npy", meas)
    return sh, m


def test_udn_and_jobs_read_the_calibrated_shutter_file(tmp_path, capsys):
    sh, m = _video_case(tmp_path, capsys)
    files = ["--model", "video", "--psf", tmp_path / "psf.npy", "--meas",
             tmp_path / "meas.npy", "--shutter", sh]
    net = ["--iters", "2", "--scales", "2", "--net-channels", "4", "--skip-channels", "2",
           "--input-channels", "4", "--device", "cpu", "--quiet"]
    # recon udn at full resolution and at downsample 2 (the shutter's rows are averaged)
    _run(capsys, "recon", "udn", *files, *net, "--out", tmp_path / "u1")
    rec = json.loads((tmp_path / "u1" / "run.json").read_text())
    assert rec["inputs"]["shutter"]["shape"] == [m.shape[0], 32]
    _run(capsys, "recon", "udn", *files, "--downsample", "2", *net,
         "--write-spec", tmp_path / "job.toml")
    text = (tmp_path / "job.toml").read_text()
    assert "shutter.npz" in text and "downsample = 2" in text
    _run(capsys, "jobs", "run", tmp_path / "job.toml", "--out", tmp_path / "j2", "--quiet")
    rec = json.loads((tmp_path / "j2" / "run.json").read_text())
    assert rec["finish_reason"] == "completed"
    assert rec["inputs"]["shutter"]["shape"] == [m.shape[0], 16]
    expected = m.reshape(m.shape[0], 16, 2).mean(axis=2)
    assert rec["inputs"]["shutter"]["array_hash"] == array_hash(expected)
    # recon fista reads it the same way
    _run(capsys, "recon", "fista", *files, "--downsample", "2", "--tau", "1e-3", "--iters",
         "3", "--out", tmp_path / "f.tif")


def _corr(a, b):
    a = np.asarray(a, np.float64).ravel()
    b = np.asarray(b, np.float64).ravel()
    a, b = a - a.mean(), b - b.mean()
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


def _dlmd_truth(ds):
    """The lensed truth of im408, read independently: BGR (H, W, 3) -> RGB (3, H/ds, W/ds)."""
    t = np.load(DLMD / "lensed_im408.npy")[:, :, ::-1].transpose(2, 0, 1).astype(np.float64)
    h, w = t.shape[1] // ds, t.shape[2] // ds
    return t[:, : h * ds, : w * ds].reshape(3, h, ds, w, ds).mean(axis=(2, 4))


@pytest.mark.skipif(not DLMD.is_dir(), reason="needs ../shared/data/dlmd (real pairs)")
def test_dlmd_pair_loads_through_the_cli_and_reconstructs_its_truth(tmp_path, capsys):
    files = ["--psf", DLMD / "psf_estimated_padded_bgr.npy", "--meas",
             DLMD / "diffuser_im408.npy", "--rgb", "--channel-order", "bgr", "--downsample", "4",
             "--tau", "1e-3", "--iters", "100"]
    _run(capsys, "recon", "fista", *files, "--out", tmp_path / "r.tif")
    x, meta = read_reconstruction(tmp_path / "r.tif")
    assert x.shape == (3, 1, 67, 120)
    assert meta["preprocessing"]["psf_grid"] == "padded"
    truth = _dlmd_truth(4)
    c_ok = _corr(x[:, 0], truth)
    c_flipped = _corr(x[:, 0], truth[:, ::-1])
    assert c_ok > 0.6, c_ok
    assert c_flipped < 0.45, c_flipped
    assert c_ok - c_flipped > 0.3
    # channel order: with the files' BGR order taken as RGB, red and blue trade places
    per_channel = [_corr(x[i, 0], truth[i]) for i in range(3)]
    assert min(per_channel) > 0.5, per_channel
    # --flip-rows flips PSF, measurement (and truth) alike: the result is the same, upside down
    _run(capsys, "recon", "fista", *files, "--flip-rows", "--out", tmp_path / "rf.tif")
    xf, _ = read_reconstruction(tmp_path / "rf.tif")
    assert _corr(xf[:, 0], truth[:, ::-1]) > 0.6
    assert _corr(xf[:, 0], truth) < 0.45


@pytest.mark.skipif(not DLMD.is_dir(), reason="needs ../shared/data/dlmd (real pairs)")
def test_dlmd_truth_is_prepared_like_the_measurement():
    spec = ProblemSpec(meas=str(DLMD / "diffuser_im408.npy"),
                       psf=str(DLMD / "psf_estimated_270x480_gray.npy"),
                       truth=str(DLMD / "lensed_im408.npy"), downsample=6, color="rgb",
                       channel_order="bgr")
    shared = load_problem(spec)  # the gray PSF serves the three colour channels
    assert shared.psf.shape == (1, 45, 80) and shared.meas.shape == (3, 45, 80)
    assert shared.truth is not None and shared.truth.shape == (3, 1, 45, 80)
    prob = load_problem(spec.with_changes(color="gray"))
    assert prob.metadata["psf_grid"] == "sensor" and prob.meas.shape == (1, 45, 80)
    assert prob.truth is not None and prob.truth.shape == (1, 1, 45, 80)
    luma = np.tensordot([0.299, 0.587, 0.114], _dlmd_truth(6), axes=(0, 0))
    assert np.allclose(prob.truth[0, 0], luma, atol=1e-5)


# -- the loader's rules and errors ----------------------------------------------------------


@pytest.fixture
def small(tmp_path):
    rng = np.random.default_rng(1)
    psf = rng.random((24, 30)).astype(np.float32) ** 6
    meas = rng.random((24, 30)).astype(np.float32)
    mask = (rng.random((24, 30)) > 0.7).astype(np.float32)
    for name, a in (("psf", psf), ("meas", meas), ("mask", mask)):
        np.save(tmp_path / f"{name}.npy", a)
    return tmp_path


def _spec(d, **kw):
    base = {"meas": str(d / "meas.npy"), "psf": str(d / "psf.npy")}
    base.update(kw)
    return ProblemSpec(**base)


def test_mask_rule_keeps_every_measured_pixel_and_averages_only_them(small):
    mask = np.load(small / "mask.npy")
    meas = np.load(small / "meas.npy")
    prob = load_problem(_spec(small, mask=str(small / "mask.npy"), downsample=3,
                              meas_normalise="none"))
    assert np.array_equal(prob.mask > 0, _any_rule(mask, 3))
    blocks_m = mask.reshape(8, 3, 10, 3)
    blocks_b = (meas * mask).reshape(8, 3, 10, 3)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = blocks_b.sum(axis=(1, 3)) / blocks_m.sum(axis=(1, 3))
    sel = prob.mask > 0
    assert np.allclose(prob.meas[0][sel], mean[sel], rtol=1e-5)


@pytest.mark.parametrize(("content", "message"), [
    (np.zeros((24, 30), np.float32), "marks no pixel as measured"),
    (np.full((24, 30), np.nan, np.float32), "NaN"),
    (np.full((24, 30), 0.5, np.float32), "values other than 0 and 1"),
    (np.ones((20, 30), np.float32), "the measurement is 24x30"),
])
def test_bad_masks_are_refused_naming_the_mask(small, content, message):
    np.save(small / "bad_mask.npy", content)
    with pytest.raises(ValueError, match=message) as info:
        load_problem(_spec(small, mask=str(small / "bad_mask.npy"), downsample=2))
    assert "bad_mask.npy" in str(info.value) and "PSF" not in str(info.value)
    assert "\n" not in str(info.value)


def test_psf_of_the_wrong_size_names_the_psf(small):
    np.save(small / "psf_small.npy", np.arange(100, dtype=np.float32).reshape(10, 10))
    with pytest.raises(ValueError, match=r"PSF file .*psf_small\.npy has shape \(1, 10, 10\)"):
        load_problem(_spec(small, psf=str(small / "psf_small.npy")))


def test_a_padded_psf_is_exact_for_the_sensor_field(small):
    """A 2x PSF: the sensor sits in the middle of the padded grid, the rest is masked out."""
    import torch

    from recon.models import build_model

    rng = np.random.default_rng(2)
    big = rng.random((48, 60)).astype(np.float32) ** 6
    np.save(small / "psf_padded.npy", big)
    scene = rng.random((1, 1, 24, 30)).astype(np.float32)
    # reference: the scene on the full padded field, crop of the virtual 48x60 sensor
    ref = build_model("2d", big, field=(24, 30)).apply(torch.as_tensor(scene)).numpy()
    np.save(small / "meas_p.npy", ref[0, 12:36, 15:45])
    prob = load_problem(_spec(small, psf=str(small / "psf_padded.npy"),
                              meas=str(small / "meas_p.npy"), meas_normalise="none",
                              psf_normalise="none"))
    assert prob.metadata["psf_grid"] == "padded" and prob.sensor == (24, 30)
    assert prob.model.scene_shape == (1, 1, 24, 30)
    pred = prob.model.apply(torch.as_tensor(scene)).numpy()
    assert np.allclose(pred[0, 12:36, 15:45], ref[0, 12:36, 15:45], rtol=1e-4, atol=1e-6)
    assert np.allclose(pred * prob.mask, prob.meas, rtol=1e-4, atol=1e-6)


def test_job_data_section_round_trips():
    spec = ProblemSpec(meas="/m.npy", psf="/p.npy", mask="/k.npy", downsample=3, field=(10, 12),
                       color="rgb", channel_order="bgr", flip_rows=True, dark="auto")
    assert ProblemSpec.from_data_section(spec.to_data_section()) == spec
    with pytest.raises(ValueError, match="shutter"):
        ProblemSpec(meas="/m.npy", psf="/p.npy", model="video")


def test_the_pixel_maps_file_of_calibrate_darks_is_a_mask(small, capsys):
    pm = small / "pixel_maps.npz"
    _run(capsys, "calibrate", "darks", "--camera", "sim", "--sim-size", "24x30", "--frames", "2",
         "--no-prompt", "--out", pm)
    prob = load_problem(_spec(small, mask=str(pm), downsample=2))
    assert prob.mask is not None and prob.mask.shape == (12, 15) and prob.mask.all()
    assert prob.inputs["mask"]["file_hash"]


def test_a_gray_psf_with_a_colour_measurement_is_shared_by_the_channels(tmp_path):
    """The MirFlickr dataset's original code keeps one gray PSF for colour data: with --rgb a
    gray PSF file serves R, G and B (said in the metadata), a colour file one per channel."""
    from tests.scenes import dataset_layout_pair

    dataset_layout_pair(tmp_path)
    np.save(tmp_path / "psf_gray.npy", np.load(tmp_path / "psf.npy").sum(axis=2))
    kw = dict(meas=str(tmp_path / "meas.npy"), truth=str(tmp_path / "truth.npy"), color="rgb",
              channel_order="bgr", flip_rows=True)
    gray = load_problem(ProblemSpec(psf=str(tmp_path / "psf_gray.npy"), **kw))
    colour = load_problem(ProblemSpec(psf=str(tmp_path / "psf.npy"), **kw))
    assert gray.psf.shape[0] == 1 and colour.psf.shape[0] == 3
    assert gray.metadata["psf_channels"] == "one gray PSF shared by R, G and B"
    assert "psf_channels" not in colour.metadata
    assert gray.model.scene_shape == colour.model.scene_shape == (3, 1, 24, 32)
    # the shared PSF predicts the colour measurement up to the per-channel gains it lacks
    import torch

    pred = gray.model.apply(torch.as_tensor(gray.truth)).numpy() * gray.mask
    for ch in range(3):
        r = np.corrcoef(pred[ch].ravel(), gray.meas[ch].ravel())[0, 1]
        assert r > 0.99, (ch, r)


def test_a_measurement_dark_that_empties_the_psf_names_psf_dark(tmp_path):
    """--dark applies to the PSF too unless --psf-dark is given: when that empties a PSF (a
    float PSF under a count-level dark), the error says so and names the option."""
    rng = np.random.default_rng(0)
    np.save(tmp_path / "psf.npy", (rng.random((16, 20)) ** 4).astype(np.float32))  # max < 1
    np.save(tmp_path / "meas.npy", (200 + 100 * rng.random((16, 20))).astype(np.float32))
    for stack in (False, True):
        kw = (dict(model="depth", psf_stack=(str(tmp_path / "psf.npy"),) * 2) if stack
              else dict(psf=str(tmp_path / "psf.npy")))
        spec = ProblemSpec(meas=str(tmp_path / "meas.npy"), dark=100.0, **kw)
        with pytest.raises(ValueError, match=r"is all zero or negative after dark subtraction "
                           r"\(dark=100\.0\): the measurement's dark \(100\.0\) is subtracted "
                           r"from the PSF too unless a PSF dark is given \(--psf-dark"):
            load_problem(spec)
        assert load_problem(spec.with_changes(psf_dark=0.0)).psf.max() > 0


def test_a_calibrated_psf_file_does_not_take_the_measurement_dark(tmp_path):
    """A calibrated PSF is dark-subtracted: --dark used to take the measurement's level off it
    a second time (the calibration recipe's simulated PSF lost 25 % of its energy, and the
    reconstruction's correlation with the scene fell from 0.994 to 0.985)."""
    import tifffile

    from recon.calibfile import calibration_kind, save_psf_calibration, save_psf_stack

    rng = np.random.default_rng(0)
    psf = (400 * rng.random((16, 20)) ** 4).astype(np.float32)  # ADU above the dark level
    meta = {"camera": {"backend": "sim"}, "exposure_us": 100.0, "gain": 1.0,
            "frames_averaged": 4, "dark_level": 100.0, "timing": None, "quality": {}}
    save_psf_calibration(tmp_path / "psf.tif", psf, meta)
    save_psf_stack(tmp_path / "stack.tif", np.stack([psf, psf[::-1]]),
                   {"camera": {}, "positions": ["a", "b"], "planes": [{}, {}], "timing": None})
    tifffile.imwrite(tmp_path / "plain.tif", psf)  # the same pixels, no calibration metadata
    np.save(tmp_path / "meas.npy", (200 + 100 * rng.random((16, 20))).astype(np.float32))
    assert calibration_kind(tmp_path / "psf.tif") == "psf"
    assert calibration_kind(tmp_path / "stack.tif") == "psf-stack"
    assert calibration_kind(tmp_path / "plain.tif") is None
    assert calibration_kind(tmp_path / "meas.npy") is None

    def load(psf_file, **kw):
        key = "psf_stack" if "stack" in psf_file else "psf"
        model = "depth" if key == "psf_stack" else "2d"
        return load_problem(ProblemSpec(meas=str(tmp_path / "meas.npy"), model=model,
                                        dark=100.0, psf_normalise="none",
                                        **{key: str(tmp_path / psf_file)}, **kw))

    prob = load(psf_file="psf.tif")
    np.testing.assert_allclose(prob.psf[0], psf, rtol=1e-6)
    assert prob.metadata["psf_dark_corrected_file"] is True
    # the dark level the PSF was read with, beside the one given (None: it took another's, or
    # none): a plain PSF took the measurement's 100 and said psf_dark null
    assert prob.metadata["psf_dark"] is None and prob.metadata["psf_dark_applied"] is None
    assert float(load(psf_file="stack.tif").psf.sum()) == pytest.approx(2 * float(psf.sum()),
                                                                           rel=1e-5)
    # a plain image still takes --dark, and an explicit PSF dark is still applied; here that
    # second dark leaves most of it well below 0, which is said (recon.checks.negative_after_dark)
    from recon.psfcheck import PsfWarning

    with pytest.warns(PsfWarning, match=r"plain\.tif with dark 100\.0: \d+% of its pixels are "
                      r"negative.*--psf-dark N"):
        plain = load(psf_file="plain.tif")
    assert plain.metadata["psf_dark_corrected_file"] is False
    assert plain.metadata["psf_dark"] is None and plain.metadata["psf_dark_applied"] == 100.0
    np.testing.assert_allclose(plain.psf[0], np.maximum(psf - 100, 0), rtol=1e-6, atol=1e-4)
    # (and said: a second dark off a calibrated PSF was silent)
    from recon.checks import MeasurementWarning

    with pytest.warns(MeasurementWarning, match="calibrated PSF, dark-subtracted already"), \
            pytest.warns(PsfWarning, match=r"psf\.tif with dark 100\.0: \d+% of its pixels"):
        twice = load(psf_file="psf.tif", psf_dark=100.0)
    np.testing.assert_allclose(twice.psf[0], np.maximum(psf - 100, 0), rtol=1e-6, atol=1e-4)
    assert any("second dark level" in w for w in twice.metadata["warnings"])
    assert twice.metadata["psf_dark_applied"] == 100.0


def test_an_all_zero_shutter_or_filter_cube_is_named(tmp_path):
    """They were blamed on the PSF ('operator norm is 0 ... normalise the PSF')."""
    from recon.problem import read_filters, read_shutter

    np.save(tmp_path / "m.npy", np.zeros((4, 16)))
    np.save(tmp_path / "f.npy", np.zeros((3, 16, 20)))
    with pytest.raises(ValueError, match=r"shutter file .*m\.npy is all zero"):
        read_shutter(tmp_path / "m.npy")
    with pytest.raises(ValueError, match=r"filter cube file .*f\.npy is all zero"):
        read_filters(tmp_path / "f.npy")


def test_a_field_beyond_the_psfs_reach_is_refused(tmp_path):
    """--field 10000x10000 on a 37x50 sensor ran for minutes on unobservable pixels."""
    rng = np.random.default_rng(1)
    np.save(tmp_path / "psf.npy", rng.random((16, 20)).astype(np.float32))
    np.save(tmp_path / "meas.npy", rng.random((16, 20)).astype(np.float32))
    spec = ProblemSpec(meas=str(tmp_path / "meas.npy"), psf=str(tmp_path / "psf.npy"))
    assert load_problem(spec.with_changes(field="full")).model.scene_shape[-2:] == (32, 40)
    assert load_problem(spec.with_changes(field=(32, 40))).model.scene_shape[-2:] == (32, 40)
    with pytest.raises(ValueError, match=r"scene field 33x40 is larger than the 32x40 from "
                                         r"which light reaches the 16x20 sensor"):
        load_problem(spec.with_changes(field=(33, 40)))


@pytest.mark.parametrize(("factor", "which", "message"), [
    (1e300, "meas", r"measurement file .*meas64\.npy has values up to 1e\+300, beyond the "
                    r"float32 range"),
    (1e-50, "meas", r"measurement file .*meas64\.npy has values no larger than 1e-50, below "
                    r"the float32 range"),
    (1e300, "psf", r"PSF file .*psf64\.npy has values up to .*e\+299, beyond the float32 range"),
    (1e-50, "psf", r"PSF file .*psf64\.npy has values no larger than .*e-5\d, below"),
])
def test_float64_files_outside_float32_are_named(small, factor, which, message):
    """They were read into float32 as inf ('cannot normalise by max: it is inf', no file named)
    or as 0 ('measurement ... is all zero', 'PSF ... is all zero or negative')."""
    name = f"{which}64.npy"
    np.save(small / name, np.load(small / f"{which}.npy").astype(np.float64) * factor)
    with pytest.raises(ValueError, match=message) as info:
        load_problem(_spec(small, **{which: str(small / name)}))
    assert "\n" not in str(info.value)
    np.save(small / name, np.load(small / f"{which}.npy").astype(np.float64) * 1e30)
    assert load_problem(_spec(small, **{which: str(small / name)})).meas.max() == 1.0


def test_saturated_measurements_are_said_and_a_fully_saturated_one_is_refused(small):
    """A uint16 frame with 30 % of its pixels at 65535 loaded without a word; one with every
    pixel there reconstructed a constant image."""
    import tifffile

    from recon.checks import MeasurementWarning

    frame = (np.load(small / "meas.npy") * 60000).astype(np.uint16)
    frame[:7] = 65535  # 7 of 24 rows: 210 of 720 pixels
    tifffile.imwrite(small / "sat.tif", frame)
    with pytest.warns(MeasurementWarning, match=r"measurement file .*sat\.tif: 210 pixels "
                                                r"\(29\.2%\) are saturated"):
        prob = load_problem(_spec(small, meas=str(small / "sat.tif")))
    assert prob.meas.max() == 1.0
    tifffile.imwrite(small / "white.tif", np.full((24, 30), 65535, np.uint16))
    with pytest.raises(ValueError, match=r"measurement file .*white\.tif: every pixel is "
                                         r"saturated \(at the full scale 65535 of uint16\)"):
        load_problem(_spec(small, meas=str(small / "white.tif")))
    # a hot pixel or two at full scale (below 0.1 % of the pixels) is not worth a word
    import warnings

    from recon.readers import load_measurement

    frame = np.tile((np.load(small / "meas.npy") * 60000).astype(np.uint16), (2, 2))
    frame[0, 0] = 65535  # 1 of 2880 pixels: 0.035 %
    tifffile.imwrite(small / "hot.tif", frame)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_measurement(str(small / "hot.tif"))
    frame[0, :3] = 65535  # 3 of 2880: 0.10 %
    tifffile.imwrite(small / "hot.tif", frame)
    with pytest.warns(MeasurementWarning, match=r"3 pixels \(0\.104%\) are saturated"):
        load_measurement(str(small / "hot.tif"))


def test_measurement_warnings_of_a_load_obey_module_filters(tmp_path):
    """load_problem catches its inputs' warnings (to keep them in the metadata) and emits
    them again as raised, so a filter by module still matches (it saw a file path)."""
    import warnings

    from recon.checks import MeasurementWarning
    from recon.simulate import synthetic_psf

    np.save(tmp_path / "psf.npy", synthetic_psf((24, 32), seed=2))
    meas = np.random.default_rng(0).random((24, 32)).astype(np.float32)
    meas[:, :20] = 0  # 62 % zeros, no mask: a MeasurementWarning
    np.save(tmp_path / "meas.npy", meas)
    spec = ProblemSpec(meas=str(tmp_path / "meas.npy"), psf=str(tmp_path / "psf.npy"))
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        warnings.filterwarnings("ignore", category=MeasurementWarning, module="recon.problem")
        prob = load_problem(spec)
    assert [str(w.message) for w in seen] == []
    assert len(prob.metadata["warnings"]) == 1 and "no mask" in prob.metadata["warnings"][0]


def test_psf_warnings_of_a_load_are_kept_too(tmp_path):
    """A clipped PSF (the tutorial's psf_sample.tif has 192 pixels at 65520) was said on
    stderr but not in run.json's warnings, which kept measurement warnings only."""
    import warnings

    from recon.psfcheck import PsfWarning
    from recon.simulate import synthetic_psf

    psf = synthetic_psf((24, 32), seed=2)
    psf = np.minimum(psf, np.quantile(psf, 0.9))  # a flat top over 10 % of the pixels
    np.save(tmp_path / "psf.npy", psf)
    np.save(tmp_path / "meas.npy", np.random.default_rng(0).random((24, 32)).astype(np.float32))
    spec = ProblemSpec(meas=str(tmp_path / "meas.npy"), psf=str(tmp_path / "psf.npy"))
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        prob = load_problem(spec)
    assert any(issubclass(w.category, PsfWarning) for w in seen)
    assert any("saturated" in t for t in prob.metadata["warnings"]), prob.metadata["warnings"]


def test_flip_rows_turns_files_stored_upside_down_upright_exactly(tmp_path):
    """--flip-rows is a plain flip of every file (what lines the MirFlickr pairs up with their
    truth; a flip keeping the PSF's zero shift at row H // 2 scored 0.20 dB lower there): files
    stored upside down reconstruct, flipped, exactly as the upright files do."""
    from recon.io import read_reconstruction
    from recon.simulate import synthetic_psf

    up, down = tmp_path / "up", tmp_path / "down"
    up.mkdir()
    down.mkdir()
    psf = synthetic_psf((48, 40), seed=4)
    scene = np.zeros((48, 40), np.float32)
    scene[10:14, 5:30] = 1.0
    import torch

    from recon.models import build_model

    meas = build_model("2d", psf).op.apply(torch.as_tensor(scene[None, None])).numpy()
    meas = meas.reshape(48, 40)
    for d, flip in ((up, False), (down, True)):
        for name, a in (("psf", psf), ("meas", meas), ("truth", scene)):
            np.save(d / f"{name}.npy", a[::-1].copy() if flip else a)
    out = {}
    for d, extra in ((up, []), (down, ["--flip-rows"])):
        assert main(["recon", "fista", "--psf", str(d / "psf.npy"), "--meas",
                     str(d / "meas.npy"), "--tau", "1e-4", "--iters", "50", *extra,
                     "--out", str(d / "x.tif")]) == 0
        out[d] = read_reconstruction(d / "x.tif")[0]
    np.testing.assert_allclose(out[down], out[up], rtol=1e-5, atol=1e-6)  # the same sums


def test_a_transposed_shutter_file_is_named_as_such(tmp_path):
    """A (rows, K) file was refused as 'K = 48 time bins for 9 rows', naming the file's own
    columns as the rows; the measurement's rows say it is transposed."""
    from recon.problem import ProblemSpec, load_problem
    from recon.simulate import synthetic_psf

    np.save(tmp_path / "psf.npy", synthetic_psf((48, 40), seed=1))
    np.save(tmp_path / "meas.npy", np.random.default_rng(0).random((48, 40)).astype(np.float32))
    np.save(tmp_path / "sh.npy", np.ones((48, 9)))  # (rows, K): transposed
    with pytest.raises(ValueError, match=r"has shape \(48, 9\): the shutter function is "
                       r"\(K, rows\), \(K, 48\) for this measurement; this one looks "
                       r"transposed"):
        load_problem(ProblemSpec(model="video", meas=str(tmp_path / "meas.npy"),
                                 psf=str(tmp_path / "psf.npy"), shutter=str(tmp_path / "sh.npy")))


def test_a_downsampling_factor_that_does_not_divide_the_size_says_what_it_drops(small):
    """24x30 at 4x: the last 2 columns were dropped silently (a bright edge lost unsaid)."""
    import warnings

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        prob = load_problem(_spec(small, downsample=4))
    said = [t for t in prob.metadata["warnings"] if "downsampling 4x" in t]
    assert said == ["downsampling 4x drops the last 2 columns of the 24x30 measurement (4 does "
                    "not divide its size): the reconstruction sees 24x28 of it"], said
    assert any("drops the last 2 columns" in str(w.message) for w in seen)
    assert prob.meas.shape[-2:] == (6, 7)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        prob = load_problem(_spec(small, downsample=3))  # divides 24 and 30: nothing dropped
    assert not [t for t in prob.metadata["warnings"] if "downsampling" in t]
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        prob = load_problem(_spec(small, downsample=5))
    assert any("the last 4 rows of the 24x30" in t for t in prob.metadata["warnings"])
