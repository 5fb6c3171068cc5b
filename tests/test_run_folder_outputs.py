"""No writer command puts its files inside a UDN run folder (jobs status/resume/combine read
the folder; `recon udn --write-spec RUN/run.json` once made a run unreadable). recon fista,
recon auto, plan --out and simulate had no such check."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.clirun import run_cli


@pytest.fixture
def run_and_inputs(tmp_path):
    from recon.simulate import synthetic_psf

    np.save(tmp_path / "psf.npy", synthetic_psf((24, 32), seed=2))
    np.save(tmp_path / "meas.npy", np.random.default_rng(0).random((24, 32)).astype(np.float32))
    run = tmp_path / "run"
    run.mkdir()
    (run / "run.json").write_text(json.dumps({"format": "lenslesscam.udn_run",
                                              "format_version": 1, "status": "completed"}))
    return tmp_path, run


@pytest.mark.parametrize("command", [
    ["recon", "fista", "--tau", "1e-3", "--iters", "5", "--out", "{run}/x.tif"],
    ["recon", "auto", "--tau", "1e-3", "--quiet", "--out", "{run}/sub/x.tif"],
    ["plan", "--no-probe", "--out", "{run}/plan.json"],
])
def test_reconstructions_and_plans_are_not_written_into_a_run(run_and_inputs, capsys, command):
    d, run = run_and_inputs
    argv = [a.replace("{run}", str(run)) for a in command]
    code, _, err = run_cli(capsys, *argv[:2] if argv[0] == "recon" else argv[:1],
                           "--psf", d / "psf.npy", "--meas", d / "meas.npy",
                           *(argv[2:] if argv[0] == "recon" else argv[1:]))
    assert code == 2 and "writes into the UDN run folder" in err, err
    assert sorted(p.name for p in run.iterdir()) == ["run.json"]


def test_simulate_is_not_written_into_a_run(run_and_inputs, capsys):
    d, run = run_and_inputs
    code, _, err = run_cli(capsys, "simulate", "--psf", d / "psf.npy", "--scene", "sample:im65",
                           "--out", run / "sim")
    assert code == 2 and "writes into the UDN run folder" in err, err
    # next to a run, not in it: fine
    code, _, err = run_cli(capsys, "recon", "fista", "--psf", d / "psf.npy", "--meas",
                           d / "meas.npy", "--tau", "1e-3", "--iters", "5", "--out",
                           d / "beside.tif")
    assert code == 0, err


def test_every_writer_command_takes_the_rule_from_the_shared_output_check(run_and_inputs,
                                                                          capsys):
    """The rule sits in check_command_outputs: calibrate (never given its own check) refuses
    too, before the camera is opened."""
    _, run = run_and_inputs
    code, _, err = run_cli(capsys, "calibrate", "darks", "--camera", "sim", "--no-prompt",
                           "--frames", "2", "--out", run / "darks.npz")
    assert code == 2 and "writes into the UDN run folder" in err, err
    assert sorted(p.name for p in run.iterdir()) == ["run.json"]
