"""Inputs that used to pass in silence and cost the reconstruction, or warned in numpy's words.

- A raw PSF on a black level, read without a dark level: a 12-bit camera pair with a black
  level of 100 counts gave 13.3 dB against 32.6 dB with ``--dark 100``, with no word. A
  caustic's darkest pixels hold almost none of its light, so a floor that holds 5 % of it is
  said (:func:`recon.psfcheck.psf_floor`); real PSFs, speckle and simulated caustics stay
  silent.
- Float data whose largest value is subnormal (a float32 frame scaled by 1e-44 holds 7
  values) was reconstructed into garbage: refused, as float64 data below float32's range was.
- ``--dark 1e300`` printed numpy's "overflow encountered in cast" before the real error.
- The factor the measurement was divided by (its normalisation) was not recorded:
  ``metadata['meas_scale']`` now, in results and run records.
- A PSF far below 0 after its dark level was clipped in silence (a measurement was warned
  of): the same rule now (:func:`recon.checks.negative_after_dark`).
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import tifffile

from app.cli import main
from recon import samples
from recon.preprocess import box_downsample
from recon.problem import ProblemSpec, load_problem
from recon.psfcheck import PsfWarning
from recon.readers import load_measurement, load_psf, load_psf_stack

SHARED = samples.shared_data_dir()


def _said(fn, category=PsfWarning, word="black level"):
    """The messages of ``category`` containing ``word`` that ``fn()`` warns of."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fn()
    return [str(w.message) for w in caught
            if issubclass(w.category, category) and word in str(w.message)]


def _camera_pair(folder, black=100, full=4095):
    """The tester's case: the tutorial caustic (150x200) and the measurement of a scene,
    written as a 12-bit camera writes them, on a black level of ``black`` counts."""
    import torch

    from recon.models import build_model
    from tests.scenes import blocks_scene

    psf = samples.tutorial_psf(normalise="sum")[0]  # (150, 200)
    scene = blocks_scene(*psf.shape, seed=3).astype(np.float32)
    b = build_model("2d", psf).apply(torch.as_tensor(scene[None, None])).numpy().reshape(psf.shape)
    span = full - black
    tifffile.imwrite(folder / "psf_cam.tif",
                     (black + psf / psf.max() * span).round().astype(np.uint16))
    tifffile.imwrite(folder / "meas_cam.tif",
                     (black + b / b.max() * span).round().astype(np.uint16))
    return folder / "psf_cam.tif", folder / "meas_cam.tif"


# -- 1. a PSF on a black level ---------------------------------------------------------------


def test_a_camera_psf_on_its_black_level_is_said_and_kept_with_the_problem(tmp_path):
    psf, meas = _camera_pair(tmp_path)
    raw = tifffile.imread(psf).astype(np.float64)
    floor = float(np.percentile(raw, 0.1))
    share = floor * raw.size / float(raw.sum())
    assert floor == 100 and share > 0.3  # the pedestal is a third of the PSF's light
    spec = ProblemSpec(psf=str(psf), meas=str(meas))
    with pytest.warns(PsfWarning) as rec:
        prob = load_problem(spec)
    said = [str(w.message) for w in rec if "black level" in str(w.message)]
    assert len(said) == 1 and "\n" not in said[0]
    assert said[0].startswith(f"PSF file {psf}: raw uint16 data read with no dark level")
    assert f"darkest pixels are at 100 counts, a floor that holds {100 * share:.0f} % " in said[0]
    assert "--dark N (the PSF's too) or --psf-dark N; 0 if the camera removes it" in said[0]
    assert said[0] in prob.metadata["warnings"]  # a result's metadata and run record keep it
    # with the dark level (the measurement's reaches the PSF), or a PSF dark of 0: silent
    for kw in ({"dark": 100.0}, {"psf_dark": 100.0}, {"psf_dark": 0.0}):
        assert _said(lambda kw=kw: load_problem(spec.with_changes(**kw))) == []


@pytest.mark.filterwarnings("default")  # shown on stderr by the CLI, as a user sees it
def test_the_cli_says_it_in_one_line(tmp_path, capsys):
    psf, meas = _camera_pair(tmp_path)
    code = main(["recon", "fista", "--psf", str(psf), "--meas", str(meas), "--tau", "1e-3",
                 "--iters", "3", "--out", str(tmp_path / "r.tif")])
    err = capsys.readouterr().err
    assert code == 0, err
    said = [line for line in err.splitlines() if "black level" in line]
    assert len(said) == 1 and said[0].startswith("lenslesscam: warning: PSF file "), err


def test_the_threshold_is_the_light_a_caustic_floor_can_hold(tmp_path):
    """Fully developed speckle (exponential intensities, contrast 1: lower than a caustic's)
    at 12 bits with no black level is silent; a pedestal holding 5 % of a PSF's light or more
    is said, one holding less is not."""
    from recon.psfcheck import FLOOR_WARN_SHARE, psf_floor

    rng = np.random.default_rng(0)
    speckle = rng.exponential(1.0, (120, 160))
    raw = np.round(speckle / speckle.max() * 4095).astype(np.uint16)
    assert psf_floor(raw)[1] < 0.01
    np.save(tmp_path / "speckle.npy", raw)
    assert _said(lambda: load_psf(tmp_path / "speckle.npy")) == []
    psf = samples.tutorial_psf(normalise="max")[0] * 3000.0  # a 12-bit caustic, floor 0
    for share, loud in ((0.6 * FLOOR_WARN_SHARE, False), (1.2 * FLOOR_WARN_SHARE, True)):
        level = round(share * float(psf.mean()) / (1 - share))  # pedestal / (psf + pedestal)
        np.save(tmp_path / "p.npy", np.round(psf + level).astype(np.uint16))
        assert bool(_said(lambda: load_psf(tmp_path / "p.npy"))) is loud, (share, level)
    # float data is not a raw frame: not judged
    np.save(tmp_path / "f.npy", (psf + 500).astype(np.float32))
    assert _said(lambda: load_psf(tmp_path / "f.npy")) == []


def test_simulated_and_bundled_psfs_stay_silent(tmp_path):
    from recon.simulate import synthetic_psf

    for seed in range(3):
        for blur in (0.0, 1.0, 3.0):
            p = synthetic_psf((60, 80), blur=blur, seed=seed)
            np.save(tmp_path / "s.npy", np.round(p / p.max() * 4095).astype(np.uint16))
            assert _said(lambda: load_psf(tmp_path / "s.npy")) == []
    assert _said(lambda: samples.tutorial_psf()) == []
    assert _said(lambda: load_psf(samples.sample_path("dlmd_psf"), channels="rgb",
                                  channel_order="bgr")) == []
    assert _said(lambda: load_psf_stack(samples.sample_path("depth"), key="psf")) == []


@pytest.mark.skipif(SHARED is None or not (SHARED / "diffusercam_tutorial").is_dir(),
                    reason="needs ../shared/data/diffusercam_tutorial")
def test_the_real_tutorial_psf_stays_silent_with_and_without_its_dark():
    """Its own black level is about 34 counts of a uint16 file holding 12 bits (x16): 2 codes,
    1.5 % of its light at the corner mean, its floor 16 (0.7 %): below what costs anything."""
    from recon.psfcheck import psf_floor

    path = SHARED / "diffusercam_tutorial" / "psf_sample.tif"
    floor, share = psf_floor(tifffile.imread(path))
    assert floor == 16 and share < 0.01
    for dark in (None, 34.08, "auto"):
        assert _said(lambda dark=dark: load_psf(path, dark=dark)) == []
        assert _said(lambda dark=dark: load_psf(path, dark=dark), word="negative") == []


# -- 2. subnormal float data -----------------------------------------------------------------


@pytest.mark.parametrize(("dtype", "scale", "bits"), [(np.float32, 1e-44, 3),
                                                      (np.float16, 1e-6, 5)])
def test_subnormal_float_data_is_refused(tmp_path, dtype, scale, bits):
    rng = np.random.default_rng(1)
    b = rng.random((20, 24))
    np.save(tmp_path / "m.npy", (b / b.max() * scale).astype(dtype))
    with pytest.raises(ValueError, match=rf"measurement file .*m\.npy has values no larger than "
                       rf".*below the smallest normal {np.dtype(dtype).name} number .*: subnormal "
                       rf"numbers that keep at most {bits} significant bits"):
        load_measurement(tmp_path / "m.npy")
    np.save(tmp_path / "p.npy", (b / b.max() * scale).astype(dtype))
    with pytest.raises(ValueError, match=r"PSF file .*p\.npy has values no larger than"):
        load_psf(tmp_path / "p.npy")
    # small but normal: read, and the same image
    ok = (b / b.max() * 100 * float(np.finfo(dtype).smallest_normal)).astype(dtype)
    np.save(tmp_path / "ok.npy", ok)
    got = load_measurement(tmp_path / "ok.npy")
    np.testing.assert_allclose(got[0], ok.astype(np.float32) / ok.max(), rtol=1e-3, atol=2e-3)


# -- 3. a dark level beyond the data's range --------------------------------------------------


@pytest.mark.filterwarnings("default")
def test_a_dark_level_beyond_float32_is_one_error_line(tmp_path, capsys):
    psf, meas = _camera_pair(tmp_path)
    code = main(["recon", "fista", "--psf", str(psf), "--meas", str(meas), "--dark", "1e300",
                 "--iters", "3", "--out", str(tmp_path / "r.tif")])
    err = capsys.readouterr().err
    assert code != 0
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "overflow" not in err and "RuntimeWarning" not in err
    assert lines[0].startswith(f"lenslesscam recon: error: measurement file {meas}: dark level "
                               "1e+300 is beyond the range of the float32 image")


def test_no_numpy_warning_from_a_huge_dark_level_or_frame(tmp_path):
    psf, meas = _camera_pair(tmp_path)
    with pytest.raises(ValueError, match=r"PSF file .*psf_cam\.tif: dark level 1e\+300 is "
                       r"beyond the range"):
        load_psf(psf, dark=1e300)
    frame = np.full(tifffile.imread(meas).shape, 1e300)
    with pytest.raises(ValueError, match=r"measurement file .*meas_cam\.tif: dark frame has "
                       r"values up to 1e\+300, beyond the range"):
        load_measurement(meas, dark=frame)
    with pytest.raises(ValueError, match=r"PSF stack file .*psf_cam\.tif: dark level 1e\+300"):
        load_psf_stack(psf, dark=1e300)


# -- 4. the measurement's scale --------------------------------------------------------------


def test_the_scale_divided_out_of_the_measurement_is_recorded(tmp_path):
    psf, meas = _camera_pair(tmp_path)
    spec = ProblemSpec(psf=str(psf), meas=str(meas), dark=100.0, downsample=2)
    prob = load_problem(spec)
    counts = box_downsample(tifffile.imread(meas).astype(np.float32) - 100.0, 2)
    scale = prob.metadata["meas_scale"]
    assert isinstance(scale, float) and scale == pytest.approx(float(counts.max()), rel=1e-6)
    np.testing.assert_allclose(prob.meas[0] * scale, np.maximum(counts, 0), rtol=1e-5,
                               atol=1e-3)
    assert prob.inputs["measurement"]["meas_scale"] == scale
    assert load_problem(spec.with_changes(meas_normalise="none")).metadata["meas_scale"] == 1.0
    l2 = load_problem(spec.with_changes(meas_normalise="l2")).metadata["meas_scale"]
    assert l2 == pytest.approx(float(np.linalg.norm(np.maximum(counts, 0))), rel=1e-5)


def test_the_scale_reaches_a_result_file_and_a_udn_run(tmp_path):
    from recon.io import read_reconstruction
    from recon.udn.jobs import run_job
    from tests.udn.conftest import write_spec

    psf, meas = _camera_pair(tmp_path)
    out = tmp_path / "r.tif"
    assert main(["recon", "fista", "--psf", str(psf), "--meas", str(meas), "--dark", "100",
                 "--tau", "1e-3", "--iters", "3", "--out", str(out)]) == 0
    scale = load_problem(ProblemSpec(psf=str(psf), meas=str(meas), dark=100.0)).metadata[
        "meas_scale"]
    assert scale > 1000  # counts above the black level
    assert read_reconstruction(out)[1]["preprocessing"]["meas_scale"] == pytest.approx(scale)
    spec = write_spec(tmp_path, data={"psf": psf.name, "measurement": meas.name, "dark": 100.0,
                                      "mask": None, "truth": None},
                      stopping={"max_iter": 2}, output={"checkpoint_every": 2,
                                                        "preview_every": 2})
    run_job(spec, tmp_path / "run")
    rec = json.loads((tmp_path / "run" / "run.json").read_text())
    assert rec["inputs"]["measurement"]["meas_scale"] == pytest.approx(scale)
    final = read_reconstruction(tmp_path / "run" / rec["results"]["final"])[1]
    assert final["preprocessing"]["meas_scale"] == pytest.approx(scale)


# -- 5. a PSF below 0 after its dark level ---------------------------------------------------


def test_a_psf_far_below_zero_is_said_as_a_measurement_is(tmp_path):
    psf, meas = _camera_pair(tmp_path)
    raw = tifffile.imread(psf).astype(np.int32)
    signed = (raw - int(np.percentile(raw, 48))).astype(np.int16)  # int16, about half negative
    assert 0.4 < np.mean(signed < 0) < 0.5
    np.save(tmp_path / "signed.npy", signed)
    said = _said(lambda: load_psf(tmp_path / "signed.npy"), word="negative")
    assert len(said) == 1
    assert said[0].startswith(f"PSF file {tmp_path / 'signed.npy'} read with no dark level "
                              "(negative in the file): ")
    assert "of its pixels are negative, together " in said[0] and "--psf-dark N" in said[0]
    # none of them below -5 % of its peak: the measurement's depth would not see it (a
    # caustic's peak is 60 times its mean), though it costs 6 dB
    from recon.checks import negative_measurement

    assert negative_measurement(signed.astype(np.float32)) is None
    # the measurement's dark of 100 right, a PSF dark of 4094 leaves one pixel above 0
    spec = ProblemSpec(psf=str(psf), meas=str(meas), dark=100.0, psf_dark=4094.0)
    with pytest.warns(PsfWarning, match=r"psf_cam\.tif with dark 4094\.0: >99\.99% of its pixels "
                      r"are negative") as rec:
        prob = load_problem(spec)
    assert len(rec) == 1
    assert any("with dark 4094.0" in w for w in prob.metadata["warnings"])
    # a stack alike; and the right dark level stays silent (read noise around 0 is not it)
    with pytest.warns(PsfWarning, match=r"PSF stack file .*psf_cam\.tif with dark 4000\.0"):
        load_psf_stack(psf, dark=4000.0)
    noisy = raw + np.random.default_rng(0).normal(0, 3, raw.shape)
    np.save(tmp_path / "noisy.npy", np.round(noisy).astype(np.uint16))
    assert _said(lambda: load_psf(tmp_path / "noisy.npy", dark=100.0), word="negative") == []
