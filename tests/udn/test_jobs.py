"""Jobs: run folders, records, spec errors, status, disk full, NaN, SIGTERM, kill + resume."""

from __future__ import annotations

import errno
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from app.cli import main as cli_main
from recon.io import read_reconstruction
from recon.udn.jobs import (
    JobError,
    format_status,
    job_status,
    load_checkpoint,
    read_loss_rows,
    request_cancel,
    resume_job,
    run_job,
)
from recon.udn.memory import MemoryRefusal
from recon.udn.runner import NumericalError
from recon.udn.spec import SpecError
from tests.udn.conftest import write_spec
from tests.udn.jobrunner import STALL_ENV, ServerChild

REPO = Path(__file__).resolve().parents[2]


def record(run_dir: Path) -> dict:
    return json.loads((run_dir / "run.json").read_text())


def test_run_folder_layout_and_record(tiny_data, tmp_path):
    spec = write_spec(tiny_data, stopping={"max_iter": 40})
    out = tmp_path / "run"
    seen = []
    outcome = run_job(spec, out, progress=seen.append)
    assert outcome.finish_reason == "completed" and outcome.iterations == 40
    assert [s.iteration for s in seen] == list(range(1, 41))
    names = {p.relative_to(out).as_posix() for p in out.rglob("*")}
    for n in ("job.toml", "run.json", "loss.csv", "checkpoint.pt", "final.tif", "final.png",
              "best.tif", "best.png", "previews/iter_0000020.png", "previews/iter_0000040.png"):
        assert n in names, n
    assert not any(n.startswith(".") or ".tmp" in n for n in names)  # no temp files left
    assert (out / "job.toml").read_text() == spec.read_text()
    rec = record(out)
    assert rec["format"] == "lenslesscam.udn_run" and rec["format_version"] >= 1
    assert rec["status"] == "finished" and rec["finish_reason"] == "completed"
    assert rec["detail"].startswith("reached the iteration limit") and rec["error"] is None
    assert rec["spec"]["data"]["psf"] == str(tiny_data / "psf.npy")
    assert set(rec["inputs"]) == {"psf", "measurement", "mask", "truth"}
    assert all(len(v["file_hash"]) == 16 for v in rec["inputs"].values())
    assert "torch" in rec["provenance"]["versions"]
    assert rec["device"]["device"] == "cpu" and rec["device"]["threads"] == 1
    assert rec["timings"]["per_iteration_s"] > 0 and rec["checkpoint"]["iteration"] == 40
    assert rec["memory"]["estimate"]["total_bytes"] > 0
    assert rec["results"]["scores"]["best"]["psnr"] > 5
    text = (out / "loss.csv").read_text()
    assert text.startswith("# format: lenslesscam.udn_loss\n# format_version: 1\n")
    rows = [ln for ln in text.splitlines() if not ln.startswith("#")]
    assert rows[0].startswith("iteration,loss,heldout") and len(rows) == 41
    assert [int(r["iteration"]) for r in read_loss_rows(out)] == list(range(1, 41))
    x, meta = read_reconstruction(out / "best.tif")
    assert x.shape == (1, 1, 24, 28)
    assert meta["method"] == "udn" and meta["estimate"] == "best"
    assert meta["inputs"]["psf"]["file_hash"] == rec["inputs"]["psf"]["file_hash"]
    ck = load_checkpoint(out / "checkpoint.pt")
    assert ck["iteration"] == 40 and ck["format"] == "lenslesscam.udn_checkpoint"


def test_a_run_that_ends_at_its_limit_still_improving_says_so(tiny_data, tmp_path):
    """At a limit, a run whose held-out best is in its last tenth of iterations was still
    improving (docs/udn.md: at full resolution, 11 of 12 real cases ended so): the detail says
    so with the command that continues it, and the results record it; a run whose held-out
    error stopped improving long before its limit does not say so."""
    out = tmp_path / "short"
    run_job(write_spec(tiny_data, stopping={"max_iter": 30}), out)
    rec = record(out)
    res = rec["results"]
    assert res["still_improving"] == (res["best_iteration"] > 27)
    assert res["still_improving"], res  # 30 iterations: the held-out error is still falling
    assert rec["detail"] == (
        f"reached the iteration limit; the held-out error was still improving (best at "
        f"iteration {res['best_iteration']} of 30): more iterations would likely give a better "
        f"result: lenslesscam jobs resume {out} --max-iter 60")
    # continued as the detail says: it goes on from iteration 30
    assert resume_job(out, max_iter=60).iterations == 60
    # a long run at a high learning rate, its patience beyond its limit: the held-out best
    # comes long before the end (iteration 345 of 600 here; anything up to 540 passes)
    out2 = tmp_path / "long"
    run_job(write_spec(tiny_data, stopping={"max_iter": 600, "patience": 1000},
                       optimizer={"lr": 0.1}), out2)
    rec2 = record(out2)
    assert rec2["results"]["best_iteration"] <= 540
    assert rec2["results"]["still_improving"] is False
    assert rec2["detail"] == "reached the iteration limit"


def cli_fails(argv, capsys) -> str:
    rc = cli_main(argv)
    err = capsys.readouterr().err
    assert rc == 2, err
    assert len(err.strip().splitlines()) == 1, err  # one line, no traceback
    return err


def test_spec_with_an_unknown_key(tiny_data, tmp_path, capsys):
    spec = write_spec(tiny_data, network={"chanels": 8})
    out = tmp_path / "run"
    err = cli_fails(["jobs", "run", str(spec), "--out", str(out)], capsys)
    assert "unknown key 'network.chanels'" in err and "did you mean 'channels'" in err
    rec = record(out)
    assert rec["finish_reason"] == "failed" and rec["error"]["type"] == "SpecError"
    assert "network.chanels" in rec["error"]["message"]
    with pytest.raises(SpecError, match="unknown section"):
        run_job(write_spec(tiny_data, name="b.toml", netwrok={"a": 1}), tmp_path / "run2")


def test_spec_naming_a_missing_file(tiny_data, tmp_path, capsys):
    spec = write_spec(tiny_data, data={"psf": "nowhere/psf.npy"})
    out = tmp_path / "run"
    err = cli_fails(["jobs", "run", str(spec), "--out", str(out)], capsys)
    assert "data.psf" in err and str(tiny_data / "nowhere" / "psf.npy") in err
    rec = record(out)
    assert rec["finish_reason"] == "failed" and "data.psf" in rec["error"]["message"]
    assert rec["error"]["type"] == "FileNotFoundError"


def test_wrong_shaped_shutter(tiny_data, tmp_path, capsys):
    np.save(tiny_data / "shutter.npy", np.ones((4, 30)))  # the sensor has 24 rows
    spec = write_spec(tiny_data, data={"model": "video", "shutter": "shutter.npy",
                                       "truth": None})
    out = tmp_path / "run"
    err = cli_fails(["jobs", "run", str(spec), "--out", str(out)], capsys)
    assert "data.shutter" in err and "(4, 30)" in err and "(K, 24)" in err
    rec = record(out)
    assert rec["finish_reason"] == "failed" and "(4, 30)" in rec["error"]["message"]


def test_video_job_with_a_right_shutter_runs_both_networks(tiny_data, tmp_path):
    shutter = np.zeros((3, 24))
    for k in range(3):
        shutter[k, k * 8 : (k + 1) * 8] = 1.0
    np.save(tiny_data / "shutter.npy", shutter)
    for variant in ("frames", "3d"):
        spec = write_spec(tiny_data, name=f"{variant}.toml",
                          data={"model": "video", "shutter": "shutter.npy", "truth": None},
                          network={"variant": variant}, stopping={"max_iter": 4})
        outcome = run_job(spec, tmp_path / variant)
        assert outcome.finish_reason == "completed"
        x, meta = read_reconstruction(tmp_path / variant / "final.tif")
        assert x.shape == (1, 3, 24, 28) and meta["kind"] == "video"
        assert (tmp_path / variant / "final.gif").exists()


def test_memory_refusal_fails_the_job_with_a_record(tiny_data, tmp_path):
    spec = write_spec(tiny_data, device={"max_memory": "100KB"})
    with pytest.raises(MemoryRefusal, match="gradient_checkpointing"):
        run_job(spec, tmp_path / "run")
    rec = record(tmp_path / "run")
    assert rec["finish_reason"] == "failed" and rec["error"]["type"] == "MemoryRefusal"
    # it never ran an iteration: the folder takes a corrected spec
    assert run_job(write_spec(tiny_data, "ok.toml", stopping={"max_iter": 2}),
                   tmp_path / "run").iterations == 2


def test_status_of_finished_and_interrupted_runs(tiny_data, tmp_path, capsys):
    out = tmp_path / "run"
    run_job(write_spec(tiny_data), out)
    assert cli_main(["jobs", "status", str(out)]) == 0
    text = capsys.readouterr().out
    for part in ("finished: completed", "iteration:  40 / 40", "device:     cpu (1 threads, "
                 "float32)", "checkpoint: 40", "previews/iter_0000040.png", "(tiny)"):
        assert part in text, part
    assert cli_main(["jobs", "status", str(out), "--json"]) == 0
    js = json.loads(capsys.readouterr().out)
    assert js["state"] == "finished" and js["iteration"] == 40
    # a record left 'running' by a process that no longer exists reads as interrupted
    rec = record(out)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    rec.update(status="running", finish_reason=None, pid=dead.pid)
    (out / "run.json").write_text(json.dumps(rec))
    st = job_status(out)
    assert st.state == "interrupted"
    assert "jobs resume" in format_status(st)
    with pytest.raises(FileNotFoundError, match="no UDN run"):
        job_status(tmp_path)


def test_disk_full_during_a_checkpoint_keeps_the_previous_one(tiny_data, tmp_path,
                                                              monkeypatch):
    from recon.udn import rundir

    real_write = rundir._write_bytes
    calls = {"n": 0}

    def write(fh, data):
        calls["n"] += 1
        if calls["n"] >= 2:  # the second checkpoint: half a file, then the disk is full
            fh.write(data[:100])
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real_write(fh, data)

    monkeypatch.setattr(rundir, "_write_bytes", write)
    out = tmp_path / "run"
    with pytest.raises(JobError, match="disk full"):
        run_job(write_spec(tiny_data, stopping={"max_iter": 60}), out)
    monkeypatch.setattr(rundir, "_write_bytes", real_write)
    ck = load_checkpoint(out / "checkpoint.pt")  # intact and readable
    assert ck["iteration"] == 20
    rec = record(out)
    assert rec["finish_reason"] == "failed" and rec["error"]["type"] == "DiskFull"
    assert f"disk full: no space left on the device of {out}" in rec["error"]["message"]
    assert "last good checkpoint (iteration 20) is kept" in rec["error"]["message"]
    assert not [p for p in out.iterdir() if ".tmp" in p.name]
    # and the run can be resumed from that checkpoint
    outcome = resume_job(out)
    assert outcome.finish_reason == "completed" and outcome.iterations == 60


def test_nan_in_the_loss_fails_with_a_record(tiny_data, tmp_path, capsys):
    spec = write_spec(tiny_data, optimizer={"lr": 1e30, "max_backoffs": 2})
    out = tmp_path / "run"
    err = cli_fails(["jobs", "run", str(spec), "--out", str(out)], capsys)
    assert "not finite" in err and "run.json" in err
    rec = record(out)
    assert rec["finish_reason"] == "failed" and rec["error"]["type"] == "NumericalError"
    assert "not finite at iteration" in rec["error"]["message"]
    assert "optimizer.lr = 1e+30 (default 0.01); lower it" in rec["error"]["message"]
    # the two restores before giving up (and the tiny case's note on its few held-out pixels)
    assert len([n for n in rec["notes"] if "held-out pixels choose" not in n]) == 2
    with pytest.raises(NumericalError):
        run_job(spec, tmp_path / "run2")


def test_cancel_file_stops_the_run_cleanly(tiny_data, tmp_path):
    out = tmp_path / "run"

    def progress(s):
        if s.iteration == 7:
            request_cancel(out)

    outcome = run_job(write_spec(tiny_data, stopping={"max_iter": 1000}), out,
                      progress=progress)
    assert outcome.finish_reason == "cancelled" and outcome.iterations == 7
    rec = record(out)
    assert rec["checkpoint"]["iteration"] == outcome.iterations
    assert "CANCEL file" in rec["detail"]
    assert (out / "final.tif").exists() and not (out / "CANCEL").exists()
    with pytest.raises(ValueError, match="not running"):
        request_cancel(out)
    # resuming a cancelled run continues it
    assert resume_job(out, max_iter=12).iterations == 12


def test_resume_rules(tiny_data, tmp_path):
    out = tmp_path / "run"
    run_job(write_spec(tiny_data, stopping={"max_iter": 20}), out)
    with pytest.raises(ValueError, match="--max-iter"):
        resume_job(out)
    outcome = resume_job(out, max_iter=30)
    assert outcome.iterations == 30 and record(out)["resumes"] == 1
    assert len(read_loss_rows(out)) == 30
    with pytest.raises(ValueError, match="already holds a run"):
        run_job(write_spec(tiny_data), out)
    np.save(tiny_data / "meas.npy", np.load(tiny_data / "meas.npy") * 2)
    with pytest.raises(ValueError, match="changed since the run started"):
        resume_job(out, max_iter=40)


def _env(**extra):
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.update(extra)
    return env


def _wait_for(cond, proc, timeout=60.0, log=None):
    t0 = time.monotonic()
    while not cond():
        assert proc.poll() is None, log.read_text() if log else proc.communicate()
        assert time.monotonic() - t0 < timeout, "timed out"
        time.sleep(0.02)


def _progress_iteration(out: Path) -> int:
    try:
        return int(record(out).get("progress", {}).get("iteration", 0))
    except (FileNotFoundError, ValueError):
        return 0


def test_kill_and_resume_ends_with_identical_weights(tiny_data, tmp_path, job_server):
    """2N iterations in one go == N, SIGKILL (mid-interval), resume for the rest."""
    spec = write_spec(tiny_data, stopping={"max_iter": 40}, optimizer={"snapshot_every": 15},
                      output={"checkpoint_every": 20, "preview_every": 10})
    whole = run_job(spec, tmp_path / "whole")
    assert whole.iterations == 40
    out = tmp_path / "killed"
    # real processes forked by the fork server (tests/udn/jobrunner.py, torch imported once);
    # the job stalls after iteration 27 (checkpoint at 20, progress written at 27): a test hook
    # of the fork server's children
    pid, log = job_server.start(["jobs", "run", spec, "--out", out, "--quiet"],
                                {STALL_ENV: "27"}, tmp_path / "run.log")
    proc = ServerChild(job_server, pid)
    try:
        _wait_for(lambda: _progress_iteration(out) == 27, proc, log=log)
    finally:
        proc.kill()
    assert proc.wait(60) == -signal.SIGKILL
    assert record(out)["checkpoint"]["iteration"] == 20
    assert len(read_loss_rows(out)) == 27
    pid, log = job_server.start(["jobs", "resume", out, "--quiet"], {}, tmp_path / "resume.log")
    assert job_server.wait(pid) == 0, log.read_text(errors="replace")
    a = load_checkpoint(tmp_path / "whole" / "checkpoint.pt")["state"]
    b = load_checkpoint(out / "checkpoint.pt")["state"]
    assert a["iteration"] == b["iteration"] == 40
    for k in a["G"]:
        assert torch.equal(a["G"][k], b["G"][k]), k
    for k in ("ema", "best", "heldout"):
        assert torch.equal(a[k], b[k]), k
    assert a["best_iteration"] == b["best_iteration"]
    for sa, sb in zip(a["opt"]["state"].values(), b["opt"]["state"].values(), strict=True):
        assert all(torch.equal(sa[k], sb[k]) for k in sa)
    ra, rb = ([float(r["loss"]) for r in read_loss_rows(p)] for p in (tmp_path / "whole", out))
    np.testing.assert_array_equal(ra, rb)  # the same history, no gaps
    rec = record(out)
    assert rec["finish_reason"] == "completed" and rec["resumes"] == 1
    assert [s["start_iteration"] for s in rec["sessions"]] == [0, 20]


@pytest.mark.parametrize("how", ["SIGTERM", "jobs cancel --signal"])
def test_sigterm_cancels_cleanly_with_a_final_checkpoint(tiny_data, tmp_path, how):
    """A SIGTERM, sent directly or by jobs cancel --signal (to the pid in the run lock's
    holder line), stops the run at the next iteration with a final checkpoint."""
    spec = write_spec(tiny_data, stopping={"max_iter": 100000})
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "app", "jobs", "run", str(spec), "--out",
                             str(out), "--quiet"], cwd=REPO, env=_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _wait_for(lambda: _progress_iteration(out) >= 5, proc)
        assert job_status(out).state == "running"
        if how == "SIGTERM":
            proc.send_signal(signal.SIGTERM)
        else:
            assert f"SIGTERM sent to pid {proc.pid}" in request_cancel(out, send_signal=True)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 3, stderr
    assert json.loads(stdout)["finish_reason"] == "cancelled"
    rec = record(out)
    assert rec["finish_reason"] == "cancelled" and rec["status"] == "finished"
    assert "signal" in rec["detail"] or (how != "SIGTERM" and "CANCEL file" in rec["detail"])
    n = rec["progress"]["iteration"]
    assert n >= 5 and load_checkpoint(out / "checkpoint.pt")["iteration"] == n
    assert (out / "final.tif").exists() and (out / "best.tif").exists()


def test_recon_udn_one_shot(tiny_data, tmp_path, capsys):
    out = tmp_path / "oneshot"
    argv = ["recon", "udn", "--psf", str(tiny_data / "psf.npy"), "--meas",
            str(tiny_data / "meas.npy"), "--mask", str(tiny_data / "mask.npy"), "--iters", "6",
            "--scales", "3", "--net-channels", "8", "--input-channels", "4", "--threads", "1",
            "--preview-every", "3", "--quiet", "--out", str(out)]
    assert cli_main(argv) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["finish_reason"] == "completed" and summary["iterations"] == 6
    rec = record(out)
    assert rec["spec"]["network"]["channels"] == 8
    assert rec["spec"]["data"]["mask"] == str(tiny_data / "mask.npy")
    assert "[network]" in (out / "job.toml").read_text()
    spec_file = tmp_path / "written.toml"
    assert cli_main([*argv[:-2], "--write-spec", str(spec_file)]) == 0
    capsys.readouterr()
    assert run_job(spec_file, tmp_path / "from_spec").iterations == 6


def test_a_seed_beyond_32_bits_is_a_spec_error(tiny_data, tmp_path):
    with pytest.raises(SpecError, match=r"optimizer\.seed must be <= 4294967295"):
        run_job(write_spec(tiny_data, optimizer={"seed": 2**64}), tmp_path / "run")


@pytest.mark.parametrize(("section", "key", "value", "words"), [
    # a config's range message named no key ('[optimizer]/[stopping]/[device] lr must be > 0')
    ("optimizer", "lr", -1.0, "optimizer.lr must be > 0"),
    # 'value cannot be converted to type float without overflow', no key named
    ("optimizer", "lr", 1e300, "optimizer.lr must be within float32's range"),
    ("stopping", "max_iter", 2**70, "stopping.max_iter must be at most 2**62 in magnitude"),
    ("output", "status_seconds", -1.0, "output.status_seconds must be >= 0"),
    ("output", "checkpoint_minutes", -5.0, "output.checkpoint_minutes must be >= 0"),
    # blamed on data.field: its value 'sensor' was found in "the sensor's black offset"
    ("data", "dark", -1.0, "data.dark must be 'auto', a dark-frame file or a finite number >= 0"),
])
def test_a_bad_spec_value_names_its_key(tiny_data, tmp_path, section, key, value, words):
    with pytest.raises(SpecError, match=re.escape(words)):
        run_job(write_spec(tiny_data, **{section: {key: value}}), tmp_path / "run")


def test_a_spec_that_is_not_toml_makes_no_run_folder(tiny_data, tmp_path, capsys):
    """A spec that is not UTF-8 was refused before anything was written; one that is not TOML
    left a failed run folder (job.toml, run.json, run.lock): now refused alike."""
    spec = write_spec(tiny_data, stopping={"max_iter": 2})
    bad = spec.parent / "bad.toml"
    bad.write_text(spec.read_text().replace("[stopping]", "[stopping", 1))
    with pytest.raises(SpecError, match=r"bad\.toml: not valid TOML: Expected ']'"):
        run_job(bad, tmp_path / "run")
    assert not (tmp_path / "run").exists()
    # into a folder holding an earlier run: its record is not this command's to point at
    run_job(spec, tmp_path / "done")
    assert cli_main(["jobs", "run", str(bad), "--out", str(tmp_path / "done")]) == 2
    err = capsys.readouterr().err
    assert "not valid TOML" in err and "run record" not in err, err


def test_a_spec_with_a_byte_order_mark_runs_and_a_folder_is_not_a_spec(tiny_data, tmp_path):
    """A spec saved with a UTF-8 byte-order mark was 'Invalid statement at line 1, column 1';
    'jobs run DIR' said 'job spec not found' for a folder that is there."""
    from recon.udn.spec import load_spec

    spec = write_spec(tiny_data, stopping={"max_iter": 2})
    bom = spec.parent / "bom.toml"  # beside it: its paths are relative to the spec
    bom.write_bytes(b"\xef\xbb\xbf" + spec.read_bytes())
    assert load_spec(bom)["stopping"]["max_iter"] == 2
    assert run_job(bom, tmp_path / "run").iterations == 2
    with pytest.raises(FileNotFoundError, match="is a folder, not a job spec"):
        run_job(tmp_path, tmp_path / "run2")


def test_spec_headroom_reaches_the_runner_config(tiny_data, tmp_path):
    from recon.udn.spec import load_spec, udn_config

    spec = load_spec(write_spec(tiny_data, "h.toml", optimizer={"headroom": 2.5}))
    assert udn_config(spec).headroom == 2.5
    assert udn_config(load_spec(write_spec(tiny_data, "d.toml"))).headroom == 1.0
    with pytest.raises((SpecError, ValueError), match="headroom"):
        udn_config(load_spec(write_spec(tiny_data, "bad.toml", optimizer={"headroom": -1.0})))


def test_global_threads_reach_jobs_run_resume_and_recon_udn(tiny_data, tmp_path, capsys):
    """``lenslesscam --threads N`` sets the job's torch threads (the spec's count is the
    default), says so in the record, and ``recon udn`` writes it into the spec it runs."""
    before = torch.get_num_threads()
    try:
        spec = write_spec(tiny_data, stopping={"max_iter": 4})
        assert "threads = 1" in spec.read_text()
        out = tmp_path / "run"
        assert cli_main(["--threads", "2", "jobs", "run", str(spec), "--out", str(out),
                         "--quiet"]) == 0
        dev = record(out)["device"]
        assert dev["threads"] == 2 and "over the spec's 1" in dev["threads_reason"]
        assert cli_main(["--threads", "3", "jobs", "resume", str(out), "--max-iter", "6",
                         "--quiet"]) == 0
        assert record(out)["device"]["threads"] == 3
        # without the global option the spec's count applies again
        assert cli_main(["jobs", "run", str(spec), "--out", str(tmp_path / "plain"),
                         "--quiet"]) == 0
        assert record(tmp_path / "plain")["device"]["threads"] == 1
        one = tmp_path / "oneshot"
        assert cli_main(["--threads", "2", "recon", "udn", "--psf", str(tiny_data / "psf.npy"),
                         "--meas", str(tiny_data / "meas.npy"), "--mask",
                         str(tiny_data / "mask.npy"), "--iters", "2", "--scales", "3",
                         "--net-channels", "8", "--input-channels", "4", "--quiet", "--out",
                         str(one)]) == 0
        assert record(one)["spec"]["device"]["threads"] == 2
        assert "threads = 2" in (one / "job.toml").read_text()
    finally:
        torch.set_num_threads(before)
        capsys.readouterr()


def test_a_run_never_starts_in_a_folder_of_other_files(tiny_data, tmp_path, capsys):
    """A folder with files that are not a run's is refused before anything is written (a run
    overwrote final.tif, loss.csv and job.toml there, and an input named best.tif); a folder
    left by a start refused on its spec may be used again."""
    spec = write_spec(tiny_data, stopping={"max_iter": 3})
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "loss.csv").write_text("my notes\n")
    with pytest.raises(ValueError, match=r"is not empty and holds no run \(1 entries, e\.g\. "
                                         r"loss\.csv\)"):
        run_job(spec, mine)
    assert sorted(p.name for p in mine.iterdir()) == ["loss.csv"]
    assert (mine / "loss.csv").read_text() == "my notes\n"
    # recon udn with its measurement inside --out: refused, the measurement untouched
    inside = tmp_path / "inside"
    inside.mkdir()
    meas = np.load(tiny_data / "meas.npy")
    np.save(inside / "meas.npy", meas)
    argv = ["recon", "udn", "--psf", str(tiny_data / "psf.npy"), "--meas",
            str(inside / "meas.npy"), "--iters", "2", "--scales", "2", "--net-channels", "4",
            "--input-channels", "4", "--threads", "1", "--quiet", "--out", str(inside)]
    assert cli_main(argv) == 2
    assert "is not empty and holds no run" in capsys.readouterr().err
    assert np.array_equal(np.load(inside / "meas.npy"), meas)
    # a start refused on its spec leaves run.json and job.toml; the folder may be used again
    bad = write_spec(tiny_data, "bad.toml", stopping={"max_iter": -1})
    again = tmp_path / "again"
    with pytest.raises((SpecError, ValueError)):
        run_job(bad, again)
    assert record(again)["spec"] is None
    assert run_job(spec, again).iterations == 3
    assert record(again)["status"] == "finished"
    with pytest.raises(ValueError, match="already holds a run"):
        run_job(spec, again)
    # a start killed before its record (during setup) leaves the lock, its job.toml and maybe
    # a temporary file: the same spec starts there again (a batch retry), another does not
    killed = tmp_path / "killed"
    killed.mkdir()
    (killed / "job.toml").write_bytes(spec.read_bytes())
    (killed / "run.lock").write_text("pid 1 on gone\n")
    (killed / ".run.json.abc123.tmp").write_text("{")
    other = write_spec(tiny_data, "other.toml", stopping={"max_iter": 2})
    with pytest.raises(ValueError, match="is not empty and holds no run"):
        run_job(other, killed)
    assert run_job(spec, killed).iterations == 3
    assert not (killed / ".run.json.abc123.tmp").exists()


def test_cancel_signals_only_the_process_that_holds_the_run(tiny_data, tmp_path):
    """A record that still says running after its process was killed: cancel says the run is
    gone (it claimed success); a pid reused by an unrelated process is never signalled (it
    SIGTERMed whatever the record named)."""
    out = tmp_path / "run"
    run_job(write_spec(tiny_data, stopping={"max_iter": 3}), out)
    rec = record(out)
    rec["status"], rec["finish_reason"] = "running", None
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    rec["pid"] = dead.pid
    (out / "run.json").write_text(json.dumps(rec))
    with pytest.raises(ValueError, match="is gone: it was interrupted"):
        request_cancel(out, send_signal=True)
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        rec["pid"] = other.pid  # alive, but not the run: it does not hold the run's lock
        (out / "run.json").write_text(json.dumps(rec))
        with pytest.raises(ValueError, match="is gone: it was interrupted"):
            request_cancel(out, send_signal=True)
        time.sleep(0.2)
        assert other.poll() is None  # still alive
        # a resume in its setup holds the lock while the record still names the dead pid: the
        # cancel is taken, and the signal goes to the lock's holder (here this process, so
        # it is not sent: the test holds the lock itself and reads the holder's line)
        from recon.udn.rundir import RunLock, lock_holder

        lock = RunLock(out).acquire()
        try:
            holder = lock_holder(out)
            assert holder is not None and holder[0] == os.getpid()
            assert "stops at its next iteration" in request_cancel(out)
            assert (out / "CANCEL").exists()
        finally:
            lock.release()
    finally:
        other.kill()
        other.wait()



def test_loss_csv_reader_reads_old_files_and_refuses_newer_ones(tmp_path):
    """loss.csv has one reader (the job's resume and the app's plot): a file from before the
    header still reads; a newer format version is refused naming the file."""
    from recon.formats import FormatError
    from recon.udn.jobs import LOSS_FILE

    run = tmp_path / "run"
    run.mkdir()
    cols = "iteration,loss,heldout,best_heldout,lr,gain,elapsed_s,restored"
    (run / LOSS_FILE).write_text(f"{cols}\n1,0.5,0.4,0.4,0.01,1.0,0.1,0\n2,0.3,,0.4,0.01,1,0.2,0\n")
    rows = read_loss_rows(run)
    assert [r["iteration"] for r in rows] == ["1", "2"] and rows[1]["heldout"] == ""
    from app.gui.jobs_core import read_loss

    its, loss, held, problem = read_loss(tmp_path)  # the app's view: folder/run/loss.csv
    assert list(its) == [1, 2] and list(loss) == [0.5, 0.3] and np.isnan(held[1])
    assert problem is None
    (run / LOSS_FILE).write_text(f"# format: lenslesscam.udn_loss\n# format_version: 99\n{cols}\n")
    with pytest.raises(FormatError, match=r"loss.csv: UDN loss.csv format version 99 is newer"):
        read_loss_rows(run)
    its, _, _, problem = read_loss(tmp_path)  # the app shows no curve and says why
    assert its.size == 0 and "format version 99 is newer" in problem
    (run / LOSS_FILE).write_text(f"{cols}\nx,0.5,,,,,,\n")
    with pytest.raises(FormatError, match="line 2: field 'iteration'"):
        read_loss_rows(run)


def test_measurement_warnings_are_kept_in_the_run_record(tiny_data, tmp_path):
    """The loader's MeasurementWarnings (here: half the pixels are 0 and no mask is given)
    went to stderr only; run.json keeps them, and they are still emitted."""
    from recon.checks import MeasurementWarning

    spec = write_spec(tiny_data, data={"mask": None}, stopping={"max_iter": 4},
                      output={"checkpoint_every": 4, "preview_every": 0})
    out = tmp_path / "run"
    with pytest.warns(MeasurementWarning, match="pixels are 0 and no mask was given"):
        assert run_job(spec, out).finish_reason == "completed"
    rec = record(out)
    assert len(rec["warnings"]) == 1, rec["warnings"]
    assert "meas.npy" in rec["warnings"][0]
    assert "pixels are 0 and no mask was given" in rec["warnings"][0]
    # a run without anything to warn of says so
    clean = write_spec(tiny_data, name="clean.toml", stopping={"max_iter": 4},
                       output={"checkpoint_every": 4, "preview_every": 0})
    assert run_job(clean, tmp_path / "clean").finish_reason == "completed"
    assert record(tmp_path / "clean")["warnings"] == []


def test_a_truth_that_cannot_score_is_refused_before_the_run(tiny_data, tmp_path):
    """An all-zero truth (nothing to score against) made an overnight run end as failed,
    exit 2, after its last iteration; then it ran to its end and said "not scored". The
    problem loader now refuses it before the first iteration, naming the file, in the run's
    record (the folder can be used again)."""
    np.save(tiny_data / "truth.npy", np.zeros_like(np.load(tiny_data / "truth.npy")))
    out = tmp_path / "run"
    with pytest.raises(ValueError, match=r"truth\.npy is constant \(every value is 0"):
        run_job(write_spec(tiny_data, stopping={"max_iter": 5}), out)
    rec = record(out)
    assert rec["finish_reason"] == "failed" and "truth.npy is constant" in rec["detail"]
    assert not (out / "best.tif").exists() and not (out / "checkpoints").exists()


def test_a_runs_own_job_toml_runs_again_with_its_relative_paths(tiny_data, tmp_path):
    """The run folder's job.toml is the spec verbatim, relative paths and all: run again
    (another seed for an ensemble) it looked for the data beside itself, 'data.psf: file not
    found: run1/psf.npy'. Its relative paths are the original spec's, at any depth of reruns."""
    spec = write_spec(tiny_data, stopping={"max_iter": 3})
    run1, run2, run3 = (tmp_path / f"run{i}" for i in (1, 2, 3))
    run_job(spec, run1)
    assert record(run1)["spec_base"] == str(tiny_data.absolute())
    run_job(run1 / "job.toml", run2, seed=1)
    run_job(run2 / "job.toml", run3, seed=2)
    for rd in (run2, run3):
        rec = record(rd)
        assert rec["spec_base"] == str(tiny_data.absolute())
        assert rec["spec"]["data"] == record(run1)["spec"]["data"]
        assert rec["status"] == "finished" and rec["finish_reason"] == "completed"
    # a job.toml that is not a run's copy still reads beside itself
    other = tmp_path / "other"
    other.mkdir()
    (other / "job.toml").write_text(spec.read_text())
    with pytest.raises(FileNotFoundError, match=r"other/psf\.npy"):
        run_job(other / "job.toml", tmp_path / "run4")
