"""An output that cannot be written is refused before any work (hostile-user review).

``recon fista ... --out /readonly/x.tif`` ran the whole reconstruction and failed at the save,
losing the work; so did recon admm / auto, simulate, plan --out and trade --out. The one
output check of every writer command (``app.commands._options.check_command_outputs``) now
probes the output's folder (or the nearest existing folder above it) first.

Tests may run as root, which ignores permission bits: the read-only folder variant is skipped
for root, and ``/proc`` (where not even root can create a file) stands in for it.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from tests.clirun import run_cli as _run

IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0


def _proc_refuses_files() -> bool:
    if not sys.platform.startswith("linux") or not os.path.isdir("/proc"):
        return False
    try:
        fd, name = tempfile.mkstemp(dir="/proc")
    except OSError:
        return True
    os.close(fd)
    os.unlink(name)
    return False




@pytest.fixture
def data(tmp_path):
    from recon.simulate import synthetic_psf

    rng = np.random.default_rng(0)
    d = tmp_path / "data"
    d.mkdir()
    psf = synthetic_psf((24, 32), seed=2).astype(np.float32)
    np.save(d / "psf.npy", psf)
    np.save(d / "meas.npy", rng.random((24, 32)).astype(np.float32))
    np.save(d / "scene.npy", rng.random((24, 32)).astype(np.float32))
    return d


@pytest.fixture
def no_work(monkeypatch):
    """Every command's first piece of work fails the test if it starts."""
    import app.commands.simulate as simulate_cmd
    import recon.problem
    import recon.trade

    def work(*_a, **_k):
        raise AssertionError("the work started before the output location was checked")

    monkeypatch.setattr(recon.problem, "load_problem", work)
    monkeypatch.setattr(recon.trade, "run_trade", work)
    monkeypatch.setattr(simulate_cmd, "load_psf_spec", work)
    import app.batch.driver
    import recon.udn.jobs

    monkeypatch.setattr(recon.udn.jobs, "run_job", work)
    monkeypatch.setattr(app.batch.driver, "run_batch", work)


def _commands(d: Path, out: Path) -> dict[str, list]:
    inputs = ["--psf", d / "psf.npy", "--meas", d / "meas.npy"]
    return {
        "recon fista": ["recon", "fista", *inputs, "--tau", "1e-3", "--iters", "3",
                        "--out", out / "x.tif"],
        "recon admm": ["recon", "admm", *inputs, "--tau", "1e-3", "--iters", "3",
                       "--out", out / "x.tif"],
        "recon auto": ["recon", "auto", *inputs, "--tau", "1e-3", "--out", out / "x.tif"],
        "plan --out": ["plan", *inputs, "--no-probe", "--tau", "1e-3", "--out",
                       out / "plan.json"],
        "simulate": ["simulate", "--psf", d / "psf.npy", "--scene", d / "scene.npy",
                     "--out", out / "sim"],
        "trade --out": ["trade", *inputs, "--quick", "--no-udn", "--out", out / "t"],
        # the commands whose --out is a folder (they gave the system's "[Errno 30] Read-only
        # file system: ..." or "[Errno 20] Not a directory: ...")
        "jobs run": ["jobs", "run", d / "job.toml", "--out", out / "run"],
        "recon udn": ["recon", "udn", *inputs, "--iters", "3", "--out", out / "run"],
        "batch run": ["batch", "run", d / "manifest.csv", "--out", out / "batch"],
    }


COMMANDS = ["recon fista", "recon admm", "recon auto", "plan --out", "simulate", "trade --out",
            "jobs run", "recon udn", "batch run"]


def _check_refused(capsys, argv: list, out: Path) -> None:
    code, _, err = _run(capsys, *argv)
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "cannot write" in lines[0] and "not writable" in lines[0], err
    assert str(out) in lines[0], err


@pytest.mark.skipif(IS_ROOT, reason="root writes into a folder without write permission; "
                                    "test_proc_output_is_refused_before_any_work covers root")
@pytest.mark.parametrize("command", COMMANDS)
def test_read_only_output_folder_is_refused_before_any_work(data, tmp_path, capsys, no_work,
                                                            command):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        _check_refused(capsys, _commands(data, ro)[command], ro)
        # a folder still to be made inside it: refused too, naming both
        _check_refused(capsys, _commands(data, ro / "new")[command], ro / "new")
        assert list(ro.iterdir()) == []
    finally:
        ro.chmod(0o755)


@pytest.mark.skipif(not _proc_refuses_files(), reason="needs Linux /proc, where no one "
                                                      "(root included) can create files")
@pytest.mark.parametrize("command", COMMANDS)
def test_proc_output_is_refused_before_any_work(data, capsys, no_work, command):
    # /proc/<new> is a folder that cannot be made; /proc itself a folder nothing is written in
    for out in (Path("/proc"), Path("/proc") / "lenslesscam-no-such-folder"):
        _check_refused(capsys, _commands(data, out)[command], out)


def test_output_under_a_regular_file_is_one_line_before_any_work(data, tmp_path, capsys,
                                                                 no_work):
    """A path through a regular file fails for root too (it was refused before this fix)."""
    f = tmp_path / "some_file.txt"
    f.write_text("not a folder")
    for command in ("recon fista", "jobs run", "recon udn", "batch run"):
        code, _, err = _run(capsys, *_commands(data, f)[command])
        assert code == 2 and len(err.strip().splitlines()) == 1, (command, err)
        assert "is a file, not a folder" in err and str(f) in err, (command, err)


def test_writable_locations_pass_and_leave_nothing_behind(tmp_path, monkeypatch):
    from app.commands._options import check_output_folders

    (tmp_path / "here").mkdir()
    monkeypatch.chdir(tmp_path / "here")
    check_output_folders([tmp_path / "here" / "a.tif", tmp_path / "here" / "a.png",
                          tmp_path / "new" / "deeper" / "b.tif", "relative.tif"])
    assert [p.name for p in tmp_path.iterdir()] == ["here"]
    assert list((tmp_path / "here").iterdir()) == []
