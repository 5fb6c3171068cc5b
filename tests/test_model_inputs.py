"""The video, spectral and depth models' own inputs: shutter functions, filter cubes, stacks.

What the loader (every recon command), ``simulate`` and ``calibrate filters`` refuse, warn
about or read, each found by a tester with a command that ran on regardless.
"""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from recon.checks import MeasurementWarning
from recon.problem import ProblemSpec, load_problem, read_filters, read_shutter
from tests.clirun import run_cli

H, W = 16, 20


@pytest.fixture
def pair(tmp_path):
    """A PSF and a measurement of a 16x20 sensor, and a scene for simulate."""
    rng = np.random.default_rng(0)
    np.save(tmp_path / "psf.npy", rng.random((H, W)).astype(np.float32))
    np.save(tmp_path / "meas.npy", rng.random((H, W)).astype(np.float32))
    np.save(tmp_path / "scene.npy", rng.random((H, W)).astype(np.float32))
    return tmp_path


def _cube(k: int = 4, h: int = H, w: int = W) -> np.ndarray:
    return np.random.default_rng(1).uniform(0.05, 1, (k, h, w)).astype(np.float32)


def _spectral(d, filters: str, **kw) -> ProblemSpec:
    return ProblemSpec(meas=str(d / "meas.npy"), psf=str(d / "psf.npy"), model="spectral",
                       filters=str(d / filters), **kw)


def _video(d, shutter: str, **kw) -> ProblemSpec:
    return ProblemSpec(meas=str(d / "meas.npy"), psf=str(d / "psf.npy"), model="video",
                       shutter=str(d / shutter), **kw)


def _one_line_error(code: int, err: str) -> str:
    assert code != 0
    lines = [ln for ln in err.splitlines() if "error" in ln]
    assert len(lines) == 1, err
    return lines[0]


# -- 1. filter cubes: the one rule of calibrate filters ---------------------------------------


def _half_negative(c: np.ndarray) -> None:
    c[:, :, ::2] -= 0.6  # a filter cannot subtract light: 38 % of a simulated frame was < 0


def _zero_band(c: np.ndarray) -> None:
    c[2] = 0.0  # the measurement holds nothing of it: FISTA filled it with TV alone


@pytest.mark.parametrize(("name", "spoil", "expect"), [
    ("halfneg", _half_negative, "negative transmissions"),
    ("zeroband", _zero_band, r"bands \[2\] are all zero"),
])
def test_a_negative_or_empty_filter_cube_is_refused_everywhere(pair, capsys, name, spoil,
                                                               expect):
    from calibration.filters import validate_filter_cube

    cube = _cube()
    spoil(cube)
    np.save(pair / f"{name}.npy", cube)
    with pytest.raises(ValueError, match=expect):
        read_filters(pair / f"{name}.npy")
    with pytest.raises(ValueError, match=rf"filter cube file .*{name}\.npy .*{expect}"):
        load_problem(_spectral(pair, f"{name}.npy"))
    # calibrate filters refuses it with the same rule (one function)
    with pytest.raises(ValueError, match=expect):
        validate_filter_cube(cube, (H, W))
    code, _, err = run_cli(capsys, "simulate", "--model", "spectral", "--psf", pair / "psf.npy",
                           "--scene", pair / "scene.npy", "--filters", pair / f"{name}.npy",
                           "--out", pair / "sim")
    assert "filter cube file" in _one_line_error(code, err)
    assert not (pair / "sim").exists()
    code, _, err = run_cli(capsys, "recon", "fista", "--model", "spectral", "--psf",
                           pair / "psf.npy", "--meas", pair / "meas.npy", "--filters",
                           pair / f"{name}.npy", "--iters", "2", "--out", pair / "x.tif")
    assert "filter cube file" in _one_line_error(code, err)


def test_rounding_below_zero_in_a_filter_cube_is_clipped_not_refused(pair):
    cube = _cube()
    cube[0, 0, 0] = -1e-9  # below 1e-6 of the maximum: rounding
    np.save(pair / "f.npy", cube)
    f = read_filters(pair / "f.npy")
    assert f.min() == 0 and f.dtype == np.float64
    assert load_problem(_spectral(pair, "f.npy")).filters.min() == 0


@pytest.mark.filterwarnings("ignore:downsampling 2x drops:recon.checks.MeasurementWarning")
def test_a_band_that_only_the_dropped_pixels_held_is_refused_after_downsampling(tmp_path):
    rng = np.random.default_rng(0)
    np.save(tmp_path / "psf.npy", rng.random((17, 20)).astype(np.float32))
    np.save(tmp_path / "meas.npy", rng.random((17, 20)).astype(np.float32))
    cube = _cube(3, 17, 20)
    cube[1, :16] = 0.0  # band 1 lives in row 16 alone, which a 2x downsampling drops
    np.save(tmp_path / "f.npy", cube)
    assert load_problem(_spectral(tmp_path, "f.npy")).filters.shape == (3, 17, 20)
    with pytest.raises(ValueError, match=r"downsampled 2x\) bands \[1\] are all zero"):
        load_problem(_spectral(tmp_path, "f.npy", downsample=2))


# -- 3. (H, W, K) filter cubes (SpectralDiffuserCam's .mat) -----------------------------------


def test_an_hwk_mat_cube_is_read_as_calibrate_filters_reads_it(pair):
    import scipy.io

    cube = _cube()
    np.save(pair / "khw.npy", cube)
    scipy.io.savemat(pair / "hwk.mat", {"mask": np.moveaxis(cube, 0, -1)})
    khw = load_problem(_spectral(pair, "khw.npy"))
    hwk = load_problem(_spectral(pair, "hwk.mat"))  # was: "is (16, 20, 4); expected (K, 16, 20)"
    np.testing.assert_array_equal(hwk.filters, khw.filters)
    assert hwk.model.scene_shape == khw.model.scene_shape == (1, 4, H, W)
    # at the reconstruction's resolution too
    small = cube.reshape(4, H // 2, 2, W // 2, 2).mean(axis=(2, 4))
    scipy.io.savemat(pair / "hwk_small.mat", {"mask": np.moveaxis(small, 0, -1)})
    down = load_problem(_spectral(pair, "hwk_small.mat", downsample=2))
    np.testing.assert_allclose(down.filters, small / small.max(), rtol=1e-6)


def test_calibrate_filters_and_recon_take_the_same_array_of_a_mat_file(pair):
    """A .mat with the cube and another array: one choice of variable, not two."""
    import scipy.io

    from calibration.filters import load_filter_cube

    cube = _cube()
    scipy.io.savemat(pair / "two.mat", {"filters": cube, "data": _cube(4, H, W)[:, ::-1]})
    recon_side = load_problem(_spectral(pair, "two.mat")).filters
    calib_side = load_filter_cube(pair / "two.mat", (H, W)).cube  # was: the "data" array
    np.testing.assert_allclose(recon_side, calib_side, rtol=1e-6)
    np.testing.assert_allclose(recon_side, cube / cube.max(), rtol=1e-6)


def test_a_filter_cube_in_other_units_gives_the_same_problem_and_result(pair, capsys):
    """Transmission in percent or in [0, 1]: the loader scales the cube to a maximum of 1,
    as the measurement, so a fixed --tau means one thing (was: 100x weaker TV in percent)."""
    cube = _cube()
    np.save(pair / "unit.npy", cube)
    np.save(pair / "percent.npy", cube * 100)
    unit = load_problem(_spectral(pair, "unit.npy"))
    percent = load_problem(_spectral(pair, "percent.npy"))
    np.testing.assert_allclose(percent.filters, unit.filters, rtol=1e-6)
    assert float(unit.filters.max()) == pytest.approx(1.0)
    assert percent.metadata["filters_scale"] == pytest.approx(100 * cube.max(), rel=1e-6)
    outs = []
    for name in ("unit", "percent"):
        code, _, err = run_cli(capsys, "recon", "fista", "--model", "spectral", "--psf",
                               pair / "psf.npy", "--meas", pair / "meas.npy", "--filters",
                               pair / f"{name}.npy", "--tau", "1e-3", "--iters", "20",
                               "--out", pair / f"{name}.npy.tif")
        assert code == 0, err
        from recon.readers import load_image
        outs.append(load_image(pair / f"{name}.npy.tif").astype(np.float64))
    np.testing.assert_allclose(outs[1], outs[0], rtol=1e-4, atol=1e-6 * outs[0].max())


def test_a_cube_that_fits_neither_or_both_layouts_says_how_to_convert_it(tmp_path, pair):
    import scipy.io

    scipy.io.savemat(pair / "bad.mat", {"mask": _cube(4, 12, 20)})
    with pytest.raises(ValueError, match=r"\(K, H, W\) or \(H, W, K\).*calibrate filters "
                                         r"--cube FILE"):
        load_problem(_spectral(pair, "bad.mat"))
    rng = np.random.default_rng(2)
    for name in ("psf", "meas"):
        np.save(tmp_path / f"sq_{name}.npy", rng.random((16, 16)).astype(np.float32))
    np.save(tmp_path / "square.npy", _cube(16, 16, 16))
    spec = ProblemSpec(meas=str(tmp_path / "sq_meas.npy"), psf=str(tmp_path / "sq_psf.npy"),
                       model="spectral", filters=str(tmp_path / "square.npy"))
    with pytest.raises(ValueError, match=r"as \(K, H, W\) and as \(H, W, K\).*calibrate filters"):
        load_problem(spec)


# -- 2. shutter functions: empty bins and dark rows -------------------------------------------


def _shutter(k: int = 4, rows: int = H) -> np.ndarray:
    m = np.zeros((k, rows))
    for r in range(rows):  # a rolling shutter: each row integrates two consecutive bins
        m[(r * (k - 1)) // rows, r] = 0.5
        m[(r * (k - 1)) // rows + 1, r] = 0.5
    return m


def test_a_time_bin_no_row_integrates_is_refused(pair, capsys):
    glob = np.zeros((9, H))
    glob[0] = 1.0  # a "global" shutter with 8 of its 9 bins empty: 8 frames of pure TV fill
    np.save(pair / "global.npy", glob)
    with pytest.raises(ValueError, match=r"8 of its 9 time bins all zero \(bins \[1-8\]\).*"
                                         r"fewer bins"):
        read_shutter(pair / "global.npy")
    with pytest.raises(ValueError, match=r"global\.npy has 8 of its 9 time bins all zero"):
        load_problem(_video(pair, "global.npy"))
    code, _, err = run_cli(capsys, "recon", "fista", "--model", "video", "--psf",
                           pair / "psf.npy", "--meas", pair / "meas.npy", "--shutter",
                           pair / "global.npy", "--iters", "2", "--out", pair / "x.tif")
    assert "bins [1-8]" in _one_line_error(code, err)
    code, _, err = run_cli(capsys, "simulate", "--model", "video", "--psf", pair / "psf.npy",
                           "--scene", pair / "scene.npy", "--shutter", pair / "global.npy",
                           "--out", pair / "sim")
    assert "bins [1-8]" in _one_line_error(code, err)


@pytest.mark.filterwarnings("ignore:downsampling 2x drops:recon.checks.MeasurementWarning")
def test_a_bin_only_the_dropped_rows_held_is_refused_after_downsampling(tmp_path):
    rng = np.random.default_rng(0)
    np.save(tmp_path / "psf.npy", rng.random((17, 20)).astype(np.float32))
    np.save(tmp_path / "meas.npy", rng.random((17, 20)).astype(np.float32))
    m = _shutter(4, 16)
    m = np.concatenate([np.vstack([m, np.zeros((1, 16))]), np.eye(5)[:, 4:]], axis=1)
    np.save(tmp_path / "m.npy", m)  # bin 4: row 16 alone, which a 2x downsampling drops
    assert load_problem(_video(tmp_path, "m.npy")).shutter.shape == (5, 17)
    with pytest.raises(ValueError, match=r"downsampled 2x\) has 1 of its 5 time bins all "
                                         r"zero \(bins \[4\]\)"):
        load_problem(_video(tmp_path, "m.npy", downsample=2))


def test_rows_that_integrate_no_light_are_named_in_a_kept_warning(pair):
    m = _shutter()
    m[:, 3:5] = 0.0
    m[:, 11] = 0.0
    np.save(pair / "m.npy", m)
    with pytest.warns(MeasurementWarning, match=r"3 of its 16 rows integrate no light in any "
                                                r"time bin \(rows \[3-4, 11\]\)"):
        prob = load_problem(_video(pair, "m.npy"))
    assert any("rows [3-4, 11]" in w for w in prob.metadata["warnings"])
    # a shutter whose every row sees light says nothing
    np.save(pair / "ok.npy", _shutter())
    assert not load_problem(_video(pair, "ok.npy")).metadata["warnings"]


# -- 4. more time bins than rows -------------------------------------------------------------


def test_more_time_bins_than_rows_is_refused_at_once(tmp_path, pair, capsys):
    rng = np.random.default_rng(0)
    np.save(tmp_path / "psf75.npy", rng.random((75, 100)).astype(np.float32))
    np.save(tmp_path / "meas75.npy", rng.random((75, 100)).astype(np.float32))
    # (the tester's 3000 bins ran for more than 5 minutes at 1.8 GB; 300 show it in seconds)
    np.save(tmp_path / "huge.npy", np.ones((300, 75), np.float32) / 300)
    t0 = time.perf_counter()
    code, _, err = run_cli(capsys, "recon", "fista", "--model", "video", "--psf",
                           tmp_path / "psf75.npy", "--meas", tmp_path / "meas75.npy",
                           "--shutter", tmp_path / "huge.npy", "--iters", "3", "--tau", "1e-5",
                           "--out", tmp_path / "h.tif")  # was: a silent power iteration
    line = _one_line_error(code, err)
    assert "K = 300 time bins for 75 rows" in line and "--bin-lines" in line
    assert time.perf_counter() - t0 < 10
    # K = rows is a shutter of one-line bins: taken
    np.save(pair / "k16.npy", np.eye(H))
    assert load_problem(_video(pair, "k16.npy")).model.k == H
    # rows after the downsampling: 12 bins of a 16-row sensor at 2x are 12 frames on 8 rows
    np.save(pair / "k12.npy", np.eye(H)[:12] + np.eye(H)[4:])
    assert load_problem(_video(pair, "k12.npy")).model.k == 12
    with pytest.raises(ValueError, match=r"K = 12 time bins for 8 rows.*smaller downsampling "
                                         r"factor than 2"):
        load_problem(_video(pair, "k12.npy", downsample=2))


# -- 5. --psf-stack makes a depth model, as in recon auto ------------------------------------


def test_a_psf_stack_without_model_depth_is_a_depth_problem(pair, capsys):
    rng = np.random.default_rng(3)
    np.save(pair / "stack.npy", rng.random((3, H, W)).astype(np.float32))
    code, out, err = run_cli(capsys, "recon", "fista", "--meas", pair / "meas.npy",
                             "--psf-stack", pair / "stack.npy", "--tau", "3e-3", "--iters",
                             "3", "--out", pair / "d.tif")  # was: "psf file is required ..."
    assert code == 0, err
    from recon.io import read_reconstruction

    x, meta = read_reconstruction(pair / "d.tif")
    assert x.shape == (1, 3, H, W) and meta["kind"] == "depth" and meta["model"] == "depth"
    # udn writes the same problem
    code, _, err = run_cli(capsys, "recon", "udn", "--meas", pair / "meas.npy", "--psf-stack",
                           pair / "stack.npy", "--write-spec", pair / "job.toml")
    assert code == 0, err
    import tomllib

    assert tomllib.loads((pair / "job.toml").read_text())["data"]["model"] == "depth"
    # admm says it takes the 2d model only; a stack with another --model is named
    code, _, err = run_cli(capsys, "recon", "admm", "--meas", pair / "meas.npy", "--psf-stack",
                           pair / "stack.npy", "--out", pair / "a.tif")
    assert "not depth" in _one_line_error(code, err)
    for model in ("2d", "video"):
        code, _, err = run_cli(capsys, "recon", "fista", "--model", model, "--meas",
                               pair / "meas.npy", "--psf-stack", pair / "stack.npy",
                               "--out", pair / "b.tif")
        assert "--psf-stack needs --model depth" in _one_line_error(code, err)
        assert f"not --model {model}" in err
    # and without a stack the default is still 2d
    code, out, err = run_cli(capsys, "recon", "fista", "--meas", pair / "meas.npy", "--psf",
                             pair / "psf.npy", "--iters", "3", "--tau", "1e-3",
                             "--out", pair / "p.tif")
    assert code == 0, err
    assert json.loads(out)["iterations"] == 3
    assert read_reconstruction(pair / "p.tif")[1]["model"] == "2d"


# -- 6. --psf-dark's help names only accepted values -----------------------------------------


def test_psf_dark_help_offers_only_accepted_values():
    from app.cli import build_parser

    parser = build_parser()
    for method in ("fista", "admm", "udn"):
        sub = parser._subparsers._group_actions[0].choices["recon"]
        action = next(a for a in sub._subparsers._group_actions[0].choices[method]._actions
                      if "--psf-dark" in a.option_strings)
        assert "none" not in action.help
        assert "a number, 'auto' or a dark-frame file" in action.help and "give 0" in action.help


def test_simulate_reads_an_hwk_cube_as_recon_does(pair, capsys):
    """simulate read only (K, H, W) cubes: SpectralDiffuserCam's (H, W, K) .mat was refused
    there while recon and calibrate filters read it."""
    import scipy.io

    cube = _cube()
    scipy.io.savemat(pair / "hwk.mat", {"mask": np.moveaxis(cube, 0, -1)})
    np.save(pair / "khw.npy", cube)
    outs = {}
    for name in ("hwk.mat", "khw.npy"):
        code, _, err = run_cli(capsys, "simulate", "--model", "spectral", "--psf",
                               pair / "psf.npy", "--scene", pair / "scene.npy", "--filters",
                               pair / name, "--out", pair / f"sim_{name[:3]}")
        assert code == 0, err
        outs[name] = np.load(pair / f"sim_{name[:3]}" / "meas.npy")
    np.testing.assert_allclose(outs["hwk.mat"], outs["khw.npy"], rtol=1e-6)


def test_recon_admm_lists_and_takes_the_2d_model_only(pair, capsys):
    """Its help listed video, spectral and depth and their inputs, which it then refused."""
    from app.cli import build_parser

    sub = build_parser()._subparsers._group_actions[0].choices["recon"]
    admm = sub._subparsers._group_actions[0].choices["admm"]
    text = admm.format_help()
    for word in ("{2d,video,spectral,depth}", "--shutter", "--filters", "--psf-stack",
                 "PSF file (2d, video, spectral)"):
        assert word not in text, word
    assert "--model 2d" in text
    for model in ("video", "spectral", "depth"):
        with pytest.raises(SystemExit) as exc:  # argparse's refusal (exit 2)
            run_cli(capsys, "recon", "admm", "--model", model, "--meas", pair / "meas.npy",
                    "--psf", pair / "psf.npy", "--out", pair / "a.tif")
        line = _one_line_error(int(exc.value.code), capsys.readouterr().err)
        assert f"handles the 2d model only, not {model}; use recon fista" in line
    assert not (pair / "a.tif").exists()
