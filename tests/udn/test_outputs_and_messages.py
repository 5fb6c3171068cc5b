"""What ``jobs combine`` takes, where UDN commands may write, and what their messages advise.

Each test is a finding of a hostile review (the old behaviour in its docstring).
"""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import numpy as np
import pytest

from app.cli import build_parser
from recon.models import build_model
from recon.stepwise import NumericalError
from recon.udn.ensemble import combine_runs
from recon.udn.jobs import job_status, run_job
from recon.udn.network import NetworkConfig
from recon.udn.runner import UDNConfig, UDNRunner
from tests.clirun import run_cli
from tests.udn.conftest import TINY_NET, tiny_problem, write_spec

SHORT = {"max_iter": 12, "patience": 1000}


@pytest.fixture
def two_runs(tiny_data, tmp_path):
    """Two finished runs of one spec (seeds 0 and 1) and the spec."""
    spec = write_spec(tiny_data, stopping=SHORT)
    runs = [tmp_path / f"s{s}" for s in (0, 1)]
    for s, r in enumerate(runs):
        run_job(spec, r, seed=s)
    return spec, runs


# -- jobs combine: failed members ----------------------------------------------------------------


def test_combine_refuses_a_failed_member_naming_it(two_runs, tiny_data, tmp_path, capsys):
    """A run that failed (non-finite loss after its restores) still leaves a best.tif, and
    combine averaged it in: the ensemble's PSNR fell with no word."""
    _, runs = two_runs
    bad_spec = write_spec(tiny_data, "bad.toml", stopping=SHORT,
                          optimizer={"lr": 1e30, "max_backoffs": 1})
    failed = tmp_path / "failed"
    with pytest.raises(NumericalError):
        run_job(bad_spec, failed, seed=2)
    rec = json.loads((failed / "run.json").read_text())
    assert rec["finish_reason"] == "failed" and rec["status"] == "finished"
    assert "best" in rec["results"]  # what the old combine took
    out = tmp_path / "ens.tif"
    with pytest.raises(ValueError, match=r"refusing 1 failed run\(s\): .*failed \("
                                         r"NumericalError: UDN: the loss is not finite"):
        combine_runs([*runs, failed], out)
    code, stdout, err = run_cli(capsys, "jobs", "combine", *runs, failed, "--out", out)
    assert code == 2 and stdout == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and str(failed) in lines[0] and "failed run" in lines[0]
    assert str(runs[0]) not in lines[0]  # only the failed member is named
    assert not out.exists()
    # without it, the ensemble is made
    code, stdout, _ = run_cli(capsys, "jobs", "combine", *runs, "--out", out)
    assert code == 0 and "ensemble of 2 runs" in stdout


# -- jobs combine: the truth is not part of the problem -----------------------------------------


def test_combine_takes_a_run_without_truth_and_scores_with_the_others(two_runs, tiny_data,
                                                                      tmp_path, capsys):
    """A run made without --truth was 'a run of other data (differs in: data.truth)', though
    the truth only scores a run and the fit never reads it."""
    _, runs = two_runs
    no_truth = write_spec(tiny_data, "nt.toml", stopping=SHORT, data={"truth": None})
    assert "truth" not in no_truth.read_text()
    bare = tmp_path / "bare"
    run_job(no_truth, bare, seed=5)
    assert "truth" not in json.loads((bare / "run.json").read_text())["inputs"]
    for members in ([runs[0], bare], [bare, runs[0]]):  # the first member without a truth too
        res = combine_runs(members, tmp_path / "ens.tif")
        assert res.scores is not None and np.isfinite(res.scores["psnr"])
        from recon.io import read_reconstruction

        meta = read_reconstruction(tmp_path / "ens.tif")[1]
        assert meta["scored_against"]["path"].endswith("truth.npy")
    code, stdout, err = run_cli(capsys, "jobs", "combine", bare, runs[1], "--out",
                                tmp_path / "ens2.tif")
    assert code == 0, err
    assert "ensemble of 2 runs" in stdout and "PSNR" in stdout
    # what the fit uses still has to agree: another mask is other data
    other = tiny_data.parent / "other"
    other.mkdir()
    for name in ("psf", "meas", "truth"):
        (other / f"{name}.npy").write_bytes((tiny_data / f"{name}.npy").read_bytes())
    mask = np.load(tiny_data / "mask.npy")
    mask.flat[np.flatnonzero(mask)[0]] = 0
    np.save(other / "mask.npy", mask)
    odd = tmp_path / "odd"
    run_job(write_spec(other, stopping=SHORT), odd, seed=6)
    # (the measurement as read differs too: erased pixels are 0 in it)
    with pytest.raises(ValueError, match=r"other data than .* \(differs in: data\.mask"
                                         r"(, data\.measurement)?\)"):
        combine_runs([runs[0], odd], tmp_path / "ens3.tif")
    # two truths: the ensemble would be scored against one of them silently
    other_truth = tiny_data.parent / "other_truth.npy"
    t2 = np.load(tiny_data / "truth.npy").copy()
    t2.flat[0] += 1.0
    np.save(other_truth, t2)
    second = tmp_path / "second"
    run_job(write_spec(tiny_data, "t2.toml", stopping=SHORT, data={"truth": str(other_truth)}),
            second, seed=7)
    with pytest.raises(ValueError, match="different truths"):
        combine_runs([runs[0], second], tmp_path / "ens4.tif")


# -- no output inside a run folder ---------------------------------------------------------------


def _udn_args(data):
    return ["recon", "udn", "--psf", data / "psf.npy", "--meas", data / "meas.npy"]


def test_write_spec_never_writes_into_a_run_folder(two_runs, tiny_data, tmp_path, capsys):
    """`recon udn ... --write-spec RUN/run.json --overwrite` wrote TOML over a finished run's
    record (status, resume and cancel then failed); RUN/final.tif was taken too."""
    _, runs = two_runs
    run = runs[0]
    record = (run / "run.json").read_bytes()
    final = (run / "final.tif").read_bytes()
    for target, extra in ((run / "run.json", ["--overwrite"]), (run / "final.tif", []),
                          (run / "notes.toml", []), (run / "previews" / "x.toml", [])):
        code, stdout, err = run_cli(capsys, *_udn_args(tiny_data), "--write-spec", target,
                                    *extra)
        assert code == 2 and stdout == ""
        assert len(err.strip().splitlines()) == 1
        assert f"--write-spec {target} writes into the UDN run folder {run}" in err
    assert (run / "run.json").read_bytes() == record
    assert (run / "final.tif").read_bytes() == final
    assert not (run / "notes.toml").exists()
    assert job_status(run).finish_reason == "completed"  # still readable
    # a folder that holds no run is fine, and so is the run folder's parent
    code, stdout, err = run_cli(capsys, *_udn_args(tiny_data), "--write-spec",
                                tmp_path / "spec.toml")
    assert code == 0 and (tmp_path / "spec.toml").is_file(), err


def test_combine_never_writes_into_another_run_folder(two_runs, tiny_data, tmp_path, capsys):
    """`jobs combine k1 k2 --out k3/best.tif --overwrite` replaced the best estimate of k3, a
    run that is not a member (members were already refused)."""
    spec, runs = two_runs
    third = tmp_path / "third"
    run_job(spec, third, seed=3)
    best = (third / "best.tif").read_bytes()
    for target in (third / "best.tif", third / "new.tif"):
        code, stdout, err = run_cli(capsys, "jobs", "combine", *runs, "--out", target,
                                    "--overwrite")
        assert code == 2 and stdout == ""
        assert f"--out {target} writes into the UDN run folder {third}" in err
    assert (third / "best.tif").read_bytes() == best and not (third / "new.tif").exists()
    with pytest.raises(ValueError, match="writes into the UDN run folder"):
        combine_runs(runs, third / "sub" / "e.tif")  # the library refuses it too


def test_a_run_folder_is_found_through_links_and_a_damaged_record(two_runs, tmp_path):
    from recon.udn.jobs import run_folder_holding

    _, runs = two_runs
    link = tmp_path / "link"
    link.symlink_to(runs[0], target_is_directory=True)
    assert run_folder_holding(link / "x.tif") == runs[0].resolve()
    assert run_folder_holding(runs[0] / ".." / "x.tif") is None
    (runs[1] / "run.json").write_text("[job]\nname = 'toml, not json'\n")  # the old damage
    assert run_folder_holding(runs[1] / "x.tif") == runs[1].resolve()
    plain = tmp_path / "plain"
    plain.mkdir()
    (plain / "run.json").write_text('{"format": "something else"}')
    assert run_folder_holding(plain / "x.tif") is None


# -- the resume hint after a time limit ------------------------------------------------------------


def test_the_time_limit_hint_is_a_command_that_is_accepted(tiny_data, tmp_path, capsys):
    """`--time-limit 0.001` ended with 'lenslesscam jobs resume RUN --time-limit 0', which
    the parser refuses (must be a finite number > 0)."""
    out = tmp_path / "run"
    code, stdout, err = run_cli(capsys, *_udn_args(tiny_data), "--mask", tiny_data / "mask.npy",
                                "--scales", 2, "--net-channels", 4, "--input-channels", 4,
                                "--time-limit", "0.001", "--quiet", "--out", out)
    assert code == 0, err
    detail = json.loads(stdout)["detail"]
    m = re.search(r"lenslesscam (jobs resume .*)$", detail)
    assert m is not None, detail
    argv = shlex.split(m.group(1))
    args = build_parser().parse_args(argv)  # SystemExit 2 on the old "--time-limit 0"
    used = json.loads((out / "run.json").read_text())["progress"]["elapsed_s"]
    assert args.time_limit > used
    code, stdout, err = run_cli(capsys, *argv, "--quiet")
    assert code == 0, err
    assert json.loads(stdout)["iterations"] > 1


@pytest.mark.parametrize("s", [2e-3, 1.2345e-3, 0.0123456, 1.0, 9.9999, 10.0, 119.2, 3e-9])
def test_seconds_are_never_rounded_down(s):
    from recon.udn.jobs import _seconds_arg

    text = _seconds_arg(s)
    assert float(text) >= s and float(text) <= 1.01 * s + 1  # at most a step above
    assert float(text) > 0


# -- divergence messages name the settings that can cause them ----------------------------------


def _runner(net=None, meas_scale=1.0, **cfg):
    psf, sim = tiny_problem()
    model = build_model("2d", psf, mask=sim.mask)
    net_cfg = NetworkConfig(**{**TINY_NET, **(net or {})})
    return UDNRunner(model, sim.meas * meas_scale, network=net_cfg,
                     config=UDNConfig(max_iter=40, holdout=0.0, seed=1, **cfg))


def _error(r):
    with pytest.raises(NumericalError) as info:
        for _ in r.steps():
            pass
    return str(info.value)


@pytest.mark.parametrize(("net", "cfg", "named"), [
    ({"input_scale": 1e30}, {}, "network.input_scale = 1e+30 (default 0.1)"),
    ({}, {"reg_noise": 1e38}, "optimizer.reg_noise = 1e+38 (default 0.05)"),
    ({}, {"headroom": 1e30}, "optimizer.headroom = 1e+30 (default 1)"),
    ({}, {"lr": 1e30}, "optimizer.lr = 1e+30 (default 0.01)"),
    ({}, {"tv_weight": 1e38}, "optimizer.tv_weight = 1e+38 (default 0)"),
])
def test_a_divergence_names_the_setting_far_from_its_range(net, cfg, named):
    """input_scale 1e30 said 'lower optimizer.tv_weight (now 0)'; reg_noise 1e38 and headroom
    1e30 said 'lower optimizer.lr' (at its default)."""
    msg = _error(_runner(net, **cfg))
    assert f"settings far above their usual range: {named}; lower it" in msg
    for other in ("input_scale", "reg_noise", "headroom", "lr", "tv_weight"):
        if other not in named:
            assert f"{other} =" not in msg and f"lower optimizer.{other}" not in msg
    assert "(now" not in msg


def test_a_divergence_with_usual_settings_blames_none(capsys):
    """Data far out of scale with every setting at its default: no setting is blamed."""
    msg = _error(_runner(meas_scale=1e30))
    assert "no setting that scales the loss or its gradient is far from its usual range" in msg
    assert "optimizer.lr 0.01" in msg and "network.input_scale 0.1" in msg
    assert "check the data" in msg and "lower optimizer" not in msg


# -- recon udn --float64 -------------------------------------------------------------------------


def test_recon_udn_does_not_offer_float64(tiny_data, capsys):
    """`recon udn --help` listed --float64, which always failed."""
    with pytest.raises(SystemExit):
        build_parser().parse_args(["recon", "udn", "--help"])
    help_text = capsys.readouterr().out
    assert "--precision" in help_text and "--float64" not in help_text
    with pytest.raises(SystemExit) as info:
        build_parser().parse_args([*map(str, _udn_args(tiny_data)), "--float64",
                                   "--write-spec", "x.toml"])
    assert info.value.code == 2
    assert "unrecognized arguments: --float64" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        build_parser().parse_args(["recon", "fista", "--help"])
    assert "--float64" in capsys.readouterr().out  # the other methods keep it



def test_a_link_then_dotdot_into_a_run_folder_is_found(tmp_path):
    """a/link -> RUN/inner: a/link/../x.tif is RUN/x.tif; '..' was taken off by text first."""
    from recon.udn.jobs import run_folder_holding

    run = tmp_path / "run"
    (run / "inner").mkdir(parents=True)
    (run / "run.json").write_text(json.dumps({"format": "lenslesscam.udn_run",
                                              "format_version": 1, "status": "completed"}))
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "link").symlink_to(run / "inner")
    assert run_folder_holding(tmp_path / "a" / "link" / ".." / "x.tif") == run.resolve()


def test_write_spec_takes_a_toml_name(tiny_data, tmp_path, capsys):
    """`--write-spec result.tif --overwrite` replaced a TIFF with TOML text under its name."""
    tif = tmp_path / "result.tif"
    tif.write_bytes(b"II*\x00 a tiff")
    for target, extra in ((tif, ["--overwrite"]), (tmp_path / "spec.txt", [])):
        code, stdout, err = run_cli(capsys, *_udn_args(tiny_data), "--write-spec", target,
                                    *extra)
        assert code == 2 and stdout == "", err
        assert len(err.strip().splitlines()) == 1
        assert f"--write-spec {target}: a job spec is saved as .toml" in err
    assert tif.read_bytes() == b"II*\x00 a tiff" and not (tmp_path / "spec.txt").exists()


def test_jobs_list_shows_each_run_and_names_a_damaged_one(two_runs, tmp_path, capsys,
                                                          monkeypatch):
    """There was no way to see the runs of a folder from the command line (the app's jobs
    table only): `jobs list` shows each, in both layouts, and a damaged record by name."""
    import shutil

    _, runs = two_runs
    root = tmp_path / "jobs"
    shutil.copytree(runs[0], root / "plain")
    shutil.copytree(runs[1], root / "20261127-app-job" / "run")  # the app's layout
    (root / "broken").mkdir()
    (root / "broken" / "run.json").write_text("{")
    # a record that parses but holds a field of the wrong type (a traceback hid every run)
    shutil.copytree(runs[0], root / "odd")
    rec = json.loads((root / "odd" / "run.json").read_text())
    rec["spec"]["job"] = "x"
    (root / "odd" / "run.json").write_text(json.dumps(rec))
    code, out, err = run_cli(capsys, "jobs", "list", root)
    assert code == 0, err
    lines = out.strip().splitlines()
    assert lines[0] == f"4 run(s) in {root}:"
    assert lines[1].startswith("  20261127-app-job/run  completed  iteration ")
    assert lines[2].startswith("  broken  unreadable: ") and "run.json" in lines[2]
    assert lines[3].startswith("  odd  unreadable: ") and "run.json" in lines[3]
    assert lines[4].startswith("  plain  completed  iteration ")
    code, out, _ = run_cli(capsys, "jobs", "list", root, "--json")
    got = json.loads(out)
    assert [Path(r["run_dir"]).name for r in got] == ["run", "broken", "odd", "plain"]
    assert got[0]["finish_reason"] == "completed" and "error" in got[1]
    # the default is the app's jobs folder
    monkeypatch.setenv("LENSLESSCAM_JOBS_DIR", str(root))
    monkeypatch.setenv("LENSLESSCAM_CONFIG_DIR", str(tmp_path / "config"))
    code, out, _ = run_cli(capsys, "jobs", "list")
    assert code == 0 and out.startswith(f"4 run(s) in {root}:")
    monkeypatch.setenv("LENSLESSCAM_JOBS_DIR", str(tmp_path / "none"))
    code, out, _ = run_cli(capsys, "jobs", "list")
    assert code == 0 and "does not exist yet" in out
    code, _, err = run_cli(capsys, "jobs", "list", tmp_path / "none")
    assert code == 2 and "no such folder" in err
    # a file is said to be one (it was "no such folder"); a run folder lists itself (it was
    # "no runs")
    code, _, err = run_cli(capsys, "jobs", "list", root / "plain" / "run.json")
    assert code == 2 and "is a file, not a folder" in err
    code, out, _ = run_cli(capsys, "jobs", "list", root / "plain")
    assert code == 0 and out.splitlines()[0] == f"1 run(s) in {root / 'plain'}:"
    assert out.splitlines()[1].startswith("  plain  completed  iteration ")
