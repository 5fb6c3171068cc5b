"""Ensembles of UDN runs: ``jobs run --seed`` and ``jobs combine`` (recon.udn.ensemble)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from app.cli import main as cli_main
from recon.io import read_reconstruction
from recon.metrics import gain_fit, psnr
from recon.udn.ensemble import combine_runs
from recon.udn.jobs import run_job
from tests.udn.conftest import write_spec


@pytest.fixture
def three_runs(tiny_data, tmp_path):
    """Runs of one spec with seeds 0, 1, 2 (the third one through the CLI)."""
    spec = write_spec(tiny_data, stopping={"max_iter": 60, "patience": 1000},
                      output={"average_every": 20})
    runs = [tmp_path / f"s{s}" for s in range(3)]
    for s in (0, 1):
        run_job(spec, runs[s], seed=s)
    assert cli_main(["jobs", "run", str(spec), "--out", str(runs[2]), "--seed", "2",
                     "--quiet"]) == 0
    return spec, runs


def test_combine_averages_the_members_and_records_them(three_runs, tiny_data, tmp_path, capsys):
    spec, runs = three_runs
    recs = [json.loads((r / "run.json").read_text()) for r in runs]
    assert [r["spec"]["optimizer"]["seed"] for r in recs] == [0, 1, 2]
    assert recs[2]["overrides"] == {"optimizer.seed": 2}
    copy = (runs[2] / "job.toml").read_text()
    assert copy.startswith("# run with 'jobs run --seed 2'") and copy.endswith(spec.read_text())
    bests = [read_reconstruction(r / "best.tif")[0] for r in runs]
    assert not np.array_equal(bests[0], bests[1])  # the seeds differ

    out = tmp_path / "ens.tif"
    res = combine_runs(runs, out)
    x, meta = read_reconstruction(out)
    np.testing.assert_allclose(x, np.mean(bests, axis=0), rtol=1e-6, atol=1e-7)
    assert meta["method"] == "udn-ensemble" and meta["estimate"] == "best"
    assert [m["seed"] for m in meta["members"]] == [0, 1, 2]
    assert [m["iteration"] for m in meta["members"]] == [r["results"]["best_iteration"]
                                                        for r in recs]
    truth = np.load(tiny_data / "truth.npy")
    assert res.scores is not None
    assert res.scores["psnr"] == pytest.approx(psnr(truth, gain_fit(truth, x)[0]), abs=1e-4)
    assert (tmp_path / "ens.png").is_file()

    assert cli_main(["jobs", "combine", *map(str, runs[:2]), "--estimate", "final", "--out",
                     str(tmp_path / "ens2.tif")]) == 0
    printed = capsys.readouterr().out
    assert "ensemble of 2 runs" in printed and "PSNR" in printed
    x2, meta2 = read_reconstruction(tmp_path / "ens2.tif")
    finals = [read_reconstruction(r / "final.tif")[0] for r in runs[:2]]
    np.testing.assert_allclose(x2, np.mean(finals, axis=0), rtol=1e-6, atol=1e-7)
    assert meta2["estimate"] == "final"


def test_combine_refuses_what_is_not_one_problem(three_runs, tiny_data, tmp_path, capsys):
    spec, runs = three_runs
    out = tmp_path / "never.tif"
    with pytest.raises(ValueError, match="at least two"):
        combine_runs(runs[:1], out)
    with pytest.raises(ValueError, match="named twice"):
        combine_runs([runs[0], runs[0]], out)
    same_seed = tmp_path / "again0"
    run_job(spec, same_seed, seed=0)
    with pytest.raises(ValueError, match="both ran with seed 0"):
        combine_runs([runs[0], same_seed], out)
    # a run of another measurement
    other = tiny_data.parent / "other"
    other.mkdir()
    for name in ("psf", "mask", "truth"):
        (other / f"{name}.npy").write_bytes((tiny_data / f"{name}.npy").read_bytes())
    meas = np.load(tiny_data / "meas.npy")
    np.save(other / "meas.npy", meas * 1.01)
    run_job(write_spec(other, stopping={"max_iter": 10}), tmp_path / "other_run", seed=5)
    with pytest.raises(ValueError, match=r"other data .*data\.measurement"):
        combine_runs([runs[0], tmp_path / "other_run"], out)
    # the same files read with another dark level are other data too
    dark = write_spec(tiny_data, "dark.toml", stopping={"max_iter": 10},
                      data={"dark": 0.01, "psf_dark": 0.0})
    run_job(dark, tmp_path / "dark_run", seed=6)
    with pytest.raises(ValueError, match=r"other data .*data\.measurement as read: the same "
                       r"files with other settings"):
        combine_runs([runs[0], tmp_path / "dark_run"], out)
    # a run that never finished (no results) and a folder that holds no run
    rec = json.loads((runs[1] / "run.json").read_text())
    del rec["results"]
    rec["status"], rec["finish_reason"] = "running", None
    (runs[1] / "run.json").write_text(json.dumps(rec))
    from recon.udn.rundir import RunLock

    with RunLock(runs[1]), pytest.raises(ValueError, match="has not finished"):
        combine_runs([runs[0], runs[1]], out)  # running: its process holds the run folder
    with pytest.raises(ValueError, match="was interrupted"):
        combine_runs([runs[0], runs[1]], out)  # nothing holds it: killed
    with pytest.raises(FileNotFoundError, match="no UDN run here"):
        combine_runs([runs[0], tmp_path], out)
    assert not out.exists()
    assert cli_main(["jobs", "combine", str(runs[0]), str(runs[1]), "--out", str(out)]) != 0
    assert "was interrupted" in capsys.readouterr().err


def test_combine_never_writes_into_a_member_nor_trusts_a_replaced_result(three_runs, tmp_path):
    """A member's files are inputs: --out inside a member's folder is refused (it destroyed the
    member's best estimate), and a result file that is not the one the run wrote (an earlier
    ensemble, a FISTA result copied there) is refused by its data hash."""
    import shutil

    _spec, runs = three_runs
    best = (runs[0] / "best.tif").read_bytes()
    with pytest.raises(ValueError, match="into the run folder"):
        combine_runs(runs[:2], runs[0] / "best.tif")
    assert (runs[0] / "best.tif").read_bytes() == best
    combine_runs(runs[:2], tmp_path / "ens.tif")
    # another run's UDN result under its name: refused by the data hash its run recorded
    saved = (runs[1] / "best.tif").read_bytes()
    shutil.copy(runs[2] / "best.tif", runs[1] / "best.tif")
    with pytest.raises(ValueError, match="is not the best estimate this run wrote"):
        combine_runs(runs[:2], tmp_path / "ens2.tif")
    # an ensemble under its name: refused by its method
    shutil.copy(tmp_path / "ens.tif", runs[1] / "best.tif")
    with pytest.raises(ValueError, match="is not the best estimate this run wrote"):
        combine_runs(runs[:2], tmp_path / "ens2.tif")
    (runs[1] / "best.tif").write_bytes(saved)
    combine_runs(runs[:2], tmp_path / "ens2.tif")


def test_combine_never_writes_over_a_members_input_nor_takes_an_unfinished_run(
        three_runs, tiny_data, tmp_path, capsys):
    """'jobs combine ... --out psf.npy --overwrite' replaced the members' PSF with the
    ensemble (and the runs could not be resumed: 'data.psf changed'); a run still running, or
    killed, was averaged with the best estimate of an earlier session."""
    _spec, runs = three_runs
    psf = (tiny_data / "psf.npy").read_bytes()
    code = cli_main(["jobs", "combine", str(runs[0]), str(runs[1]), "--out",
                     str(tiny_data / "psf.npy"), "--overwrite"])
    err = capsys.readouterr().err
    assert code == 2 and "refusing to write" in err and "of " + str(runs[0]) in err, err
    assert (tiny_data / "psf.npy").read_bytes() == psf
    rec_path = runs[1] / "run.json"
    rec = json.loads(rec_path.read_text())
    rec["status"] = "running"  # as a live run, or one killed by the system, leaves it
    rec_path.write_text(json.dumps(rec))
    from recon.udn.rundir import RunLock

    with RunLock(runs[1]), pytest.raises(  # running: its process holds the run folder
            ValueError, match=r"the run has not finished \(status running\)"):
        combine_runs(runs[:2], tmp_path / "ens.tif")
    assert not (tmp_path / "ens.tif").exists()
    # killed (nothing holds its folder, whatever its recorded pid is now): not "wait for it"
    # (jobs status said interrupted meanwhile)
    with pytest.raises(ValueError, match=r"the run was interrupted \(no process holds its "
                       r"folder\).*resume it \('lenslesscam jobs resume "):
        combine_runs(runs[:2], tmp_path / "ens.tif")


def test_combine_with_fista_is_half_the_runs_and_half_recon_fistas_result(three_runs, tiny_data,
                                                                           tmp_path, capsys):
    """--with-fista: one run is enough; the result is 0.5 x its iterate mean (mean.tif; its
    best with --estimate best, or for a run without a mean) + 0.5 x what `recon fista` with its
    defaults gives on the same inputs (the same loader, tau rule and solver), recorded in the
    metadata; inputs changed since the run are refused, nothing written."""
    _spec, runs = three_runs
    out = tmp_path / "wf.tif"
    assert cli_main(["jobs", "combine", str(runs[0]), "--with-fista", "--estimate", "best",
                     "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "ensemble of 1 run and FISTA-TV" in printed and "FISTA-TV  tau" in printed
    x, meta = read_reconstruction(out)
    assert meta["method"] == "udn-ensemble+fista-tv" and meta["fista"]["weight"] == 0.5
    assert meta["estimate"] == "best"
    assert cli_main(["recon", "fista", "--psf", str(tiny_data / "psf.npy"), "--meas",
                     str(tiny_data / "meas.npy"), "--mask", str(tiny_data / "mask.npy"),
                     "--out", str(tmp_path / "f.tif")]) == 0
    capsys.readouterr()
    xf, fmeta = read_reconstruction(tmp_path / "f.tif")
    assert meta["fista"]["tau"] == fmeta["parameters"]["tau"]
    assert meta["fista"]["iterations"] == fmeta["iterations"]
    best = read_reconstruction(runs[0] / "best.tif")[0]
    # one computation in two processes' thread counts: float sums may differ in the last bits
    np.testing.assert_allclose(x, 0.5 * best + 0.5 * xf.reshape(best.shape), rtol=0,
                               atol=1e-4 * float(np.abs(best).max()))
    assert not np.allclose(x, best, atol=1e-3 * float(np.abs(best).max()))
    # the default: each run's iterate mean (the estimate at 20, 40, 60), then half and half
    assert cli_main(["jobs", "combine", str(runs[0]), "--with-fista", "--out",
                     str(tmp_path / "wfm.tif")]) == 0
    assert "mean of 3 estimates, the last at iteration 60 of 60" in capsys.readouterr().out
    xm, mmeta = read_reconstruction(tmp_path / "wfm.tif")
    mean0, m0meta = read_reconstruction(runs[0] / "mean.tif")
    assert mmeta["estimate"] == "mean" and m0meta["mean_count"] == 3
    assert m0meta["average_every"] == 20 and mmeta["members"][0]["mean_count"] == 3
    np.testing.assert_allclose(xm, 0.5 * mean0 + 0.5 * xf.reshape(best.shape), rtol=0,
                               atol=1e-4 * float(np.abs(best).max()))
    assert not np.allclose(mean0, best, atol=1e-3 * float(np.abs(best).max()))
    # the same run with output.with_fista (the default) writes that average itself at its end
    on = write_spec(tiny_data, "on.toml", stopping={"max_iter": 60, "patience": 1000},
                    output={"average_every": 20, "with_fista": True})
    run_job(on, tmp_path / "w0", seed=0)
    np.testing.assert_array_equal(read_reconstruction(tmp_path / "w0" / "mean.tif")[0], mean0)
    xw, wmeta = read_reconstruction(tmp_path / "w0" / "with_fista.tif")
    np.testing.assert_allclose(xw, xm, rtol=0, atol=1e-4 * float(np.abs(best).max()))
    assert wmeta["method"] == "udn+fista-tv" and wmeta["udn_estimate"] == "mean"
    assert wmeta["fista"]["tau"] == mmeta["fista"]["tau"]
    res0 = json.loads((tmp_path / "w0" / "run.json").read_text())["results"]
    assert res0["with_fista"] == "with_fista.tif" and res0["with_fista_estimate"] == "mean"
    assert res0["fista"]["tau"] == mmeta["fista"]["tau"]
    assert res0["scores"]["with_fista"]["psnr"] == pytest.approx(
        psnr(np.load(tiny_data / "truth.npy"), gain_fit(np.load(tiny_data / "truth.npy"),
                                                        xw)[0]), abs=1e-3)
    # two runs: the mean of the runs, then half and half
    res = combine_runs(runs[:2], tmp_path / "wf2.tif", with_fista=True)
    means = [read_reconstruction(r / "mean.tif")[0] for r in runs[:2]]
    np.testing.assert_allclose(res.x, 0.5 * np.mean(means, axis=0) + 0.5 * xf.reshape(best.shape),
                               rtol=0, atol=1e-4 * float(np.abs(best).max()))
    assert res.estimate == "mean"
    # a run from before the iterate average (no mean in its record, no average_every in its
    # spec): the best estimates of all, and a note that says why
    rec_path = runs[1] / "run.json"
    rec = json.loads(rec_path.read_text())
    del rec["results"]["mean"]
    del rec["spec"]["output"]["average_every"]
    rec_path.write_text(json.dumps(rec))
    res = combine_runs(runs[:2], tmp_path / "wf3.tif", with_fista=True)
    bests = [read_reconstruction(r / "best.tif")[0] for r in runs[:2]]
    assert res.estimate == "best"
    assert res.note is not None and "1 of 2 run(s) have none" in res.note
    assert f"{runs[1]} (a run from before the iterate average)" in res.note
    assert read_reconstruction(tmp_path / "wf3.tif")[1]["estimate_note"] == res.note
    np.testing.assert_allclose(res.x, 0.5 * np.mean(bests, axis=0) + 0.5 * xf.reshape(best.shape),
                               rtol=0, atol=1e-4 * float(np.abs(best).max()))
    with pytest.raises(ValueError, match=r"wrote no mean estimate \(a run from before the "
                       r"iterate average\); use --estimate best"):
        combine_runs(runs[1:2], tmp_path / "never.tif", estimate="mean", with_fista=True)
    # a run shorter than its average_every: says how to get one
    rec["spec"]["output"]["average_every"] = 100
    rec_path.write_text(json.dumps(rec))
    with pytest.raises(ValueError, match=r"it ran 60 iterations, fewer than its average_every "
                       r"100: 'lenslesscam jobs resume RUN --max-iter 100'"):
        combine_runs(runs[1:2], tmp_path / "never.tif", estimate="mean", with_fista=True)
    # a mean of one estimate (a run just past average_every) is one early iterate: not used
    rec0 = json.loads((runs[0] / "run.json").read_text())
    rec0["results"].update(mean_count=1, mean_last_iteration=20)
    (runs[0] / "run.json").write_text(json.dumps(rec0))
    res = combine_runs(runs[:1], tmp_path / "wf5.tif", with_fista=True)
    assert res.estimate == "best"
    assert "its mean is the one estimate of iteration 20, not an average" in str(res.note)
    # a mean.tif deleted since: auto takes the best estimates, and says so
    (runs[0] / "mean.tif").unlink()
    res = combine_runs(runs[:1], tmp_path / "wf4.tif", with_fista=True)
    assert res.estimate == "best" and "mean.tif is missing" in str(res.note)
    # without it one run is still refused; inputs changed since the run are refused
    with pytest.raises(ValueError, match="at least two runs"):
        combine_runs(runs[:1], tmp_path / "never.tif")
    meas = np.load(tiny_data / "meas.npy")
    np.save(tiny_data / "meas.npy", meas * 1.01)
    with pytest.raises(ValueError, match=r"data.measurement changed since the run"):
        combine_runs(runs[:1], tmp_path / "never.tif", with_fista=True)
    assert not (tmp_path / "never.tif").exists()


def test_with_fista_is_written_only_when_asked_and_the_run_ended(tiny_data, tmp_path):
    """output.with_fista false: no with_fista.tif; a cancelled run: none either (its estimate
    is not its last); a run whose mean holds one estimate averages its best instead."""
    off = write_spec(tiny_data, "off.toml", stopping={"max_iter": 6},
                     output={"with_fista": False})
    run_job(off, tmp_path / "off")
    assert not (tmp_path / "off" / "with_fista.tif").exists()
    assert "with_fista" not in json.loads((tmp_path / "off" / "run.json").read_text())["results"]
    on = write_spec(tiny_data, "on.toml", stopping={"max_iter": 30},
                    output={"average_every": 20, "with_fista": True})
    calls = iter(range(10**6))
    run_job(on, tmp_path / "cancelled", cancel=lambda: next(calls) >= 5)
    rec = json.loads((tmp_path / "cancelled" / "run.json").read_text())
    assert rec["finish_reason"] == "cancelled" and "with_fista" not in rec["results"]
    assert not (tmp_path / "cancelled" / "with_fista.tif").exists()
    run_job(on, tmp_path / "one")  # one estimate averaged (iteration 20 of 30): best
    res = json.loads((tmp_path / "one" / "run.json").read_text())["results"]
    assert res["mean_count"] == 1 and res["with_fista_estimate"] == "best"
