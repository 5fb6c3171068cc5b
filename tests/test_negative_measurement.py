"""A measurement mostly below 0 after its dark level is said, not clipped to 0 in silence.

A dark level above the sensor's black level (or a frame saved after subtracting one) leaves a
large share of the pixels well below 0; the loader clips them to 0 and the reconstruction fits
them as black. An all-zero measurement warned, a 55 %-negative one did not. The rule
(recon.checks.negative_measurement): more than 5 % of the measured pixels below -5 % of the
largest magnitude; the read noise of a correct dark level (many pixels slightly below 0)
stays silent.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from app.cli import main
from recon.checks import MeasurementWarning
from recon.problem import ProblemSpec, load_problem


def _bench(tmp_path):
    """A simulated 2D capture: PSF, and the measurement of a scene (max 1, float32)."""
    import torch

    from recon.models import build_model
    from recon.simulate import synthetic_psf
    from tests.scenes import blocks_scene

    psf = synthetic_psf((24, 32), seed=4)
    scene = blocks_scene(24, 32, seed=2).astype(np.float32)
    b = build_model("2d", psf).apply(torch.as_tensor(scene[None, None])).numpy()[0]
    b = (b / b.max()).astype(np.float32)
    np.save(tmp_path / "psf.npy", psf)
    return b


def _silent(spec):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        prob = load_problem(spec)
    said = [str(w.message) for w in caught if issubclass(w.category, MeasurementWarning)]
    assert said == []
    return prob


def test_a_dark_level_above_the_black_level_is_said(tmp_path):
    b = _bench(tmp_path)
    rng = np.random.default_rng(0)
    raw = np.round(100 + 1000 * b + rng.normal(0, 2, b.shape)).astype(np.uint16)  # black 100
    np.save(tmp_path / "raw.npy", raw)
    spec = ProblemSpec(psf=str(tmp_path / "psf.npy"), meas=str(tmp_path / "raw.npy"),
                       dark=100.0, psf_dark=0.0)
    _silent(spec)  # the right dark level: silent
    # a dark level of 700: 100 above the black level, the frame mostly below 0
    with pytest.warns(MeasurementWarning, match=r"raw\.npy with dark 700\.0: \d+% of its "
                      r"measured pixels are negative, \d+% below -5% of its largest value .*"
                      r"the dark level is likely above the sensor's black level") as rec:
        load_problem(spec.with_changes(dark=700.0))
    assert len([w for w in rec if "negative" in str(w.message)]) == 1
    assert "\n" not in str(rec[0].message)


@pytest.mark.filterwarnings("default")  # shown on stderr by the CLI, as a user sees it
def test_a_file_saved_after_too_large_a_dark_is_said_by_every_command(tmp_path, capsys):
    """The hostile tester's case: a simulated measurement minus 0.5 (55 % negative)."""
    b = _bench(tmp_path)
    np.save(tmp_path / "meas.npy", b - 0.5)
    assert np.mean(b - 0.5 < 0) > 0.3
    inputs = ["--psf", str(tmp_path / "psf.npy"), "--meas", str(tmp_path / "meas.npy"),
              "--tau", "1e-3"]
    for argv in (["recon", "fista", *inputs, "--iters", "5", "--out", str(tmp_path / "r.tif")],
                 ["plan", *inputs, "--no-probe"]):
        code = main(argv)
        err = capsys.readouterr().err
        assert code == 0, err
        said = [line for line in err.splitlines() if "negative" in line]
        assert len(said) == 1, err
        assert said[0].startswith("lenslesscam: warning: measurement file ")
        assert "read with no dark level (negative in the file)" in said[0]
        assert "clipped to 0" in said[0]
    # and the result's metadata keeps it (load_problem's warnings)
    from recon.io import read_reconstruction

    meta = read_reconstruction(tmp_path / "r.tif")[1]
    assert any("negative" in w for w in meta["preprocessing"]["warnings"])


def test_read_noise_around_a_correct_dark_stays_silent(tmp_path):
    """A sparse frame (60 % of the pixels dark) with read noise of 1 % of its maximum: a third
    of its pixels are slightly negative after the right dark level: no warning."""
    from recon.checks import NEGATIVE_WARN_FRACTION, negative_measurement

    rng = np.random.default_rng(1)
    signal = np.where(rng.random((24, 32)) < 0.6, 0.0, rng.uniform(0.2, 1.0, (24, 32)))
    b = (signal + rng.normal(0, 0.01, signal.shape)).astype(np.float32)
    assert np.mean(b < 0) > 5 * NEGATIVE_WARN_FRACTION  # the fraction alone would fire
    assert negative_measurement(b) is None
    _bench(tmp_path)
    np.save(tmp_path / "meas.npy", b)
    _silent(ProblemSpec(psf=str(tmp_path / "psf.npy"), meas=str(tmp_path / "meas.npy")))
    # the same frame 10 % of its maximum too low: said
    assert negative_measurement(b - 0.1) is not None


def test_the_rule_counts_measured_pixels_only():
    """A frame 95 % erased (0) whose measured pixels are mostly negative: the fraction is of
    the measured pixels (all of them would dilute it below 5 %)."""
    from recon.checks import NEGATIVE_WARN_DEPTH, NEGATIVE_WARN_FRACTION, negative_measurement

    rng = np.random.default_rng(2)
    mask = rng.random((40, 50)) < 0.05
    b = np.zeros((1, 40, 50), np.float32)
    b[0, mask] = rng.uniform(-0.5, 0.4, int(mask.sum()))
    assert negative_measurement(b) is None  # diluted by the erased zeros
    msg = negative_measurement(b, mask)
    assert msg is not None and msg.startswith(f"{100 * np.mean(b[0, mask] < 0):.0f}% of its "
                                              "measured pixels are negative")
    # the depth is relative to the largest magnitude: counts or a frame of max 1 alike
    assert negative_measurement(1000 * b, mask) is not None
    # no positive pixel at all: the loaders' "all zero" error says it, not this
    assert negative_measurement(b - 1.0, mask) is None
    assert NEGATIVE_WARN_DEPTH == 0.05 and NEGATIVE_WARN_FRACTION == 0.05


def test_load_problem_checks_the_measured_pixels_of_its_mask(tmp_path):
    _bench(tmp_path)
    rng = np.random.default_rng(3)
    mask = (rng.random((24, 32)) < 0.1).astype(np.float32)
    b = np.zeros((24, 32), np.float32)
    b[mask > 0] = rng.uniform(-0.5, 0.5, int(mask.sum()))
    np.save(tmp_path / "meas.npy", b)
    np.save(tmp_path / "mask.npy", mask)
    with pytest.warns(MeasurementWarning, match="of its measured pixels are negative"):
        load_problem(ProblemSpec(psf=str(tmp_path / "psf.npy"), meas=str(tmp_path / "meas.npy"),
                                 mask=str(tmp_path / "mask.npy")))
