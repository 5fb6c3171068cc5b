"""Overrides of model and planes on a plan made from a PSF stack (``--set planes=...``).

``--set planes=[0,7]`` on a plan that chose one plane gave a 2d model of plane 6 (the old
rule kept the strongest plane of the range because the model stayed 2d), while the reason said
the user's planes were used; ``--set model=depth`` alone gave a "depth" model of one plane, and
the K line kept the analysis' "one PSF plane ... a 2D model" text. Planes set now choose the
model (one plane 2d, more depth), ``model=depth`` alone takes the depth analysis' best range,
and a model that contradicts the planes set with it is refused in one line.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from app.cli import main
from app.commands.plan import register_auto
from recon.plan import Plan
from recon.plan.planner import planned_model
from recon.simulate import synthetic_psf

H, W = 32, 40
ANALYSIS = ("one PSF plane (1) predicts held-out pixels as well as more planes (held-out MSE "
            "2d plane 1: 4.54e-05; ...): a 2D model")
# the depth evidence make_plan wrote for a scene in plane 1 of a 4-plane stack
DEPTH = {"planes": [1, 2], "energy_per_plane": [0.2353, 0.3288, 0.2251, 0.2108],
         "candidates": [
             {"label": "2d plane 1", "k": 1, "heldout_mse": 4.54e-05, "planes": [1, 2]},
             {"label": "depth planes 0..1", "k": 2, "heldout_mse": 6.134e-05, "planes": [0, 2]},
             {"label": "depth planes 0..2", "k": 3, "heldout_mse": 6.484e-05, "planes": [0, 3]},
             {"label": "depth planes 0..3", "k": 4, "heldout_mse": 6.183e-05, "planes": [0, 4]},
         ]}


def _stack_plan(**kw):
    base = {"model": "2d", "k": 1, "sensor": (H, W), "field": (H, W),
            "region": (0, 0, H, W), "downsample": 1, "method": "fista-tv", "iterations": 300,
            "planes": (1, 2), "reasons": {"model": ANALYSIS, "k": ANALYSIS},
            "evidence": {"depth": DEPTH}}
    base.update(kw)
    return Plan(**base)


def test_planes_of_more_than_one_plane_switch_to_the_depth_model():
    p = _stack_plan().override(planes=[0, 3])
    assert (p.model, p.k, p.planes) == ("depth", 3, (0, 3))
    assert "depth" in p.reasons["model"] and "planes 0..2" in p.reasons["model"]
    assert "2D model" not in p.reasons["k"] and "3 planes" in p.reasons["k"]
    assert "planes 0..2 set by the user" in p.reasons["planes"]
    assert "model      depth (PSF planes 0..2)" in p.describe()
    stack = np.stack([synthetic_psf((H, W), seed=s) for s in range(4)]).astype(np.float32)
    assert planned_model(p, psf_stack=stack).scene_shape[1] == 3  # three planes are solved


def test_one_plane_set_keeps_a_2d_model_of_that_plane():
    p = _stack_plan().override(planes=[2, 3])
    assert (p.model, p.k, p.planes) == ("2d", 1, (2, 3))
    assert "plane 2" in p.reasons["k"] and "2D model" not in p.reasons["k"]
    assert "model      2d (PSF plane 2)" in p.describe()


def test_model_depth_alone_takes_the_analysis_best_range_of_planes():
    p = _stack_plan().override(model="depth")
    # of the ranges of more than one plane, 0..1 predicted held-out pixels best
    assert (p.model, p.k, p.planes) == ("depth", 2, (0, 2))
    assert "planes 0..1" in p.reasons["model"] and "6.13e-05" in p.reasons["model"]
    assert p.reasons["k"] == "2 planes: the depth model's planes 0..1"
    with pytest.raises(ValueError, match="records no depth analysis") as info:
        _stack_plan(evidence={}).override(model="depth")
    assert "\n" not in str(info.value)


def test_model_2d_of_a_depth_plan_keeps_its_strongest_plane_and_says_so():
    depth = _stack_plan().override(model="depth", planes=[0, 4])
    assert (depth.model, depth.k) == ("depth", 4)
    p = depth.override(model="2d")
    assert (p.model, p.k, p.planes) == ("2d", 1, (1, 2))  # plane 1 holds the most energy
    assert "plane 1 of the plan's planes 0..3" in p.reasons["model"]
    assert p.reasons["k"] == "one image: a 2d model of PSF plane 1"


@pytest.mark.parametrize(("plan_kw", "change", "message"), [
    ({}, {"model": "2d", "planes": [0, 3]}, "a 2d plan reconstructs one PSF plane"),
    ({}, {"model": "depth", "planes": [2, 3]}, "a depth plan needs more than one PSF plane"),
    ({}, {"model": "depth", "planes": [0, 3], "k": 2}, "'k' 2 does not match planes"),
    ({}, {"planes": None}, "cannot be null"),
    ({"planes": None, "evidence": {}}, {"planes": [0, 2]},
     "applies to a plan made from a PSF stack"),
])
def test_contradicting_model_and_planes_are_refused_in_one_line(plan_kw, change, message):
    with pytest.raises(ValueError, match=message) as info:
        _stack_plan(**plan_kw).override(**change)
    assert "\n" not in str(info.value)


def test_recon_auto_runs_the_planes_set(tmp_path, capsys):
    """The reported case: recon auto --set planes=[0,7] reconstructed plane 6 alone."""
    from pathlib import Path

    from recon.io import read_reconstruction

    z = np.load(Path(__file__).resolve().parents[2] / "recon" / "samples" / "depth_usaf.npz")
    np.save(tmp_path / "meas.npy", z["meas"])
    np.save(tmp_path / "stack.npy", z["psf"][2:10].astype(np.float32))
    inputs = ["--psf-stack", str(tmp_path / "stack.npy"), "--meas", str(tmp_path / "meas.npy")]
    plan_file = tmp_path / "plan.json"
    assert main(["plan", *inputs, "--tau", "1e-3", "--no-probe", "--out",
                 str(plan_file)]) == 0
    capsys.readouterr()
    assert json.loads(plan_file.read_text())["model"] == "2d"  # the analysis' own choice
    parser = argparse.ArgumentParser()
    register_auto(parser.add_subparsers())
    out = tmp_path / "rec.tif"
    args = parser.parse_args(["auto", *inputs, "--plan", str(plan_file), "--set",
                              "planes=[0,7]", "--set", "iterations=2", "--out", str(out),
                              "--quiet"])
    assert args.func(args) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert (summary["model"], summary["k"]) == ("depth", 7)
    x, meta = read_reconstruction(out)
    assert x.shape[1] == 7 and meta["plan"]["planes"] == [0, 7]


def test_k_set_with_the_planes_it_agrees_with_is_a_depth_plan():
    """(spectral/depth review) planes=[0,3] with k=3 on a 2d plan was refused as "a 2d plan
    has k = 1 (set model=video with it)", against docs/plan.md; k alone on a 2d plan names
    depth too."""
    p = _stack_plan().override(planes=[0, 3], k=3)
    assert (p.model, p.k, p.planes) == ("depth", 3, (0, 3))
    with pytest.raises(ValueError, match=r"does not match planes"):
        _stack_plan().override(planes=[0, 3], k=2)
    with pytest.raises(ValueError, match=r"a 2d plan has k = 1 \(set model=video, or "
                                         r"planes=\[first,last\] for depth"):
        _stack_plan().override(k=3)
    with pytest.raises(ValueError, match=r"a 2d plan has k = 1"):
        _stack_plan().override(planes=[2, 3], k=3)  # one plane: 2d
