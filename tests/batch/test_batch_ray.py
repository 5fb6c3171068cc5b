"""Batches on a real local Ray (2 CPUs, as in CI), started once for this module.

- a manifest of 12 small items (10 FISTA, 1 ADMM, 1 short UDN) runs to completion and every
  result equals the result of the same ``lenslesscam recon`` / ``jobs run`` command run on its
  own in this process (same code, same thread count: max abs difference <= 1e-6 of the result's
  peak for FISTA/ADMM, <= 1e-5 for the UDN);
- a worker killed with SIGKILL mid-batch (its pid from the item's running marker): the batch
  finishes, the killed item is retried (attempt 2) and its UDN job resumed from its checkpoint,
  each result exists once;
- a finished batch reruns with no work; a changed input reruns that item only;
- ``batch cancel``: the driver stops, results already written stay;
- Ray leaves no process behind and runs no dashboard.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from app.batch.driver import BatchOptions, run_batch, start_ray
from app.batch.state import batch_status, request_cancel
from app.batch.summary import read_summary
from app.cli import main
from recon.io import read_reconstruction
from tests.batch.conftest import make_data, write_udn_spec
from tests.procs import children_of

pytestmark = pytest.mark.slow

OPTS = BatchOptions(progress=False, poll_s=0.1, max_retries=2)


@pytest.fixture(scope="module")
def ray_local():
    """A local Ray with 2 CPUs, started as ``batch run`` starts it; checked clean at the end."""
    import ray

    before = {p for p, _ in children_of(os.getpid())}
    assert start_ray(None, 2) is True
    assert os.environ["RAY_USAGE_STATS_ENABLED"] == "0"
    assert ray.cluster_resources()["CPU"] == 2
    with socket.socket() as s:  # no dashboard (its default port is closed)
        assert s.connect_ex(("127.0.0.1", 8265)) != 0
    yield ray
    ray.shutdown()
    deadline = time.monotonic() + 30
    left = [c for c in children_of(os.getpid()) if c[0] not in before]
    while left and time.monotonic() < deadline:
        time.sleep(0.2)
        left = [c for c in children_of(os.getpid()) if c[0] not in before]
    assert not left, f"Ray left processes behind: {left}"


def _wait_for(cond, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        v = cond()
        if v:
            return v
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def _peak_diff(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


def test_twelve_items_equal_recon_item_by_item(ray_local, tmp_path: Path) -> None:
    d = make_data(tmp_path / "data", 10)
    write_udn_spec(d, max_iter=15, checkpoint_every=5)
    (d / "m.csv").write_text(
        "measurement,psf,method,iters,tau,truth,spec\n"
        "meas/m0*.npy,psf.npy,fista,25,1e-3,,\n"
        "meas/m00.npy,psf.npy,admm,25,1e-3,meas/t00.npy,\n"
        "meas/m01.npy,psf.npy,udn,,,meas/t01.npy,udn.toml\n")
    rep = run_batch(d / "m.csv", tmp_path / "out", OPTS)
    assert rep.status == "finished" and rep.ran == 12
    assert rep.counts == {"done": 12}
    out = tmp_path / "out"
    for i in range(10):
        ref = tmp_path / f"ref{i}.tif"
        assert main(["recon", "fista", "--psf", str(d / "psf.npy"),
                     "--meas", str(d / "meas" / f"m{i:02d}.npy"), "--iters", "25",
                     "--tau", "1e-3", "--out", str(ref)]) == 0
        got, meta = read_reconstruction(out / "results" / f"m{i:02d}-fista.tif")
        want, _ = read_reconstruction(ref)
        assert _peak_diff(got, want) <= 1e-6
        assert meta["method"] == "fista-tv" and meta["iterations"] == 25
    ref = tmp_path / "ref-admm.tif"
    assert main(["recon", "admm", "--psf", str(d / "psf.npy"), "--meas",
                 str(d / "meas" / "m00.npy"), "--iters", "25", "--tau", "1e-3",
                 "--out", str(ref)]) == 0
    assert _peak_diff(read_reconstruction(out / "results" / "m00-admm.tif")[0],
                      read_reconstruction(ref)[0]) <= 1e-6
    # the UDN item is the job its spec describes, with the item's measurement and truth
    spec = (d / "udn.toml").read_text().replace("meas/m00.npy", "meas/m01.npy")
    (d / "udn01.toml").write_text(spec + '\n[device]\nthreads = 1\n')
    assert main(["jobs", "run", str(d / "udn01.toml"), "--out", str(tmp_path / "ref-run"),
                 "--quiet"]) == 0
    rec = json.loads((out / "items" / "m01-udn.json").read_text())
    got = read_reconstruction(out / rec["output"])[0]
    want = read_reconstruction(tmp_path / "ref-run" / "final.tif")[0]
    assert _peak_diff(got, want) <= 1e-5
    assert rec["iterations"] == 15 and rec["attempt"] == 1
    # summary: one row per item, metrics where a truth is named
    summary = read_summary(out / "summary.csv")
    assert len(summary.rows) == 12 and summary.meta["counts"] == {"done": 12}
    by_id = {r["id"]: r for r in summary.rows}
    assert by_id["m00-admm"]["psnr"] != "" and by_id["m01-udn"]["psnr"] != ""
    assert by_id["m05-fista"]["psnr"] == ""
    assert "| m01-udn | udn | done |" in (out / "summary.md").read_text()
    st = batch_status(out)
    assert st["status"] == "finished" and st["counts"] == {"done": 12}


def test_rerun_does_no_work_and_a_changed_input_reruns_one_item(ray_local, tmp_path: Path,
                                                                 capsys) -> None:
    d = make_data(tmp_path / "data", 4)
    (d / "m.csv").write_text("measurement,psf,method,iters,tau\n"
                             "meas/m*.npy,psf.npy,fista,20,1e-3\n")
    out = tmp_path / "out"
    assert run_batch(d / "m.csv", out, OPTS).ran == 4
    stamps = {p.name: p.stat().st_mtime_ns for p in (out / "results").iterdir()}
    capsys.readouterr()
    rep = run_batch(d / "m.csv", out, replace(OPTS, progress=None))  # stderr not a terminal
    assert rep.ran == 0 and rep.counts == {"skipped": 4} and rep.status == "finished"
    # the line that says what runs where is printed into a log too (it was terminal-only)
    assert "batch: 4 items, 4 already done, 0 to run; nothing to run" in capsys.readouterr().err
    assert {p.name: p.stat().st_mtime_ns for p in (out / "results").iterdir()} == stamps
    np.save(d / "meas" / "m02.npy", np.load(d / "meas" / "m02.npy")[:, ::-1].copy())
    rep = run_batch(d / "m.csv", out, OPTS)
    assert rep.ran == 1 and rep.counts == {"skipped": 3, "done": 1}
    now = {p.name: p.stat().st_mtime_ns for p in (out / "results").iterdir()}
    changed = sorted(n for n in now if now[n] != stamps[n])
    assert changed and all(n.startswith("m02-fista") for n in changed)
    # a result damaged on disk is not trusted: that item runs again
    (out / "results" / "m00-fista.tif").write_bytes(b"damaged")
    assert run_batch(d / "m.csv", out, OPTS).ran == 1
    assert read_reconstruction(out / "results" / "m00-fista.tif")[0].shape == (1, 1, 24, 28)
    # state.json lost or damaged: the folder was refused for good ('not empty and holds no
    # batch'); the item records still say what was done
    for damage in ("missing", "damaged"):
        if damage == "missing":
            (out / "state.json").unlink()
        else:
            (out / "state.json").write_text("{not json")
        capsys.readouterr()
        rep = run_batch(d / "m.csv", out, OPTS)
        assert rep.ran == 0 and rep.counts == {"skipped": 4}, damage
        assert (f"state.json is {damage}; continuing from the item records"
                in capsys.readouterr().err)
    other = d / "other.csv"
    other.write_text((d / "m.csv").read_text())
    (out / "state.json").unlink()
    with pytest.raises(ValueError, match=r"holds the items of another manifest \(m\.csv:2"):
        run_batch(other, out, OPTS)  # its item records name m.csv
    # a damaged state.json where no item is recorded yet: named, with what to do
    empty = tmp_path / "empty"
    (empty / "items").mkdir(parents=True)
    (empty / "state.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"not valid JSON.*no item record .* delete the "
                       r"folder's state\.json"):
        run_batch(d / "m.csv", empty, OPTS)


def test_a_failed_item_is_recorded_and_the_batch_goes_on(ray_local, tmp_path: Path) -> None:
    d = make_data(tmp_path / "data", 3)
    np.save(d / "psf_small.npy", np.load(d / "psf.npy")[:10, :10])
    (d / "m.csv").write_text("measurement,psf,method,iters,tau\n"
                             "meas/m00.npy,psf_small.npy,fista,20,1e-3\n"
                             "meas/m0[12].npy,psf.npy,fista,20,1e-3\n")
    out = tmp_path / "out"
    rep = run_batch(d / "m.csv", out, OPTS)
    assert rep.status == "failed" and rep.counts == {"failed": 1, "done": 2}
    rec = json.loads((out / "items" / "m00-fista.json").read_text())
    assert rec["status"] == "failed" and rec["attempt"] == 1  # an input error: no retry
    assert "ValueError" in rec["error"] and "\n" not in rec["error"]
    assert "| m00-fista | fista | failed |" in (out / "summary.md").read_text()
    assert not (out / "results" / "m00-fista.tif").exists()
    rep = run_batch(d / "m.csv", out, OPTS)  # a rerun retries the failed item only
    assert rep.ran == 1 and rep.counts == {"failed": 1, "skipped": 2}


def test_worker_killed_mid_batch(ray_local, tmp_path: Path, capfd) -> None:
    d = make_data(tmp_path / "data", 6)
    write_udn_spec(d, max_iter=150, checkpoint_every=10)
    (d / "m.csv").write_text("measurement,psf,method,iters,tau,spec\n"
                             "meas/m00.npy,psf.npy,udn,,,udn.toml\n"
                             "meas/m*.npy,psf.npy,fista,300,1e-3,\n")
    out = tmp_path / "out"
    box: dict = {}
    t = threading.Thread(target=lambda: box.setdefault("rep", run_batch(d / "m.csv", out, OPTS)))
    t.start()
    try:
        def checkpointed():
            runs = list((out / "runs").glob("m00-udn-*/run.json")) if out.exists() else []
            if not runs:
                return None
            try:
                rec = json.loads(runs[0].read_text())
            except ValueError:
                return None
            return rec if (rec.get("checkpoint") or {}).get("iteration", 0) >= 10 else None

        rec = _wait_for(checkpointed, 120, "the UDN item's first checkpoint")
        marker = json.loads((out / "items" / "m00-udn.running").read_text())
        assert marker["attempt"] == 1 and rec["pid"] == marker["pid"]
        os.kill(marker["pid"], signal.SIGKILL)
    finally:
        t.join(timeout=300)
    rep = box["rep"]
    assert rep.status == "finished" and rep.counts == {"done": 7}
    udn = json.loads((out / "items" / "m00-udn.json").read_text())
    assert udn["attempt"] == 2 and udn["resumed"] and udn["iterations"] == 150
    run = json.loads((out / udn["run_dir"] / "run.json").read_text())
    assert run["resumes"] == 1 and run["sessions"][1]["start_iteration"] >= 10
    # each result once: one run folder, one TIFF per FISTA item, no temporary files
    assert len(list((out / "runs").iterdir())) == 1
    assert sorted(p.name for p in (out / "results").glob("*.tif")) == [
        f"m{i:02d}-fista.tif" for i in range(6)]
    assert not list(out.rglob("*.tmp")) and not list(out.rglob("*.running"))
    # Ray's own report of the dead worker (coloured, with its notes) stays off the terminal:
    # the batch's records say what happened
    seen = capfd.readouterr()
    assert "(raylet)" not in seen.out + seen.err and "\x1b[" not in seen.out + seen.err, seen


def test_cancel_stops_and_keeps_results(ray_local, tmp_path: Path) -> None:
    d = make_data(tmp_path / "data", 3)
    write_udn_spec(d, max_iter=100000, checkpoint_every=50)
    (d / "m.csv").write_text("measurement,psf,method,iters,tau,spec\n"
                             "meas/m*.npy,psf.npy,fista,20,1e-3,\n"
                             "meas/m00.npy,psf.npy,udn,,,udn.toml\n"
                             "meas/m01.npy,psf.npy,udn,,,udn.toml\n")
    out = tmp_path / "out"
    box: dict = {}
    t = threading.Thread(target=lambda: box.setdefault("rep", run_batch(d / "m.csv", out, OPTS)))
    t.start()
    try:
        def fista_done() -> bool:
            n = 0
            for p in (out / "items").glob("*-fista.json"):
                try:
                    n += json.loads(p.read_text())["status"] == "done"
                except ValueError:
                    pass
            return n == 3

        _wait_for(lambda: fista_done() and list((out / "runs").glob("*/checkpoint.pt")), 120,
                  "the FISTA records and a UDN checkpoint")
        assert main(["batch", "status", str(out)]) == 0
        assert batch_status(out)["status"] == "running"
        assert "cancellation requested" in request_cancel(out)
    finally:
        t.join(timeout=120)
    assert not t.is_alive(), "the driver did not stop after the cancel"
    rep = box["rep"]
    info = {k: (r.get("status"), r.get("error") or r.get("detail")) for k, r in rep.records.items()}
    assert rep.status == "cancelled", info
    assert rep.counts == {"done": 3, "cancelled": 2}, info
    assert len(list((out / "results").glob("*.tif"))) == 3  # results written stay
    udn = json.loads((out / "items" / "m00-udn.json").read_text())
    assert udn["status"] == "cancelled"
    st = batch_status(out)
    assert st["status"] == "cancelled" and not (out / "CANCEL").exists()
    shutil.rmtree(out)
