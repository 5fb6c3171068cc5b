"""Plan requests that cost GBs for nothing are bounded or refused (hostile-user review).

- ``--set field=[H,W]`` (plan / recon auto) far past the light's reach was accepted: a
  1500x1500 field on a 48x64 sensor took 57 s and 640 MB to plan. It now follows the one
  rule of ``--field`` (:func:`recon.checks.check_field`: at most sensor + PSF extent).
- ``plan --timing`` with a long exposure built one-line shutter bins: rows 1000, exposure
  100000 lines made a (100499, 1000) float64 shutter, 1.6 GB traced in ``base_shutter`` alone
  (1.9 GB peak RSS for ``plan``). The bins are now merged to at most
  ``MAX_SHUTTER_ELEMENTS`` values; normal timings keep one-line bins.
"""

from __future__ import annotations

import json
import tracemalloc

import numpy as np
import pytest

from drivers.timing import SensorTiming
from recon.plan import Plan, make_plan
from recon.plan.planner import MAX_SHUTTER_ELEMENTS, base_bin_lines, base_shutter
from recon.preprocess import bin_time
from tests.clirun import run_cli as _run

H, W = 48, 64


def _plan(**kw):
    base = {"model": "2d", "k": 1, "sensor": (H, W), "field": (H, W),
            "region": (0, 0, H, W), "downsample": 1, "method": "fista-tv",
            "iterations": 300, "base_bins": 36, "reasons": {"model": "because"}}
    base.update(kw)
    return Plan(**base)


# ------------------------------------------------------------------------------------------
# the scene field: one rule for --field, --set field=..., a saved plan and make_plan
# ------------------------------------------------------------------------------------------

LIMIT = r"larger than the 96x128 from which light reaches the 48x64 sensor"


def test_override_refuses_a_field_past_the_lights_reach():
    p = _plan()
    assert p.override(field=(2 * H, 2 * W)).field == (96, 128)  # the full field: accepted
    for bad in ((2 * H + 1, 2 * W), (H, 2 * W + 1), (1500, 1500)):
        with pytest.raises(ValueError, match=rf"plan field 'field' {bad[0]}x{bad[1]} is {LIMIT}"):
            p.override(field=list(bad))


def test_a_saved_plan_with_a_field_past_the_reach_is_refused():
    d = json.loads(json.dumps(_plan().to_json()))
    d.update(field=[1500, 1500], region=[0, 0, 1500, 1500])
    with pytest.raises(ValueError, match=LIMIT):
        Plan.from_json(d)


def test_make_plan_refuses_the_field_before_the_analysis(static_cap, monkeypatch):
    import recon.plan.planner as planner

    def analysis(*_a, **_k):
        raise AssertionError("the analysis ran on a field no light leaves")

    monkeypatch.setattr(planner, "psf_resolution", analysis)
    with pytest.raises(ValueError, match=LIMIT):
        make_plan(static_cap.psf, static_cap.meas, field=(1500, 1500), probe=False)




@pytest.fixture
def pair(tmp_path):
    rng = np.random.default_rng(0)
    np.save(tmp_path / "psf.npy", rng.random((H, W)).astype(np.float32))
    np.save(tmp_path / "meas.npy", rng.random((H, W)).astype(np.float32))
    return ["--psf", tmp_path / "psf.npy", "--meas", tmp_path / "meas.npy", "--tau", "1e-3"]


@pytest.fixture
def no_planning(monkeypatch):
    import recon.plan

    def planning(*_a, **_k):
        raise AssertionError("planning started on a field no light leaves")

    monkeypatch.setattr(recon.plan, "make_plan", planning)


@pytest.mark.parametrize("command", [["plan", "--no-probe"], ["recon", "auto"]])
def test_set_field_and_field_share_one_rule_and_fail_before_planning(pair, tmp_path, capsys,
                                                                     no_planning, command):
    argv = [*command, *pair]
    if command[0] == "recon":
        argv += ["--out", tmp_path / "x.tif"]
    code, _, err = _run(capsys, *argv, "--set", "field=[1500,1500]")
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "plan field 'field' 1500x1500 is larger than the 96x128" in err
    code, _, err = _run(capsys, *argv, "--field", "1500x1500")
    assert code == 2 and "scene field 1500x1500 is larger than the 96x128" in err
    assert not (tmp_path / "x.tif").exists()


def test_padded_psf_reach_is_the_real_sensors(tmp_path, capsys, no_planning):
    """A PSF on the padded grid (twice the sensor): the plan's grid is the padded one, the
    light reaches the 24x32 sensor from 24+48 x 32+64 = 72x96, as --field says."""
    rng = np.random.default_rng(1)
    np.save(tmp_path / "psf.npy", rng.random((48, 64)).astype(np.float32))
    np.save(tmp_path / "meas.npy", rng.random((24, 32)).astype(np.float32))
    argv = ["plan", "--no-probe", "--tau", "1e-3", "--psf", tmp_path / "psf.npy", "--meas",
            tmp_path / "meas.npy"]
    for opt in (["--set", "field=[73,96]"], ["--field", "73x96"]):
        code, _, err = _run(capsys, *argv, *opt)
        assert code == 2 and "73x96 is larger than the 72x96 from which light reaches the " \
                              "24x32 sensor through its 48x64 PSF" in err, err


def test_recon_auto_refuses_a_saved_plan_past_the_reach(pair, tmp_path, capsys):
    d = json.loads(json.dumps(_plan().to_json()))
    (tmp_path / "plan.json").write_text(json.dumps(d))
    code, _, err = _run(capsys, "recon", "auto", *pair[:4], "--plan", tmp_path / "plan.json",
                        "--set", "field=[97,128]", "--out", tmp_path / "x.tif")
    assert code == 2 and "plan field 'field' 97x128 is larger than the 96x128" in err, err
    assert not (tmp_path / "x.tif").exists()


# ------------------------------------------------------------------------------------------
# the shutter of a long exposure: bounded memory
# ------------------------------------------------------------------------------------------


def test_long_exposure_shutter_is_built_in_bounded_memory():
    t = SensorTiming(rows=1000, line_time_us=10.0, exposure_lines=100_000, pattern="outside-in")
    tracemalloc.start()
    try:
        m, note = base_shutter(None, t, 1000)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert m is not None and m.size <= MAX_SHUTTER_ELEMENTS
    # one-line bins: 100499 x 1000 float64 = 804 MB, 1.6 GB traced while building
    assert peak < 3 * 8 * MAX_SHUTTER_ELEMENTS, f"{peak / 1e6:.0f} MB"  # float64, < 3 copies
    width = base_bin_lines(t.frame_lines, t.rows)
    assert width == -(-t.frame_lines // (MAX_SHUTTER_ELEMENTS // 1000)) == 6
    assert m.shape == (-(-t.frame_lines // width), 1000)
    assert "bins of 6 lines" in note and "100499 one-line bins merged" in note
    # every row still integrates its whole exposure (in bins of `width` lines)
    np.testing.assert_allclose(m.sum(axis=0), t.exposure_lines / width, rtol=1e-12)


def test_merged_bins_are_the_mean_of_the_one_line_bins():
    t = SensorTiming(rows=300, line_time_us=1.0, exposure_lines=80_000, pattern="centre-out")
    m, _ = base_shutter(None, t, 300)
    width = base_bin_lines(t.frame_lines, t.rows)
    assert width == 2 and m is not None
    np.testing.assert_allclose(m, bin_time(t.shutter(1), width), rtol=0, atol=1e-12)


@pytest.mark.parametrize(("rows", "exposure", "pattern"),
                         [(48, 13, "top-down"), (12, 4, "outside-in"), (1000, 300, "top-down"),
                          (2048, 1000, "outside-in"), (2048, 2000, "top-down"),
                          (1944, 500, "top-down"), (2048, 2000, "outside-in")])
def test_normal_timings_keep_one_line_bins(rows, exposure, pattern):
    t = SensorTiming(rows=rows, line_time_us=10.0, exposure_lines=exposure, pattern=pattern)
    assert base_bin_lines(t.frame_lines, t.rows) == 1
    if rows <= 48:
        m, note = base_shutter(None, t, rows)
        np.testing.assert_array_equal(m, t.shutter(1))
        assert note.endswith(f"{t.frame_lines} one-line bins")


def test_plan_with_a_long_exposure_timing(static_cap):
    """The planner runs on the merged bins and records them (base_bins = K0)."""
    cap = static_cap
    t = SensorTiming(rows=H, line_time_us=10.0, exposure_lines=200_000, pattern="outside-in")
    plan = make_plan(cap.psf, cap.meas, timing=t, probe=False)
    width = base_bin_lines(t.frame_lines, H)
    assert width == 1 and plan.base_bins == t.frame_lines  # 48 rows: 349 525 one-line bins fit
    assert plan.base_bins * H <= MAX_SHUTTER_ELEMENTS


def test_a_saved_plan_keeps_its_bins_whatever_the_cap(static_cap, monkeypatch):
    """A plan records its base bins; executing it builds the timing's bins that wide, not
    what base_bin_lines would choose now (a smaller cap, or an older plan of one-line bins)."""
    from recon.plan import planner
    from recon.plan.planner import prepare

    cap = static_cap
    t = SensorTiming(rows=H, line_time_us=10.0, exposure_lines=2000, pattern="outside-in")
    plan = make_plan(cap.psf, cap.meas, timing=t, probe=False).override(model="video", k=4)
    assert plan.base_bins == t.frame_lines
    monkeypatch.setattr(planner, "MAX_SHUTTER_ELEMENTS", 16 * H)  # now: bins of 130 lines
    assert base_bin_lines(t.frame_lines, H) > 1
    prep = prepare(plan, cap.psf, cap.meas, timing=t)
    assert prep.model.k == plan.k == 4


def test_a_video_plan_keeps_a_row_per_frame(moving_cap, monkeypatch):
    """The time analysis may find more frames than the resolution's grid has rows (36 frames,
    3 px per sample on 48 rows: 16): the plan lowers the downsampling, as recon fista refuses
    K > rows, and the budget's raise stops there too (it made K = 36 on 16 rows)."""
    import dataclasses

    import recon.plan.planner as planner

    real_ts, real_res = planner.time_scale, planner.psf_resolution
    monkeypatch.setattr(planner, "time_scale", lambda *a, **kw: dataclasses.replace(
        real_ts(*a, **kw), k=36, factor=1, motion=True))
    monkeypatch.setattr(planner, "psf_resolution", lambda *a, **kw: dataclasses.replace(
        real_res(*a, **kw), factor=3))
    cap = moving_cap
    for budget, probe in ((30.0, False), (0.01, True)):
        plan = planner.make_plan(cap.psf, cap.meas, timing=cap.timing, budget_s=budget,
                                 probe=probe)
        assert (plan.model, plan.k, plan.downsample) == ("video", 36, 1)
        assert "lowered from 3 to 1 so the 48 rows resolve the K = 36 frames" in (
            plan.reasons["downsample"])
