"""``lenslesscam plan``, ``recon auto`` (through register_auto) and ``bench plan``."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from app.cli import build_parser, main
from app.commands.plan import parse_budget, parse_overrides, register_auto


@pytest.fixture()
def files(tmp_path, moving_cap):
    cap = moving_cap
    np.save(tmp_path / "psf.npy", cap.psf)
    np.save(tmp_path / "meas.npy", cap.meas)
    (tmp_path / "timing.json").write_text(json.dumps({"timing": cap.timing.to_dict()}))
    return tmp_path


def _inputs(d):
    return ["--psf", str(d / "psf.npy"), "--meas", str(d / "meas.npy"),
            "--timing", str(d / "timing.json")]


def test_plan_prints_reasons_and_json(files, capsys):
    assert main(["plan", *_inputs(files), "--no-probe"]) == 0
    text = capsys.readouterr().out
    assert "model      video" in text and "why:" in text
    out = files / "plan.json"
    assert main(["plan", *_inputs(files), "--json", "--budget", "30s", "--out", str(out),
                 "--set", "iterations=40"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["model"] == "video" and d["iterations"] == 40 and d["budget_s"] == 30.0
    saved = json.loads(out.read_text())
    # the saved plan also records which measurement and PSF it is for (recon.suggest)
    assert set(saved.pop("inputs")) == {"measurement", "psf"} and saved.pop("created_utc")
    assert "iterations" in d["overridden"] and saved == d
    # the reason names the values tried, not the search range's ends ('from 1e-07' when the
    # first value tried was 1e-06)
    search = d["evidence"]["tau_search"]
    tried, (lo, hi) = search["taus_tried"], search["tau_range"]
    assert len(tried) == search["values_tried"]
    assert lo * (1 - 1e-6) <= min(tried) <= max(tried) <= hi * (1 + 1e-6)  # float rounding
    assert f"tried from {min(tried):.3g} to {max(tried):.3g} within" in d["reasons"]["tau"]


def test_recon_auto_runs_a_saved_plan_with_overrides(files, capsys):
    parser = argparse.ArgumentParser()
    register_auto(parser.add_subparsers())
    plan_file = files / "plan.json"
    assert main(["plan", *_inputs(files), "--no-probe", "--out", str(plan_file)]) == 0
    capsys.readouterr()
    out = files / "rec.tif"
    args = parser.parse_args(["auto", *_inputs(files), "--plan", str(plan_file), "--set",
                              "model=2d", "--set", "iterations=20", "--out", str(out),
                              "--quiet"])
    assert args.func(args) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["model"] == "2d" and summary["iterations"] <= 20 and out.exists()
    from recon.io import read_reconstruction

    x, meta = read_reconstruction(out)
    assert x.shape == (1, 1, 48, 64) and meta["plan"]["overridden"] == ["model", "iterations"]


def test_a_saved_plan_of_other_data_is_said_and_recorded(files, capsys):
    """A plan made on another measurement of the same size ran without a word, and the
    result's metadata (tau "chosen from held-out measured pixels") did not say whose."""
    import numpy as np

    from recon.io import read_reconstruction

    plan_file = files / "plan.json"
    assert main(["plan", *_inputs(files), "--no-probe", "--out", str(plan_file)]) == 0
    capsys.readouterr()
    meas = np.load(files / "meas.npy")
    np.save(files / "other.npy", np.roll(meas, 5, axis=-1))  # another scene, the same size
    out = files / "other.tif"
    argv = ["recon", "auto", "--psf", str(files / "psf.npy"), "--timing",
            str(files / "timing.json"), "--plan", str(plan_file), "--set", "iterations=5",
            "--quiet"]
    assert main([*argv, "--meas", str(files / "other.npy"), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "was made on another measurement (hashes differ)" in err, err
    assert len([line for line in err.splitlines() if "plan file" in line]) == 1
    got = read_reconstruction(out)[1]["plan_inputs"]
    assert got["match"] is False and got["recorded"]["psf"] == got["this"]["psf"]
    empty = json.loads(plan_file.read_text())
    empty["inputs"] = {}  # records nothing: not "made on another measurement and PSF"
    (files / "empty.json").write_text(json.dumps(empty))
    assert main([*argv[:7], str(files / "empty.json"), *argv[8:], "--meas",
                 str(files / "other.npy"), "--out", str(files / "e.tif")]) == 0
    assert "hashes differ" not in capsys.readouterr().err
    assert "plan_inputs" not in read_reconstruction(files / "e.tif")[1]
    same = files / "same.tif"
    assert main([*argv, "--meas", str(files / "meas.npy"), "--out", str(same)]) == 0
    assert "hashes differ" not in capsys.readouterr().err
    assert read_reconstruction(same)[1]["plan_inputs"]["match"] is True


def test_a_udn_plan_that_spent_its_budget_setting_up_says_so(capsys):
    """A 1 s budget ran 1 of the plan's 500 UDN iterations and saved the result without a
    word."""
    from types import SimpleNamespace

    from app.commands.plan import warn_udn_budget_spent

    plan = SimpleNamespace(method="udn", iterations=500, budget_s=1.0)
    warn_udn_budget_spent(plan, SimpleNamespace(stop_reason="time_limit", iterations=1))
    err = capsys.readouterr().err
    assert "the UDN ran only 1 of the plan's 500 iterations within the 1 s budget" in err
    for res in (SimpleNamespace(stop_reason="time_limit", iterations=50),
                SimpleNamespace(stop_reason="max_iter", iterations=1)):
        warn_udn_budget_spent(plan, res)
    warn_udn_budget_spent(SimpleNamespace(method="fista-tv", iterations=500, budget_s=1.0),
                          SimpleNamespace(stop_reason="time_limit", iterations=1))
    assert capsys.readouterr().err == ""


def test_bad_inputs_are_one_line_errors(files, capsys):
    assert main(["plan", *_inputs(files), "--budget", "soon"]) == 2
    assert "time budget" in capsys.readouterr().err
    assert main(["plan", *_inputs(files), "--budget", "-5s"]) == 2  # "expected one argument"
    assert "the time budget must be positive, got '-5s'" in capsys.readouterr().err
    assert main(["plan", "--meas", str(files / "meas.npy")]) == 2
    assert "--psf" in capsys.readouterr().err
    assert main(["plan", *_inputs(files), "--no-probe", "--set", "k"]) == 2
    assert "KEY=VALUE" in capsys.readouterr().err


def test_parsers():
    assert parse_budget("90") == 90.0 and parse_budget("2min") == 120.0
    assert parse_budget("1.5h") == 5400.0 and parse_budget("250ms") == 0.25
    assert parse_budget(None) is None
    assert parse_overrides(["k=4", "model=video", "region=[1,2,3,4]"]) == {
        "k": 4, "model": "video", "region": [1, 2, 3, 4]}


def test_bench_plan_is_registered():
    args = build_parser().parse_args(["bench", "plan", "--size", "48x64", "--markdown"])
    assert args.size == (48, 64) and args.markdown and callable(args.func)


def test_plan_names_the_measurement_not_the_padded_psf_grid(tmp_path, capsys):
    """A measurement embedded in a padded PSF grid (the dataset layout): the plan says the
    measurement's size and the grid it runs on (it used to call the grid the measurement)."""
    from tests.scenes import dataset_layout_pair

    dataset_layout_pair(tmp_path)
    argv = ["plan", "--psf", str(tmp_path / "psf.npy"), "--meas", str(tmp_path / "meas.npy"),
            "--rgb", "--channel-order", "bgr", "--flip-rows", "--no-probe"]
    assert main(argv) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert "for a 24x32 measurement in a 48x64 padded PSF grid (3 channels)" in first
    assert main([*argv, "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["measurement_window"] == [24, 32] and d["sensor"] == [48, 64]
    assert main([*argv, "--out", str(tmp_path / "plan.json")]) == 0
    capsys.readouterr()
    assert json.loads((tmp_path / "plan.json").read_text())["measurement_window"] == [24, 32]


def test_inputs_that_would_be_ignored_are_refused(files, capsys):
    """--psf beside --psf-stack, or a shutter for a depth plan, were ignored yet recorded as
    the result's inputs."""
    base = ["--meas", str(files / "meas.npy"), "--no-probe"]
    assert main(["plan", "--psf", str(files / "psf.npy"), "--psf-stack",
                 str(files / "psf.npy"), *base]) == 2
    assert "give --psf or --psf-stack, not both" in capsys.readouterr().err
    np.save(files / "sh.npy", np.ones((2, 4)))
    assert main(["plan", "--psf-stack", str(files / "psf.npy"), "--shutter",
                 str(files / "sh.npy"), *base]) == 2
    assert "takes no --shutter or --timing" in capsys.readouterr().err


def test_timing_from_a_saved_frame_and_a_wrong_timing_file(tmp_path, capsys):
    """docs/plan.md allows a frame's metadata as --timing; a TIFF gave 'utf-8 codec can't
    decode' without the file's name."""
    frame = tmp_path / "f.tif"
    assert main(["snap", "--camera", "sim", "--out", str(frame)]) == 0
    from recon.simulate import synthetic_psf

    np.save(tmp_path / "psf.npy", synthetic_psf((64, 80), seed=0))
    base = ["plan", "--psf", str(tmp_path / "psf.npy"), "--meas", str(frame), "--dark", "100",
            "--psf-dark", "0",
            "--no-probe", "--json"]
    assert main([*base, "--timing", str(frame)]) == 0
    capsys.readouterr()
    assert main([*base, "--timing", str(tmp_path / "psf.npy")]) == 2
    assert "psf.npy: not a JSON timing file or a saved frame" in capsys.readouterr().err


def test_a_measurement_too_small_to_plan_says_so(tmp_path, capsys):
    """A 1x32 measurement failed in plan and recon auto with 'downsampling 1x32 by 1 leaves
    too few pixels' (a plan's own check, no word of the input); recon fista handles it."""
    rng = np.random.default_rng(0)
    np.save(tmp_path / "p.npy", rng.random((1, 32)).astype(np.float32))
    np.save(tmp_path / "m.npy", rng.random((1, 32)).astype(np.float32))
    files = ["--psf", str(tmp_path / "p.npy"), "--meas", str(tmp_path / "m.npy")]
    for argv in (["plan", *files, "--no-probe"],
                 ["recon", "auto", *files, "--out", str(tmp_path / "a.tif")]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "a 1x32 measurement is too small to plan" in err and "recon fista" in err, err
        assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "a.tif").exists()


def test_psf_dark_help_names_only_values_it_accepts():
    """The help said "none for a calibrated PSF file": "none" is not a value --psf-dark takes
    (a number, 'auto' or a dark-frame file); a calibrated PSF file wants it left out, or 0."""
    parser = argparse.ArgumentParser()
    p = parser.add_subparsers().add_parser("plan")
    from app.commands.plan import add_plan_inputs

    add_plan_inputs(p)
    (action,) = [a for a in p._actions if "--psf-dark" in a.option_strings]
    assert action.help == (
        "dark level of the PSF: a number, 'auto' or a dark-frame file (default: the --dark "
        "level; leave it out for a calibrated PSF file, which is dark-subtracted already, "
        "or give 0)")
    assert "none" not in action.help
