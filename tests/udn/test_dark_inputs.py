"""Dark-frame files are inputs of a run: hashed in its record, checked at a resume and by
``jobs combine``. They were named by path only; a changed dark file then read as "the same
measurement file prepared differently by this version" at a resume."""

from __future__ import annotations

import json

import numpy as np
import pytest

from recon.udn.ensemble import combine_runs
from recon.udn.jobs import resume_job, run_job
from tests.udn.conftest import write_spec


def _dark(folder, name: str, level: float):
    meas = np.load(folder / "meas.npy")
    np.save(folder / name, np.full(meas.shape[-2:], level, np.float32))
    return name


def test_a_changed_dark_file_is_named_at_a_resume(tiny_data, tmp_path):
    spec = write_spec(tiny_data, stopping={"max_iter": 10},
                      data={"dark": _dark(tiny_data, "dark.npy", 0.001), "psf_dark": 0.0})
    out = tmp_path / "run"
    run_job(spec, out)
    rec = json.loads((out / "run.json").read_text())
    assert len(rec["inputs"]["dark"]["file_hash"]) == 16
    assert "psf_dark" not in rec["inputs"]  # a number, not a file
    _dark(tiny_data, "dark.npy", 0.002)
    with pytest.raises(ValueError, match=r"data\.dark \(.*dark\.npy\) changed since the run "
                       r"started"):
        resume_job(out, max_iter=20)


def test_combine_names_the_dark_and_takes_a_record_from_before_darks_were_hashed(
        tiny_data, tmp_path):
    _dark(tiny_data, "dark.npy", 0.001)
    _dark(tiny_data, "dark2.npy", 0.002)
    runs = []
    for seed, dark in ((0, "dark.npy"), (1, "dark.npy"), (2, "dark2.npy")):
        spec = write_spec(tiny_data, f"s{seed}.toml", stopping={"max_iter": 10},
                          data={"dark": dark, "psf_dark": 0.0})
        runs.append(tmp_path / f"s{seed}")
        run_job(spec, runs[-1], seed=seed)
    with pytest.raises(ValueError, match=r"other data .*data\.dark"):
        combine_runs([runs[0], runs[2]], tmp_path / "never.tif")
    # a member recorded before dark files were hashed: the same dark, not other data
    rec = json.loads((runs[1] / "run.json").read_text())
    del rec["inputs"]["dark"]
    (runs[1] / "run.json").write_text(json.dumps(rec))
    res = combine_runs(runs[:2], tmp_path / "ens.tif")
    assert (tmp_path / "ens.tif").is_file() and res is not None
    assert resume_job(runs[1], max_iter=12).iterations == 12  # and it resumes
