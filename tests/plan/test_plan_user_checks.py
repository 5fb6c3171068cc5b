"""What ``plan`` / ``recon auto`` say about the user's own settings and a saved plan.

- a region (or field) set by the user that holds little of the scene's energy is warned about
  (the plan's reasons, and one line on stderr): it gave a poor result silently;
- the automatic tau's search is reported (``tau_search_s``, the tau reason), not hidden
  behind ``plan_s`` and a budget that covers the reconstruction only;
- a saved plan made for another measurement names the real sizes (a padded grid's sensor),
  before the plan's own checks speak of a sensor that is not this one;
- ``--tau`` equal to the default is "given"; an empty region is printed as given; a negative
  iteration count of a fista-tv plan says ">= 1" as 0 does.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from app.cli import main
from recon.plan import make_plan
from recon.plan.planner import prepare
from tests.clirun import run_cli as _run


@pytest.fixture()
def files(tmp_path, static_cap):
    np.save(tmp_path / "psf.npy", static_cap.psf)
    np.save(tmp_path / "meas.npy", static_cap.meas)
    return tmp_path


def _inputs(d, meas="meas.npy", psf="psf.npy"):
    return ["--psf", d / psf, "--meas", d / meas]


# -- 3: a user's region or field far smaller than the scene --------------------------------


def test_a_small_user_region_is_warned_about_and_a_fitting_one_is_not(static_cap):
    from recon.plan.planner import region_energy_warning

    cap = static_cap  # a still scene filling the 48x64 field
    plan = make_plan(cap.psf, cap.meas, probe=False)
    assert "energy_map" in plan.evidence["extent"]
    small = plan.override(region=[0, 0, 12, 16])
    assert "warning: region 12x16 at (0, 0) of the 48x64 field holds" in small.reasons["region"]
    assert region_energy_warning(small) is not None
    assert "\n" not in small.reasons["region"]
    # a field set by the user (the region follows it) is checked the same way
    tiny = plan.override(field=[8, 8])
    assert "warning: the 8x8 field holds" in tiny.reasons["region"]
    # most of the field: silent
    big = plan.override(region=[2, 2, 44, 60])
    assert "warning" not in big.reasons["region"] and region_energy_warning(big) is None
    # the plan's own choice is never warned about
    assert region_energy_warning(plan) is None


def test_the_region_warning_measures_the_energy_the_plan_found(object_cap):
    """The object case: a small object off-centre in the 2x field. Its own region is silent,
    the same size elsewhere is warned about with the share it holds."""
    from recon.plan.planner import REGION_ENERGY_WARN, region_energy_warning

    cap, (top, left, oh, ow) = object_cap
    plan = make_plan(cap.psf, cap.meas, field=(96, 128), probe=False)
    assert plan.evidence["extent"]["cropped"]
    on = plan.override(region=[max(top - 4, 0), max(left - 4, 0), oh + 8, ow + 8])
    assert region_energy_warning(on) is None
    off = plan.override(region=[0, 0, oh + 8, ow + 8])  # the opposite corner
    text = region_energy_warning(off)
    assert text is not None and f"threshold {100 * REGION_ENERGY_WARN:.0f}%" in text
    share = int(text.split(" holds ")[1].split("%")[0])
    assert share < 30


def test_plan_and_recon_auto_print_the_region_warning(files, capsys):
    code, out, err = _run(capsys, "plan", *_inputs(files), "--tau", "1e-3", "--no-probe",
                          "--set", "region=[0,0,12,16]")
    assert code == 0, err
    lines = [line for line in err.splitlines() if "warning" in line]
    assert len(lines) == 1 and lines[0].startswith("lenslesscam plan: warning: region 12x16")
    assert "warning: region 12x16" in out  # in the region's reason too
    # recon auto --quiet still says it, and so does a saved plan run with a region set
    plan_file = files / "plan.json"
    assert main(["plan", *map(str, _inputs(files)), "--tau", "1e-3", "--no-probe", "--out",
                 str(plan_file)]) == 0
    capsys.readouterr()
    code, _, err = _run(capsys, "recon", "auto", *_inputs(files), "--plan", plan_file,
                        "--set", "region=[0,0,12,16]", "--set", "iterations=5", "--quiet",
                        "--out", files / "r.tif")
    assert code == 0, err
    assert "lenslesscam recon: warning: region 12x16 at (0, 0)" in err
    code, _, err = _run(capsys, "recon", "auto", *_inputs(files), "--plan", plan_file,
                        "--set", "iterations=5", "--quiet", "--out", files / "s.tif")
    assert code == 0, err
    assert "warning" not in err


# -- 4: the automatic tau's search is reported --------------------------------------------


def test_recon_auto_reports_the_tau_search_apart_from_plan_s_and_the_budget(files, capsys):
    code, out, err = _run(capsys, "recon", "auto", *_inputs(files), "--budget", "30s",
                          "--out", files / "a.tif")
    assert code == 0, err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["tau_search_s"] > 0
    assert "the search took" in err and ("not counted in plan_s nor in the 30 s budget, which "
                                         "covers the reconstruction only") in err
    from recon.io import read_reconstruction

    plan = read_reconstruction(files / "a.tif")[1]["plan"]
    assert plan["evidence"]["tau_search"]["seconds"] == summary["tau_search_s"]
    # a given tau: no search
    code, out, err = _run(capsys, "recon", "auto", *_inputs(files), "--tau", "1e-3",
                          "--set", "iterations=5", "--quiet", "--out", files / "b.tif")
    assert code == 0, err
    assert json.loads(out.strip().splitlines()[-1])["tau_search_s"] is None


# -- 5: a saved plan for another measurement ----------------------------------------------


def test_a_plan_for_another_measurement_names_the_real_sizes(files, static_cap, capsys):
    plan_file = files / "plan.json"
    assert main(["plan", *map(str, _inputs(files)), "--tau", "1e-3", "--no-probe", "--out",
                 str(plan_file)]) == 0
    capsys.readouterr()
    # a 30x40 measurement with a PSF on its 60x80 padded grid, run with the 48x64 plan (it
    # said "the plan is for a (48, 64) sensor, the measurement is (60, 80)", after printing
    # the plan)
    np.save(files / "small.npy", static_cap.meas[9:39, 12:52])
    np.save(files / "padded.npy", np.pad(static_cap.psf, ((6, 6), (8, 8))))
    small = _inputs(files, meas="small.npy", psf="padded.npy")
    code, out, err = _run(capsys, "recon", "auto", *small, "--plan", plan_file,
                          "--out", files / "r.tif")
    assert code == 2 and out == ""
    assert err.strip() == (
        f"lenslesscam recon: error: plan file {plan_file} is for a 48x64 measurement; this "
        "is a 30x40 measurement (on a 60x80 padded PSF grid): the plan does not fit it; "
        "make a plan for this measurement (lenslesscam plan ... --out)")
    # the same grid is not enough: a 24x32 measurement on the 48x64 padded grid is another
    # sensor (and field) than the 48x64 measurement the plan was made for
    np.save(files / "quarter.npy", static_cap.meas[12:36, 16:48])
    code, _, err = _run(capsys, "recon", "auto", *_inputs(files, meas="quarter.npy"),
                        "--plan", plan_file, "--out", files / "r.tif")
    assert code == 2
    assert ("is for a 48x64 measurement; this is a 24x32 measurement (on a 48x64 padded PSF "
            "grid)") in err
    # and a plan made for that padded measurement runs on it (measurement_window agrees)
    padded_plan = files / "padded_plan.json"
    assert main(["plan", *map(str, _inputs(files, meas="quarter.npy")), "--tau", "1e-3",
                 "--no-probe", "--out", str(padded_plan)]) == 0
    code, _, err = _run(capsys, "recon", "auto", *_inputs(files, meas="quarter.npy"),
                        "--plan", padded_plan, "--set", "iterations=3", "--quiet",
                        "--out", files / "q.tif")
    assert code == 0, err
    # a plan from Python (Plan.to_json: no window, no inputs) is checked on its grid only
    bare = json.loads(padded_plan.read_text())
    for key in ("measurement_window", "inputs", "created_utc"):
        bare.pop(key, None)
    (files / "bare.json").write_text(json.dumps(bare))
    code, _, err = _run(capsys, "recon", "auto", *_inputs(files, meas="quarter.npy"),
                        "--plan", files / "bare.json", "--set", "iterations=3", "--quiet",
                        "--out", files / "b.tif")
    assert code == 0, err
    # a plan whose sensor was edited: the mismatch first, not its own field check
    saved = json.loads(plan_file.read_text())
    saved["sensor"] = [10, 10]
    plan_file.write_text(json.dumps(saved))
    code, _, err = _run(capsys, "recon", "auto", *_inputs(files), "--plan", plan_file,
                        "--out", files / "r.tif")
    assert code == 2
    assert f"plan file {plan_file} is for a 10x10 measurement; this is a 48x64" in err
    assert "through its" not in err and err.count("plan file") == 1


def test_prepare_names_both_grids(static_cap):
    cap = static_cap
    plan = make_plan(cap.psf, cap.meas, probe=False)
    with pytest.raises(ValueError, match=r"^the plan is for a 48x64 measurement grid \(its "
                       r"'sensor'\), this measurement's grid is 40x64"):
        prepare(plan, cap.psf[:40], cap.meas[:40])


# -- 6: small things said wrong -----------------------------------------------------------


def test_a_given_tau_equal_to_the_default_is_given(files, capsys, static_cap):
    code, out, err = _run(capsys, "plan", *_inputs(files), "--tau", "0.001", "--no-probe",
                          "--json")
    assert code == 0, err
    assert json.loads(out)["reasons"]["tau"] == "given"
    cap = static_cap
    assert "default" in make_plan(cap.psf, cap.meas, probe=False).reasons["tau"]
    assert make_plan(cap.psf, cap.meas, tau=1e-3, probe=False).reasons["tau"] == "given"


def test_an_empty_region_is_printed_as_given(files, capsys):
    code, _, err = _run(capsys, "plan", *_inputs(files), "--tau", "1e-3", "--no-probe",
                        "--set", "region=[0,0,0,0]")
    assert code == 2
    assert "region' [0, 0, 0, 0] (top, left, height, width) has an empty size" in err
    assert "48, 64" not in err


def test_negative_iterations_say_the_fista_rule(static_cap):
    plan = make_plan(static_cap.psf, static_cap.meas, probe=False)
    for bad in (-5, 0):
        with pytest.raises(ValueError, match=">= 1 for fista-tv"):
            plan.override(iterations=bad)
    with pytest.raises(ValueError, match=r"'iterations' must be >= 0, got -5"):
        plan.override(method="udn", iterations=-5)
    assert plan.override(method="udn", iterations=0).iterations == 0
