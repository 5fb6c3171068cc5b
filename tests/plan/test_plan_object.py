"""The Plan object (JSON, overrides, description), the budget rule, the cost cache, depth."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from benchmarks.plan_cases import background
from recon.models import build_model
from recon.plan import PLAN_FORMAT, Plan, execute, make_plan
from recon.plan.cost import (
    DEFAULT_ITERS,
    MAX_ITERS,
    UDN_MIN_BUDGET_CPU_S,
    CostEstimate,
    cache_path,
    iteration_cost,
    method_for_budget,
)
from recon.simulate import simulate, synthetic_psf


def _plan(**kw):
    base = {"model": "2d", "k": 1, "sensor": (48, 64), "field": (48, 64),
            "region": (0, 0, 48, 64), "downsample": 1, "method": "fista-tv",
            "iterations": 300, "base_bins": 36, "reasons": {"model": "because"}}
    base.update(kw)
    return Plan(**base)


def test_json_round_trip_keeps_every_field(static_cap):
    cap = static_cap
    plan = make_plan(cap.psf, cap.meas, timing=cap.timing, budget_s=30.0)
    d = json.loads(json.dumps(plan.to_json()))
    assert d["format"] == PLAN_FORMAT and d["format_version"] == 1
    back = Plan.from_json(d)
    assert back == plan
    assert plan.seconds_per_iter is not None and plan.estimated_s is not None
    assert plan.evidence["cost"]["source"] in ("probe", "cache")
    with pytest.raises(ValueError, match="not a plan"):
        Plan.from_json({"format": "something else"})
    with pytest.raises(ValueError, match="newer"):
        Plan.from_json({**d, "format_version": 99})


def test_a_plan_with_udn_settings_keeps_them_and_is_version_2(monkeypatch):
    """A plan's UDN settings (from a trade row) survive its JSON; such a plan is format
    version 2, so a release that reads only version 1 (and would run its default network)
    refuses it; a plan without them stays version 1."""
    import recon.plan.planner as planner

    udn = {"network": {"scales": 2, "channels": 4}, "config": {"lr": 0.02, "holdout": 0.0}}
    plan = _plan(method="udn", iterations=0, udn=udn)
    d = json.loads(json.dumps(plan.to_json()))
    assert d["format_version"] == 2 and d["udn"] == udn
    assert Plan.from_json(d) == plan
    assert "network scales 2, channels 4, lr 0.02, holdout 0.0" in plan.describe()
    assert _plan().to_json()["format_version"] == 1
    with pytest.raises(ValueError, match=r"plan\.udn must be an object with a 'network'"):
        _plan(udn={"network": [4]})
    monkeypatch.setattr(planner, "PLAN_VERSION", 1)
    with pytest.raises(ValueError, match="plan format version 2 is newer than this software"):
        Plan.from_json(d)


def test_describe_gives_a_reason_for_each_choice(static_cap):
    cap = static_cap
    text = make_plan(cap.psf, cap.meas, timing=cap.timing).describe()
    for word in ("model", "K", "region", "downsample", "method", "tau", "why:",
                 "held-out", "autocorrelation", "FISTA-TV"):
        assert word in text


def test_overrides_follow_related_fields_and_say_so():
    p = _plan()
    v = p.override(model="video", k=8)
    assert (v.model, v.bin_factor, v.k) == ("video", 5, 8)  # ceil(36 / 8) = 5 -> 8 frames
    assert v.overridden == ("model", "k") and "set by the user" in v.reasons["k"]
    assert v.seconds_per_iter is None  # the size changed: the cost estimate is dropped
    # the same model with another count: the estimate follows it (it kept the old count's)
    timed = dataclasses.replace(p, seconds_per_iter=0.002, estimated_s=(300 + 25) * 0.002)
    assert timed.override(iterations=100).estimated_s == pytest.approx((100 + 25) * 0.002)
    seven = p.override(model="video", k=7)  # ceil(36 / 7) = 6 -> 6 frames: the reason says why
    assert seven.k == 6 and "7 requested" in seven.reasons["k"]
    assert "36 shutter bins in groups of 6 make 6 frames" in seven.reasons["k"]
    back = v.override(model="2d")
    assert (back.k, back.bin_factor) == (1, None)
    r = p.override(region=(4, 6, 20, 30))
    assert r.region == (4, 6, 20, 30) and r.override(region="whole").region_obj.is_whole
    f = p.override(field=(96, 128))
    assert f.region == (0, 0, 96, 128)
    with pytest.raises(ValueError, match="cannot override"):
        p.override(colour="blue")
    with pytest.raises(ValueError, match="outside"):
        p.override(region=(40, 0, 20, 10))
    with pytest.raises(ValueError, match="shutter"):
        _plan(base_bins=None).override(model="video")
    with pytest.raises(ValueError, match="k = 1"):
        _plan(k=2)
    with pytest.raises(ValueError, match="method"):
        _plan(method="magic")


def test_budget_rule():
    cost = CostEstimate(0.01, "probe", "key")
    assert method_for_budget(cost, None).iterations == DEFAULT_ITERS
    c = method_for_budget(cost, 2.0)  # 200 - 25 setup iterations
    assert c.method == "fista-tv" and c.iterations == 175 and c.affordable
    assert method_for_budget(cost, 1000.0, gpu=False).iterations == MAX_ITERS
    tight = method_for_budget(cost, 0.5)
    assert not tight.affordable and "under-converged" in tight.reason
    # the UDN only for long budgets (and only when recon.udn imports)
    assert method_for_budget(cost, 3600.0, gpu=False).method == "fista-tv"
    assert method_for_budget(cost, UDN_MIN_BUDGET_CPU_S, gpu=False).method == "udn"
    assert method_for_budget(cost, 1800.0, gpu=True).method == "udn"
    with pytest.raises(ValueError, match="positive"):
        method_for_budget(cost, -1.0)


def test_cost_is_measured_once_then_cached(tmp_path):
    model = build_model("2d", synthetic_psf((24, 32), seed=1))
    path = tmp_path / "costs.json"
    first = iteration_cost(model, path=path)
    second = iteration_cost(model, path=path)
    assert first.source == "probe" and second.source == "cache"
    assert second.seconds_per_iter == pytest.approx(first.seconds_per_iter)
    assert first.key in json.loads(path.read_text())
    assert cache_path().name == "plan_costs.json"


def test_a_tight_budget_raises_the_downsampling(static_cap):
    cap = static_cap
    plan = make_plan(cap.psf, cap.meas, budget_s=1e-3)
    assert plan.downsample > 1 and "raised" in plan.reasons["downsample"]


def test_depth_stack_plans_2d_for_one_plane_and_depth_for_two():
    h, w = 48, 64
    stack = np.stack([synthetic_psf((h, w), n_points=40, seed=s) for s in (1, 2, 3, 4)])
    one = np.zeros((1, 4, h, w))
    one[0, 1] = background(h, w, "im740")
    sim = simulate(build_model("depth", stack), one, photons=20000, seed=0)
    plan = make_plan(None, sim.meas, psf_stack=stack, probe=False)
    assert plan.model == "2d" and plan.planes == (1, 2)
    res = execute(plan.override(iterations=30), None, sim.meas, psf_stack=stack)
    assert res.x.shape == (1, 1, h, w)
    two = one.copy()
    two[0, 2] = np.roll(background(h, w, "im65"), 10, axis=1)
    sim2 = simulate(build_model("depth", stack), two, photons=20000, seed=0)
    plan2 = make_plan(None, sim2.meas, psf_stack=stack, probe=False)
    assert plan2.model == "depth" and plan2.planes is not None
    assert plan2.planes[0] <= 1 and plan2.planes[1] >= 3


def test_mask_and_execute_contract(static_cap):
    cap = static_cap
    rng = np.random.default_rng(0)
    mask = (rng.random(cap.meas.shape) > 0.2).astype(np.float32)
    plan = make_plan(cap.psf, cap.meas * mask, timing=cap.timing, mask=mask, probe=False)
    assert plan.model == "2d"
    steps = []
    res = execute(plan.override(iterations=20), cap.psf, cap.meas * mask, timing=cap.timing,
                  mask=mask, callback=steps.append, cancel=lambda: len(steps) >= 5)
    assert res.iterations == 5 and len(steps) == 5 and res.stop_reason == "cancelled"
    assert res.x.dtype == np.float32 and res.metadata()["plan"]["model"] == "2d"
    with pytest.raises(ValueError, match="sensor"):
        execute(plan, cap.psf, cap.meas[:40], timing=cap.timing)
    with pytest.raises(ValueError, match="shutter"):
        execute(plan.override(model="video", k=4), cap.psf, cap.meas)  # no timing given
    assert torch.get_num_threads() == 1


def test_udn_method_runs_through_the_runner(static_cap):
    cap = static_cap
    plan = make_plan(cap.psf, cap.meas, timing=cap.timing, probe=False)
    res = execute(plan.override(method="udn", iterations=2), cap.psf, cap.meas,
                  timing=cap.timing)
    assert res.x.shape == (1, 1, 48, 64) and res.iterations == 2
    assert res.params["method"] == "udn"


def test_a_udn_plans_budget_counts_the_networks_set_up(static_cap, monkeypatch):
    """The time limit counted the iterations only: a 1 s budget ran 2.3 s (torch and the
    network's set-up, about 1.5 s, came on top). The runner now starts with that time spent."""
    import time

    from recon.udn import UDNRunner

    cap = static_cap
    plan = make_plan(cap.psf, cap.meas, timing=cap.timing, probe=False)
    seen = {}
    run = UDNRunner.run

    def spy(self, *a, **k):
        seen["elapsed"], seen["at"] = self.elapsed_s, time.perf_counter()
        return run(self, *a, **k)

    monkeypatch.setattr(UDNRunner, "run", spy)
    t0 = time.perf_counter()
    res = execute(plan.override(method="udn", iterations=2, budget_s=3600.0), cap.psf,
                  cap.meas, timing=cap.timing)
    assert res.iterations == 2
    assert 0 < seen["elapsed"] <= seen["at"] - t0  # the set-up so far, within the call


@pytest.mark.parametrize(("change", "message"), [
    ({"planes": 3}, "'planes' must be a list of 2 integers"),
    ({"planes": [5]}, "'planes' must be a list of 2 integers"),
    ({"region": 1}, "'region' must be a list of 4 integers"),
    ({"region": [1, 2]}, "'region' must be a list of 4 integers"),
    ({"k": [1]}, "'k' must be an integer"),
    ({"tau": [1]}, "'tau' must be a number"),
    ({"field": "full"}, "'field' must be a list of 2 integers"),
    ({"budget_s": -1}, "'budget_s' must be > 0"),
    ({"lambda_t": float("nan")}, "'lambda_t' must be a number"),
    ({"bin_factor": 0}, "'bin_factor' must be >= 1"),
    ({"tv_depth": -1}, "'tv_depth' must be >= 0"),
    ({"k": -3, "model": "video"}, "'k' must be >= 1"),
    ({"k": 4}, "k applies to a video or depth plan"),
    ({"planes": [2, 0]}, r"\[first, last\) with first < last"),
    # 36 frames for 24 rows: recon fista refuses that (K > rows); recon auto ran it
    ({"model": "video", "k": 36, "downsample": 2},
     r"K = 36 frames for 24 rows \(48 downsampled 2x\).*set k=18 or fewer"),
])
def test_bad_overrides_are_one_line_errors(change, message):
    """``--set`` values of the wrong kind were tracebacks (TypeError, IndexError) or silently
    ignored (k on a 2d plan); each is now a ValueError naming the field."""
    with pytest.raises(ValueError, match=message) as info:
        _plan().override(**change)
    assert "\n" not in str(info.value)


def test_planes_beyond_the_stack_are_refused():
    """--set planes=[0,5] on a 3-plane stack ran, and the metadata said k 5."""
    import torch

    from recon.models import build_model
    from recon.simulate import synthetic_psf

    stack = np.stack([synthetic_psf((32, 40), seed=s) for s in range(3)]).astype(np.float32)
    x = np.zeros((1, 3, 32, 40), np.float32)
    x[0, 1, 10:20, 10:30] = 1
    b = build_model("depth", stack).apply(torch.as_tensor(x)).numpy()[0]
    p = make_plan(None, b, psf_stack=stack, probe=False)
    with pytest.raises(ValueError, match=r"\[0, 5\] reaches past the 3-plane stack"):
        p.override(planes=[0, 5])
    assert p.override(model="depth", planes=[0, 2]).k == 2


def test_a_whole_float_format_version_is_that_version():
    """1.0 (as some JSON writers put 1) is version 1, in plans as in every versioned file
    (recon.formats.whole_version); it was "must be a whole number >= 1, got 1.0"."""
    from recon.formats import whole_version

    d = _plan().to_json()
    d["format_version"] = 1.0
    assert Plan.from_json(d) == _plan()
    d["format_version"] = 1.5
    with pytest.raises(ValueError, match=r"whole number >= 1, got 1\.5"):
        Plan.from_json(d)
    assert [whole_version(v) for v in (1, 2.0, 1.5, True, "1", None)] == [1, 2, None, None,
                                                                          None, None]


def test_frames_with_a_short_last_one_are_said_so(monkeypatch):
    """9 shutter bins grouped 2 at a time were "5 frames of 2 shutter bins each": the last
    frame has 1. The planner's reason and an override's both say it now."""
    import recon.plan.planner as planner
    from recon.plan.analysis import CVCandidate, TimeScale

    def five_of_two(psf, b, base, region, factor, **kw):
        return TimeScale(5, 2, True, (CVCandidate("2d", 1, 2.0, 1.0, 9.0),
                                      CVCandidate("video K=5", 5, 1.0, 0.0, 0.0)),
                         int(base.shape[0]))

    monkeypatch.setattr(planner, "time_scale", five_of_two)
    psf = synthetic_psf((36, 40), seed=1)
    meas = np.abs(np.random.default_rng(0).normal(size=(36, 40))) + 0.1
    shutter = np.zeros((9, 36))
    for i in range(9):
        shutter[i, 4 * i:4 * i + 4] = 1.0
    plan = make_plan(psf, meas, shutter=shutter, probe=False)
    assert (plan.model, plan.k, plan.bin_factor, plan.base_bins) == ("video", 5, 2, 9)
    assert "5 frames of 2 shutter bins (the last of 1)" in plan.reasons["k"]
    assert "each" not in plan.reasons["k"]
    # 11 bins, 5 frames asked: groups of 3 make 4 frames, the last of 2
    four = _plan(base_bins=11).override(model="video", k=5)
    assert four.k == 4
    assert "11 shutter bins in groups of 3 make 4 frames (the last of 2)" in four.reasons["k"]


def test_a_plan_file_of_more_frames_than_rows_loads_and_is_mended_by_set():
    """The K-rows rule refused such a plan file as it was read, so `--set k=...` (applied
    after reading) could never mend it; it is refused when it would run, and mended by --set."""
    bad = _plan(model="video", k=36, bin_factor=1, downsample=2)  # 36 frames, 24 rows
    back = Plan.from_json(json.loads(json.dumps(bad.to_json())))
    with pytest.raises(ValueError, match=r"K = 36 frames for 24 rows.*set k=18 or fewer"):
        back.check_rows()
    cap_psf = synthetic_psf((48, 64), seed=1)
    with pytest.raises(ValueError, match=r"K = 36 frames for 24 rows"):
        execute(back, cap_psf, np.ones((48, 64), np.float32),
                shutter=np.ones((36, 48), np.float32))
    fixed = back.override(k=18)
    assert (fixed.k, fixed.bin_factor) == (18, 2)
    fixed.check_rows()
