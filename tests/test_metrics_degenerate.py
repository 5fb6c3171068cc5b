"""``lenslesscam metrics`` on inputs with nothing (or the wrong scale) to score.

Three ways it reported a number that meant nothing, without a word:

- the tool's own 8-bit preview (0..255) against a 0..1 truth scored -42 dB for its units
  alone: a ``scale_note`` (JSON and stderr) now says so and points to ``--gain-fit``;
- an all-zero reference with ``--data-range 1 --gain-fit`` fitted gain 0 to any estimate and
  scored it perfect (PSNR inf, SSIM 1): a constant reference is refused in one line;
- an all-zero estimate with ``--gain-fit`` reported ``gain`` 1.0 and ``gain_fit`` true, a fit
  that is undefined there and was skipped: ``gain`` is null, ``gain_fit`` false, with a note.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from recon import metrics as M
from tests.clirun import run_cli as _run


def _truth(h: int = 40, w: int = 50) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w]
    rng = np.random.default_rng(3)
    t = 0.5 + 0.3 * np.sin(x / 4.0) * np.cos(y / 6.0) + 0.1 * rng.random((h, w))
    return t.astype(np.float32)


@pytest.fixture()
def files(tmp_path: Path) -> Path:
    """truth.npy (0..1), est.tif (a reconstruction about twice as bright, with its est.png
    preview, 0..255), zeros.npy and zest.npy (all zero, the truth's shape)."""
    from recon.io import save_reconstruction

    t = _truth()
    np.save(tmp_path / "truth.npy", t)
    rng = np.random.default_rng(5)
    est = (2.0 * t + 0.05 * rng.standard_normal(t.shape)).clip(0).astype(np.float32)
    save_reconstruction(tmp_path / "est.tif", est[None, None], {"method": "test"})
    assert (tmp_path / "est.png").is_file()  # the tool's own preview
    np.save(tmp_path / "zeros.npy", np.zeros_like(t))
    np.save(tmp_path / "zest.npy", np.zeros_like(t))
    return tmp_path


# ------------------------------------------------------------------------------------------
# 1. scales far apart, no gain fit: said
# ------------------------------------------------------------------------------------------


def test_preview_png_against_a_float_truth_is_noted(files: Path, capsys) -> None:
    code, out, err = _run(capsys, "metrics", "--ref", files / "truth.npy",
                          "--est", files / "est.png")
    assert code == 0
    rep = json.loads(out)
    assert rep["psnr"] < -20  # the number is what it was; it is no longer silent
    note = rep["scale_note"]
    assert "255" in note and "larger" in note and "--gain-fit" in note
    assert err.strip() == f"lenslesscam metrics: note: {note}"  # one line on stderr

    code, out, err = _run(capsys, "metrics", "--ref", files / "truth.npy",
                          "--est", files / "est.png", "--gain-fit")
    assert code == 0 and "scale_note" not in json.loads(out) and err == ""


def test_a_normal_scale_difference_is_not_noted(files: Path, capsys) -> None:
    """A reconstruction twice as bright as its truth is the usual case: no note."""
    code, out, err = _run(capsys, "metrics", "--ref", files / "truth.npy",
                          "--est", files / "est.tif")
    assert code == 0 and "scale_note" not in json.loads(out) and err == ""


def test_scale_note_in_the_report() -> None:
    t = _truth().astype(np.float64)
    assert "scale_note" not in M.metrics_report(t, 2.0 * t)
    assert "scale_note" not in M.metrics_report(t, 0.2 * t)
    big = M.metrics_report(t / t.max(), 255.0 * t / t.max())
    assert "reach 255 and ref's 1 (255 times larger)" in big["scale_note"]
    small = M.metrics_report(t, t / 1000.0)
    assert "(1e+03 times smaller)" in small["scale_note"]
    assert "scale_note" not in M.metrics_report(t, t / 1000.0, gain_fit=True)
    # at the limits of float64 the factor is still written, not overflowed
    assert "1e600 times larger" in M.metrics_report(t * 1e-300, t * 1e300)["scale_note"]
    json.dumps(big)


# ------------------------------------------------------------------------------------------
# 2. a constant reference: nothing to score against
# ------------------------------------------------------------------------------------------


def test_all_zero_reference_is_refused_not_scored_perfect(files: Path, capsys) -> None:
    code, out, err = _run(capsys, "metrics", "--ref", files / "zeros.npy",
                          "--est", files / "est.tif", "--data-range", "1", "--gain-fit")
    assert code == 2 and out == ""
    line = err.strip()
    assert "\n" not in line
    assert line.startswith("lenslesscam metrics: error: ref is constant (every value is 0): "
                           "nothing to score against")
    assert "zeros.npy" in line


def test_constant_reference_is_refused_in_the_report() -> None:
    est = _truth().astype(np.float64)
    ref = np.zeros_like(est)
    for fit in (False, True):
        with pytest.raises(ValueError, match=r"ref is constant \(every value is 0\): "
                           "nothing to score against"):
            M.metrics_report(ref, est, gain_fit=fit, data_range=1.0)
    with pytest.raises(ValueError, match="ref is constant"):  # the default data range too
        M.metrics_report(ref, est, gain_fit=True)
    flat = np.full_like(est, 0.5)  # a flat-field target: its range is 0, give one
    with pytest.raises(ValueError, match=r"every value is 0\.5\) and no data range"):
        M.metrics_report(flat, est)
    near = flat + 0.05 * np.random.default_rng(0).standard_normal(est.shape)
    rep = M.metrics_report(flat, near, data_range=1.0)  # scored, as before
    assert rep["psnr"] == pytest.approx(-10 * np.log10(np.mean((near - flat) ** 2)), rel=1e-6)


# ------------------------------------------------------------------------------------------
# 3. an all-zero estimate has no least-squares gain
# ------------------------------------------------------------------------------------------


def test_all_zero_estimate_reports_no_gain(files: Path, capsys) -> None:
    code, out, err = _run(capsys, "metrics", "--ref", files / "truth.npy",
                          "--est", files / "zest.npy", "--gain-fit")
    assert code == 0
    rep = json.loads(out)
    assert rep["gain"] is None and rep["gain_fit"] is False
    assert "est is all zero" in rep["gain_note"]
    assert err.strip() == f"lenslesscam metrics: note: {rep['gain_note']}"
    code, out2, _ = _run(capsys, "metrics", "--ref", files / "truth.npy",
                         "--est", files / "zest.npy")
    plain = json.loads(out2)  # scored as it is: the same numbers as without the fit
    assert plain["gain"] == 1.0 and plain["gain_fit"] is False and "gain_note" not in plain
    assert rep["psnr"] == pytest.approx(plain["psnr"]) and rep["ssim"] == pytest.approx(
        plain["ssim"])


def test_all_zero_estimate_in_the_report() -> None:
    t = _truth().astype(np.float64)
    rep = M.metrics_report(t, np.zeros_like(t), gain_fit=True)
    assert rep["gain"] is None and rep["gain_fit"] is False and "gain_note" in rep
    assert "scale_note" not in rep
    json.dumps(rep)
    # a normal estimate: fitted as before, no notes (batch, jobs, ensemble scores unchanged)
    normal = M.metrics_report(t, 0.5 * t, gain_fit=True)
    assert normal["gain_fit"] is True and normal["gain"] == pytest.approx(2.0)
    assert not {"gain_note", "scale_note"} & set(normal)
