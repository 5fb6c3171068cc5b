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


# -- a new run is not made inside another run's folder ---------------------------------------


def _tiny_spec(d):
    """A spec of the fixture's data (never run: the refusals come before any work)."""
    spec = d / "job.toml"
    spec.write_text('[data]\npsf = "psf.npy"\nmeasurement = "meas.npy"\n\n[network]\n'
                    'scales = 2\nchannels = 4\nskip_channels = 2\ninput_channels = 4\n\n'
                    '[stopping]\nmax_iter = 2\n', encoding="utf-8")
    return spec


@pytest.mark.parametrize("where", ["run/sub", "run/sub/deeper", "link/sub", "deep_link/sub"])
def test_jobs_run_and_recon_udn_make_no_run_inside_a_run(run_and_inputs, capsys, where):
    """`jobs run SPEC --out RUN/sub` and `recon udn ... --out RUN/sub` made a second run inside
    a finished run's folder (whose files jobs status/resume/combine read); through a link to
    the run (or to a folder in it) too. The shared check missed a link to a folder in a run
    for every writer command (`recon fista --out LINK/x.tif`, LINK -> RUN/deep)."""
    d, run = run_and_inputs
    (run / "deep").mkdir()
    (d / "link").symlink_to(run, target_is_directory=True)
    (d / "deep_link").symlink_to(run / "deep", target_is_directory=True)
    before = sorted(p.name for p in run.rglob("*"))
    out = d / where
    for argv in (["jobs", "run", _tiny_spec(d), "--out", out, "--quiet"],
                 ["recon", "udn", "--psf", d / "psf.npy", "--meas", d / "meas.npy", "--iters",
                  "2", "--scales", "2", "--net-channels", "4", "--skip-channels", "2",
                  "--input-channels", "4", "--device", "cpu", "--quiet", "--out", out],
                 ["recon", "fista", "--psf", d / "psf.npy", "--meas", d / "meas.npy", "--tau",
                  "1e-3", "--iters", "2", "--out", out / "x.tif"]):
        code, stdout, err = run_cli(capsys, *argv)
        assert code == 2 and stdout == "", err
        assert len(err.strip().splitlines()) == 1
        assert f"writes into the UDN run folder {run} (it holds run.json)" in err, err
        assert sorted(p.name for p in run.rglob("*")) == before


def test_run_job_itself_refuses_a_folder_inside_a_run(run_and_inputs):
    """The library's rule too (batch items, the app's job processes, any caller)."""
    from recon.udn.jobs import run_job

    d, run = run_and_inputs
    with pytest.raises(ValueError, match=r"lies inside the UDN run folder .*: a run's folder "
                                         "holds only the run's own files"):
        run_job(_tiny_spec(d), run / "sub")
    assert sorted(p.name for p in run.iterdir()) == ["run.json"]


def test_the_run_folder_itself_is_still_refused_as_a_run(run_and_inputs, capsys):
    """`--out RUN` (a run already there) keeps its own advice: resume it, or another folder.
    Beside a run is fine (the refusal is for folders inside one only)."""
    d, run = run_and_inputs
    code, stdout, err = run_cli(capsys, "jobs", "run", _tiny_spec(d), "--out", run, "--quiet")
    assert code == 2 and stdout == ""
    assert f"{run} already holds a run: use 'jobs resume {run}'" in err, err
    from app.commands._options import refuse_run_folder_outputs

    refuse_run_folder_outputs([d / "beside"], "--out")  # beside a run: no error
