"""Batch item records without Ray (``run_item`` in this process): what they keep."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from app.batch.manifest import input_hashes, item_hash, read_manifest
from app.batch.state import BatchPaths
from app.batch.task import run_item
from recon.checks import MeasurementWarning
from tests.batch.conftest import make_data, write_udn_spec

WORDS = "pixels are 0 and no mask was given"


@pytest.fixture
def one_thread(monkeypatch):
    old = torch.get_num_threads()
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # run_item sets it
    yield
    torch.set_num_threads(old)


def test_measurement_warnings_are_kept_in_the_item_records(tmp_path: Path, one_thread) -> None:
    """The loader's MeasurementWarnings (a measurement 0 on 40 % of its pixels, no mask) went
    to stderr only (and a batch task's recon stderr is not even shown): both a fista item's and
    a udn item's record keep them."""
    data = make_data(tmp_path / "data", 1)
    meas = np.load(data / "meas" / "m00.npy")
    rng = np.random.default_rng(0)
    meas[..., rng.random(meas.shape[-2:]) < 0.4] = 0
    np.save(data / "meas" / "z.npy", meas)
    write_udn_spec(data, max_iter=3, checkpoint_every=3)
    (data / "m.csv").write_text("measurement,psf,method,spec,iters\n"
                                "meas/z.npy,psf.npy,fista,,20\n"
                                "meas/m00.npy,psf.npy,fista,,20\n"
                                "meas/z.npy,psf.npy,udn,udn.toml,3\n")
    items = read_manifest(data / "m.csv")
    out = tmp_path / "batch"
    BatchPaths(out).make()
    recs = []
    for it in items:
        hashes = input_hashes(it)
        if "m00" in it.argv[1]:
            recs.append(run_item(it, str(out), item_hash(it, hashes), hashes))
            continue
        with pytest.warns(MeasurementWarning, match=WORDS):
            recs.append(run_item(it, str(out), item_hash(it, hashes), hashes))
    assert [r["status"] for r in recs] == ["done", "done", "done"], recs
    for rec, warned in zip(recs, (True, False, True), strict=True):
        on_disk = json.loads(BatchPaths(out).record(rec["id"]).read_text())
        assert on_disk["warnings"] == rec["warnings"]
        if warned:
            assert len(rec["warnings"]) == 1 and WORDS in rec["warnings"][0], rec
            assert "z.npy" in rec["warnings"][0]
        else:
            assert rec["warnings"] == []
