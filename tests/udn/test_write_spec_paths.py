"""How ``recon udn --write-spec`` names the data files in the spec it writes.

It wrote every path absolute and resolved through symbolic links: a folder of data and spec
could not be moved, copied or shared (the copy's spec still read the original's files, or
none). Data under the spec's folder is now named relative to it (a spec's relative paths are
read relative to the spec file), other data as the user gave it, made absolute against the
current folder only.
"""

from __future__ import annotations

import json
import shutil
import tomllib

import numpy as np

from tests.clirun import run_cli

NET = ["--iters", "2", "--scales", "2", "--net-channels", "4", "--skip-channels", "2",
       "--input-channels", "4", "--device", "cpu", "--checkpoint-every", "2",
       "--preview-every", "0", "--quiet"]


def _record(run):
    return json.loads((run / "run.json").read_text())


def _inputs(run):
    return _record(run)["inputs"]


def test_written_spec_names_data_under_its_folder_relative_to_it(tiny_data, tmp_path,
                                                                 monkeypatch, capsys):
    proj = tmp_path / "proj"
    shutil.copytree(tiny_data, proj / "data")
    np.save(proj / "data" / "dark.npy", np.zeros_like(np.load(tiny_data / "meas.npy")))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    shutil.copy(tiny_data / "truth.npy", elsewhere / "truth.npy")
    (tmp_path / "linked").symlink_to(elsewhere, target_is_directory=True)
    monkeypatch.chdir(tmp_path)
    files = ["--psf", "proj/data/psf.npy",                    # relative to the current folder
             "--meas", tmp_path / "proj" / "data" / "meas.npy",  # absolute
             "--mask", "proj/../proj/data/mask.npy",
             "--dark", "proj/data/dark.npy",                  # a dark file is a path too
             "--truth", "linked/truth.npy"]                   # outside, through a link
    code, _, err = run_cli(capsys, "recon", "udn", *files, *NET, "--write-spec",
                           "proj/job.toml")
    assert code == 0, err
    data = tomllib.loads((proj / "job.toml").read_text(encoding="utf-8"))["data"]
    assert (data["psf"], data["measurement"], data["mask"], data["dark"]) == (
        "data/psf.npy", "data/meas.npy", "data/mask.npy", "data/dark.npy")
    assert data["truth"] == str(tmp_path / "linked" / "truth.npy")  # link kept, not resolved

    # it loads from another current folder, and its run records what `recon udn --out` does
    code, _, err = run_cli(capsys, "recon", "udn", *files, *NET, "--out", "direct")
    assert code == 0, err
    other = tmp_path / "other"
    other.mkdir()
    monkeypatch.chdir(other)
    code, _, err = run_cli(capsys, "jobs", "run", "../proj/job.toml", "--out", "../from_spec",
                           "--quiet")
    assert code == 0, err
    direct, from_spec = _inputs(tmp_path / "direct"), _inputs(tmp_path / "from_spec")
    assert from_spec == direct  # same resolved paths, same file and array hashes
    assert {"psf", "measurement", "mask", "truth"} <= direct.keys()
    # the spec the record keeps (every path absolute and resolved, the dark file's too)
    assert _record(tmp_path / "from_spec")["spec"]["data"] == \
        _record(tmp_path / "direct")["spec"]["data"]
    assert from_spec["psf"]["path"] == str((proj / "data" / "psf.npy").resolve())

    # the folder moved (and the original removed): the copy's spec reads the copy's data
    moved = tmp_path / "moved"
    shutil.move(proj, moved)
    code, _, err = run_cli(capsys, "jobs", "run", moved / "job.toml", "--out", "../run_moved",
                           "--quiet")
    assert code == 0, err
    after = _inputs(tmp_path / "run_moved")
    assert after.keys() == direct.keys()
    for name, entry in after.items():
        assert {k: v for k, v in entry.items() if k != "path"} == \
            {k: v for k, v in direct[name].items() if k != "path"}, name
    assert after["measurement"]["path"] == str((moved / "data" / "meas.npy").resolve())
    assert after["truth"]["path"] == str((elsewhere / "truth.npy").resolve())


def test_written_spec_through_a_link_to_its_folder(tiny_data, tmp_path, monkeypatch, capsys):
    """The spec's folder given through a link, the data by its real path: still under it."""
    (tmp_path / "proj_link").symlink_to(tiny_data.parent, target_is_directory=True)
    monkeypatch.chdir(tmp_path)
    code, _, err = run_cli(capsys, "recon", "udn", "--psf", tiny_data / "psf.npy", "--meas",
                           tiny_data / "meas.npy", *NET, "--write-spec", "proj_link/s.toml")
    assert code == 0, err
    data = tomllib.loads((tiny_data.parent / "s.toml").read_text(encoding="utf-8"))["data"]
    assert (data["psf"], data["measurement"]) == ("data/psf.npy", "data/meas.npy")


def test_a_relative_path_is_written_only_when_it_leads_to_the_same_file(tmp_path,
                                                                        monkeypatch):
    """``s/L/../x.npy`` with L a link out of ``s``: the system reads ``e/x.npy``; the
    spelling alone would say ``s/x.npy`` (another file of the same name)."""
    from app.commands.recon_udn import spec_file_path

    (tmp_path / "s").mkdir()
    (tmp_path / "e" / "deep").mkdir(parents=True)
    np.save(tmp_path / "s" / "x.npy", np.zeros(2))
    np.save(tmp_path / "e" / "x.npy", np.ones(2))
    (tmp_path / "s" / "L").symlink_to(tmp_path / "e" / "deep", target_is_directory=True)
    monkeypatch.chdir(tmp_path)
    written = spec_file_path("s/L/../x.npy", "s/spec.toml")
    assert written == str(tmp_path / "s" / "L" / ".." / "x.npy")
    assert np.load(written)[0] == 1.0
    assert spec_file_path("s/x.npy", "s/spec.toml") == "x.npy"
    assert spec_file_path("e/x.npy", "s/spec.toml") == str(tmp_path / "e" / "x.npy")
    assert spec_file_path("s/x.npy", "new/spec.toml") == str(tmp_path / "s" / "x.npy")
