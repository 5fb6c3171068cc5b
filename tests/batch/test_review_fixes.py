"""Defects of the batch path found by a review: each test failed on the code before its fix.

Most run without Ray (the manifest, the driver's checks before Ray, or the whole driver with
its items run in this process); one runs ``lenslesscam batch run`` on a real embedded Ray in a
subprocess, to send it SIGTERM.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from app.batch.manifest import input_hashes, item_hash, read_manifest
from app.batch.state import BatchPaths
from app.cli import main
from tests.batch.conftest import make_data, write_udn_spec


@pytest.fixture
def data(tmp_path: Path) -> Path:
    return make_data(tmp_path / "data", 3)


@pytest.fixture
def in_process(monkeypatch):
    """``run_batch`` with its items run here, one after another, by the task function."""
    from app.batch import driver
    from app.batch.task import run_item

    def execute(self, todo) -> None:
        for it, h, hashes in todo:
            rec = run_item(it, str(self.paths.root), h, hashes, 1)
            self.records[it.id] = rec
            self.status[it.id] = rec["status"]
            self.ran += 1

    old = torch.get_num_threads()
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # run_item sets it
    monkeypatch.setattr(driver._Driver, "execute", execute)
    monkeypatch.setattr(driver, "start_ray", lambda *a, **k: False)
    yield driver
    torch.set_num_threads(old)


# -- 1. a udn item's spec-named files are hashed -----------------------------------------------


def test_files_a_udn_spec_names_are_inputs_of_its_item(data: Path, tmp_path: Path) -> None:
    """Changing the PSF that only the spec names reported "1 already done (skipped)"."""
    write_udn_spec(data, 5, 5)
    np.save(data / "dark.npy", np.zeros((24, 28)))
    spec = data / "udn.toml"
    spec.write_text(spec.read_text().replace('[data]\n', '[data]\ndark = "dark.npy"\n'))
    (data / "m.csv").write_text("measurement,method,spec\nmeas/m01.npy,udn,udn.toml\n")
    (item,) = read_manifest(data / "m.csv")
    inputs = dict(item.inputs)
    assert inputs["psf"] == str((data / "psf.npy").resolve())
    assert inputs["dark"] == str((data / "dark.npy").resolve())
    assert inputs["measurement"] == str((data / "meas" / "m01.npy").resolve())
    before = item_hash(item)
    assert input_hashes(item)["psf"] is not None
    np.save(data / "psf.npy", np.load(data / "psf.npy")[::-1].copy())
    assert item_hash(item) != before
    mid = item_hash(item)
    np.save(data / "dark.npy", np.full((24, 28), 0.01))
    assert item_hash(item) != mid
    # a file the spec names inside the batch folder is refused as a column's is
    from app.batch.driver import run_batch
    from app.batch.state import STATE_FORMAT

    out = tmp_path / "b"
    out.mkdir()
    (out / "state.json").write_text(json.dumps({"format": STATE_FORMAT,
                                                "manifest": str((data / "m.csv").resolve())}))
    np.save(out / "psf.npy", np.load(data / "psf.npy"))
    spec.write_text(spec.read_text().replace('psf = "psf.npy"', f'psf = "{out / "psf.npy"}"'))
    with pytest.raises(ValueError, match=r"m01-udn's psf lies in the batch folder"):
        run_batch(data / "m.csv", out)


# -- 2, 3, 4. [defaults] and whole numbers ------------------------------------------------------


def test_defaults_for_fista_leave_a_udn_spec_solver_alone(data: Path) -> None:
    """A [defaults] iters/seed meant for FISTA replaced the spec's max_iter and seed."""
    from app.batch.task import build_udn_spec

    write_udn_spec(data, 10, 5)
    (data / "m.toml").write_text(
        '[defaults]\npsf = "psf.npy"\nmethod = "fista"\niters = 500\nseed = 3\n\n'
        '[[item]]\nmeasurement = "meas/m00.npy"\n\n'
        '[[item]]\nmeasurement = "meas/m00.npy"\nmethod = "udn"\nspec = "udn.toml"\n\n'
        '[[item]]\nmeasurement = "meas/m01.npy"\nmethod = "udn"\nspec = "udn.toml"\n'
        'iters = 7\n')
    fista, udn, own = read_manifest(data / "m.toml")
    assert "500" in fista.argv
    assert not [t for t in udn.spec_data if t[0] != "data"], udn.spec_data
    spec, _ = build_udn_spec(udn)
    assert spec["stopping"]["max_iter"] == 10 and "optimizer" not in spec
    assert ("stopping", "max_iter", 7) in own.spec_data  # the item's own column does


def test_a_defaults_key_that_no_method_takes_is_one_line(data: Path, capsys) -> None:
    (data / "m.toml").write_text('[defaults]\npsf = "psf.npy"\nmethod = "fista"\ntua = 1e-1\n\n'
                                 '[[item]]\nmeasurement = "meas/m00.npy"\n')
    with pytest.raises(ValueError, match=r"m\.toml: \[defaults\]: 'tua' is not a column of any "
                                         r"item .*did you mean 'tau'\?"):
        read_manifest(data / "m.toml")
    assert main(["batch", "run", str(data / "m.toml"), "--out", str(data / "b")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "'tua'" in err
    assert not (data / "b").exists()


@pytest.mark.parametrize(("cell", "got"), [("iters = 1.9", "1.9"), ("downsample = true", "true"),
                                           ("iters = 2.0", "2.0"), ("seed = -1", "-1")])
def test_whole_number_spec_columns_are_not_truncated(data: Path, cell: str, got: str) -> None:
    write_udn_spec(data, 10, 5)
    (data / "m.toml").write_text('[[item]]\nmeasurement = "meas/m00.npy"\nmethod = "udn"\n'
                                 f'spec = "udn.toml"\n{cell}\n')
    col = cell.split()[0]
    with pytest.raises(ValueError, match=rf"item 1: column '{col}' must be an integer >= "
                                         rf"[01], got '{got}'"):
        read_manifest(data / "m.toml")


# -- 5. an item's own exception: recorded once, one line ---------------------------------------


def _busy_udn_item(data: Path, out: Path):
    """A udn item whose run folder another process holds (its lock taken here)."""
    from app.batch.state import STATE_FORMAT
    from recon.udn.rundir import RunLock

    write_udn_spec(data, max_iter=100000, checkpoint_every=20)
    (data / "m.csv").write_text("measurement,psf,method,spec\n"
                                "meas/m01.npy,psf.npy,udn,udn.toml\n"
                                "meas/m00.npy,psf.npy,udn,udn.toml\n")
    busy = read_manifest(data / "m.csv")[0]
    paths = BatchPaths(out)
    paths.make()
    (out / "state.json").write_text(json.dumps({"format": STATE_FORMAT,
                                                "manifest": str((data / "m.csv").resolve())}))
    run_dir = paths.run_dir(busy.id, item_hash(busy))
    run_dir.mkdir(parents=True)
    return busy, RunLock(run_dir).acquire()


def test_an_exception_an_item_raises_is_recorded_at_once_in_one_line(data: Path,
                                                                     tmp_path: Path,
                                                                     monkeypatch) -> None:
    """A deterministic error other than ValueError (here RunFolderBusy, a RuntimeError)
    propagated to Ray, which retried it and printed its traceback three times."""
    from app.batch.task import run_item

    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    old = torch.get_num_threads()
    out = tmp_path / "b"
    item, lock = _busy_udn_item(data, out)
    hashes = input_hashes(item)
    try:
        rec = run_item(item, str(out), item_hash(item, hashes), hashes, 1)
    finally:
        lock.release()
        torch.set_num_threads(old)
    assert rec["status"] == "failed" and rec["attempt"] == 1
    assert rec["error"].startswith("RunFolderBusy: ") and "\n" not in rec["error"], rec["error"]
    assert json.loads(BatchPaths(out).record(item.id).read_text())["status"] == "failed"
    assert not BatchPaths(out).running(item.id).exists()


# -- 6 (and 5 on Ray). SIGTERM cancels as Ctrl-C does; failures are one line --------------------


@pytest.mark.slow
def test_sigterm_cancels_the_batch_as_ctrl_c_does(data: Path, tmp_path: Path) -> None:
    out = tmp_path / "b"
    busy, lock = _busy_udn_item(data, out)  # fails at once, deterministically
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "app.cli", "batch", "run",
                             str(data / "m.csv"), "--out", str(out), "--num-cpus", "2",
                             "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env=env, cwd=Path(__file__).parents[2])
    try:
        deadline = time.monotonic() + 240
        failed = out / "items" / f"{busy.id}.json"
        while time.monotonic() < deadline and proc.poll() is None and not (
                failed.is_file() and list((out / "runs").glob("*/checkpoint.pt"))):
            time.sleep(0.2)
        assert proc.poll() is None, proc.communicate()[0]
        assert failed.is_file(), "the failing item was not recorded in time"
        time.sleep(1.0)  # Ray's reports of a failed task arrive on the driver within a second
        proc.send_signal(signal.SIGTERM)
        text, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        lock.release()
    assert proc.returncode == 130, text
    assert "batch cancelled: 0 done, 0 already done (skipped), 1 failed, 1 cancelled" in text
    assert "Traceback" not in text and "\x1b[" not in text and "(raylet)" not in text, text
    assert "SIGTERM received" not in text
    rec = json.loads(failed.read_text())
    assert rec["status"] == "failed" and rec["attempt"] == 1  # not retried
    assert rec["error"].startswith("RunFolderBusy: ") and "\n" not in rec["error"]
    assert f"failed {busy.id}: {rec['error']}" in text
    assert json.loads((out / "state.json").read_text())["status"] == "cancelled"
    udn = json.loads((out / "items" / "m00-udn.json").read_text())
    assert udn["status"] == "cancelled"
    (run_json,) = (out / "runs").glob("m00-udn-*/run.json")
    run = json.loads(run_json.read_text())
    assert run["finish_reason"] == "cancelled"
    assert run["checkpoint"]["iteration"] == run["progress"]["iteration"]  # a final checkpoint


# -- 7, 8. options refused up front --------------------------------------------------------------


def test_max_retries_is_bounded(data: Path, capsys) -> None:
    """2**31 was an OverflowError traceback after Ray had started."""
    (data / "m.csv").write_text("measurement,psf,method\nmeas/m00.npy,psf.npy,fista\n")
    with pytest.raises(SystemExit) as exc:
        main(["batch", "run", str(data / "m.csv"), "--out", str(data / "b"),
              "--max-retries", "2147483648"])
    assert exc.value.code == 2
    assert "--max-retries: must be an integer >= 0 and <= 1000" in capsys.readouterr().err
    assert not (data / "b").exists()


def test_a_batch_folder_inside_a_udn_run_folder_is_refused(data: Path, tmp_path: Path,
                                                          capsys) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / "run.json").write_text(json.dumps({"format": "lenslesscam.udn_run"}))
    (data / "m.csv").write_text("measurement,psf,method\nmeas/m00.npy,psf.npy,fista\n")
    # a closed port: the old code made the folder and stopped at the address
    rc = main(["batch", "run", str(data / "m.csv"), "--out", str(run / "b"), "--address",
               "127.0.0.1:1", "--connect-timeout", "2"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.count("\n") == 0
    assert f"--out {run / 'b'} writes into the UDN run folder {run}" in err, err
    assert not (run / "b").exists()


# -- 9, 10. globs and folder names with brackets --------------------------------------------------


def test_a_manifest_folder_with_glob_characters_and_a_literal_bracket_file(tmp_path: Path
                                                                           ) -> None:
    d = make_data(tmp_path / "scan[2024]", 2)
    (d / "m.csv").write_text("measurement,psf,method\nmeas/m*.npy,psf.npy,fista\n")
    assert [it.id for it in read_manifest(d / "m.csv")] == ["m00-fista", "m01-fista"]
    for folder, src in (("e[1]", "m00"), ("e1", "m01")):
        (d / folder).mkdir()
        np.save(d / folder / "a.npy", np.load(d / "meas" / f"{src}.npy"))
    (d / "n.csv").write_text("measurement,psf,method,name\ne[1]/a.npy,psf.npy,fista,x\n")
    (item,) = read_manifest(d / "n.csv")
    assert dict(item.inputs)["measurement"] == str((d / "e[1]" / "a.npy").resolve())
    assert item.id == "x"  # a file, not a glob: no stem appended
    (d / "g.csv").write_text("measurement,psf,method\ne[1x]/a.npy,psf.npy,fista\n")
    (item,) = read_manifest(d / "g.csv")  # no such file: a glob, as before
    assert dict(item.inputs)["measurement"] == str((d / "e1" / "a.npy").resolve())


# -- 11, 12. the batch folder: temporary files, newer formats --------------------------------------


def test_temp_files_of_killed_writes_go_and_newer_files_are_refused(data: Path, tmp_path: Path,
                                                                   in_process) -> None:
    from recon.formats import NewerFormat

    (data / "m.csv").write_text("measurement,psf,method,iters\nmeas/m0[01].npy,psf.npy,fista,5\n")
    out = tmp_path / "b"
    rep = in_process.run_batch(data / "m.csv", out)
    assert rep.status == "finished" and rep.ran == 2
    left = [out / ".state.json.a1b2.tmp", out / "items" / ".m00-fista.json.x9.tmp",
            out / "results" / ".m01-fista.abc.tmp.tif"]
    for p in left:
        p.write_bytes(b"half")
    rep = in_process.run_batch(data / "m.csv", out)
    assert rep.ran == 0 and rep.counts == {"skipped": 2}
    assert not [p for p in left if p.exists()]
    # a newer release's item record: refused, not rerun over
    rec_path = out / "items" / "m00-fista.json"
    rec = json.loads(rec_path.read_text())
    rec["format_version"] = 99
    rec_path.write_text(json.dumps(rec))
    with pytest.raises(NewerFormat, match=r"m00-fista\.json: format_version 99 was written by "
                                          r"a newer lenslesscam"):
        in_process.run_batch(data / "m.csv", out)
    assert json.loads(rec_path.read_text())["format_version"] == 99
    rec["format_version"] = 1
    rec_path.write_text(json.dumps(rec))
    st = json.loads((out / "state.json").read_text())
    st["format_version"] = 99
    (out / "state.json").write_text(json.dumps(st))
    with pytest.raises(NewerFormat, match=r"state\.json: format_version 99"):
        in_process.run_batch(data / "m.csv", out)
    assert main(["batch", "status", str(out)]) == 2
    assert json.loads((out / "state.json").read_text())["format_version"] == 99
    # a damaged version (a string, a hand edit) is damage, not a newer release: the item
    # runs again, as for any damaged record (it refused the whole batch)
    st["format_version"] = 1
    (out / "state.json").write_text(json.dumps(st))
    rec["format_version"] = "1"
    rec_path.write_text(json.dumps(rec))
    rep = in_process.run_batch(data / "m.csv", out)
    assert rep.ran == 1 and json.loads(rec_path.read_text())["format_version"] == 1


# -- 13. runs that cannot start leave no folder ----------------------------------------------------


def test_a_run_that_cannot_start_leaves_no_folder(data: Path, tmp_path: Path,
                                                 monkeypatch) -> None:
    from app.batch.driver import BatchOptions, run_batch
    from app.cli import CliError

    (data / "m.csv").write_text("measurement,psf,method\nmeas/m00.npy,psf.npy,fista\n")
    with pytest.raises(CliError, match=r"cannot reach the Ray cluster at 127\.0\.0\.1:1"):
        run_batch(data / "m.csv", tmp_path / "b1",
                  BatchOptions(address="127.0.0.1:1", connect_timeout_s=2))
    assert not (tmp_path / "b1").exists()
    # `auto` with no cluster on this machine (the README's example): refused before the folder
    from ray._private import services

    def none_here(address):  # Ray's reading of `auto` (a Ray of another test may run here)
        raise ConnectionError("Could not find any running Ray instance. Please specify ...")

    monkeypatch.setattr(services, "canonicalize_bootstrap_address", none_here)
    with pytest.raises(CliError) as refused:
        run_batch(data / "m.csv", tmp_path / "b0", BatchOptions(address="auto"))
    assert not (tmp_path / "b0").exists()
    assert str(refused.value).startswith("cannot join the Ray cluster at auto: Could not find "
                                         "any running Ray instance; start one")
    with monkeypatch.context() as m:
        m.setitem(sys.modules, "ray", None)  # as if Ray were not installed
        with pytest.raises(CliError, match="lenslesscam batch needs Ray"):
            run_batch(data / "m.csv", tmp_path / "b2")
    assert not (tmp_path / "b2").exists()
    long = "n" * 300
    (data / "n.csv").write_text(f"measurement,psf,method,name\nmeas/m00.npy,psf.npy,fista,{long}\n")
    with pytest.raises(ValueError, match=r"n\.csv:2: column 'name' makes an item id of 300 "
                                         r"bytes .* at most 200"):
        read_manifest(data / "n.csv")
    np.save(data / "meas" / f"{long[:250]}.npy", np.load(data / "meas" / "m00.npy"))
    (data / "o.csv").write_text("measurement,psf,method\nmeas/n*.npy,psf.npy,fista\n")
    with pytest.raises(ValueError, match=r"o\.csv:2: column 'measurement': the file name gives "
                                         r"an item id of 256 bytes"):
        read_manifest(data / "o.csv")


def test_rays_reports_are_quiet_for_the_batch_only_and_memory_notices_stay(
        caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    """(diff review) The patch of Ray's report printer stayed for the rest of the process and
    dropped the OOM killer's notice of why a worker died with the tracebacks."""
    import logging

    pytest.importorskip("ray")
    from ray._private import worker as ray_worker

    from app.batch.driver import _loud_ray_reports, _quiet_ray_reports

    monkeypatch.delenv("RAY_IGNORE_UNHANDLED_ERRORS", raising=False)
    printed: list[dict] = []

    def printer(data: dict, ignore_prefix: bool) -> None:
        printed.append(data)

    monkeypatch.setattr(ray_worker, "print_to_stdstream", printer)
    _quiet_ray_reports()
    try:
        assert ray_worker.print_to_stdstream is not printer
        with caplog.at_level(logging.DEBUG, logger="app.batch.ray"):
            ray_worker.print_to_stdstream({"pid": "raylet", "lines": [
                "Task run_item failed. Traceback ...",
                "1 Workers killed due to memory pressure (OOM)"]}, ignore_prefix=False)
            ray_worker.print_to_stdstream({"pid": 123, "lines": ["a worker's own"]},
                                          ignore_prefix=False)
        warned = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
        assert warned == ["ray: 1 Workers killed due to memory pressure (OOM)"]
        assert [d["pid"] for d in printed] == [123]  # a worker's output still reaches it
    finally:
        _loud_ray_reports()
    assert ray_worker.print_to_stdstream is printer
    assert "RAY_IGNORE_UNHANDLED_ERRORS" not in os.environ
