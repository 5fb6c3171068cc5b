"""``trade`` and ``plan --trade``: threads, locks, output folders and reproducible choices.

Each test is a finding of a hostile review (the old behaviour in its docstring).
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch

from app.cli import build_parser
from recon.formats import FORMAT_VERSION
from recon.simulate import synthetic_psf
from recon.trade import Config, TradeRow
from recon.udn.rundir import RunLock
from tests.clirun import run_cli

#: two cheap settings: the tests are about the command, not the grid
GRID = [Config("fista", 1e-4, (5, 10)), Config("fista", 1e-3, (5,))]


@pytest.fixture
def small_grid(monkeypatch):
    import recon.trade as rt

    monkeypatch.setattr(rt, "default_grid", lambda quick=False, with_udn=True: list(GRID))


@pytest.fixture
def pair(tmp_path):
    psf = synthetic_psf((24, 32), seed=1)
    meas = np.random.default_rng(0).random((24, 32)).astype(np.float32)
    np.save(tmp_path / "psf.npy", psf)
    np.save(tmp_path / "meas.npy", meas)
    return ["--meas", str(tmp_path / "meas.npy"), "--psf", str(tmp_path / "psf.npy")]


@pytest.fixture
def keep_torch_threads():
    old = torch.get_num_threads()
    yield
    torch.set_num_threads(old)


def test_the_global_threads_option_reaches_trade(pair, small_grid, tmp_path, capsys,
                                                 monkeypatch, keep_torch_threads):
    """`lenslesscam --threads 1 trade ...` reported 'N torch thread(s): auto': trade's own
    --threads default (0) replaced the global request; trade.md's command dropped it."""
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    out = tmp_path / "t"
    code, _, err = run_cli(capsys, "--threads", 1, "trade", *pair, "--budgets", "1",
                           "--out", out)
    assert code == 0, err
    md = (out / "trade.md").read_text()
    assert "1 torch thread(s): requested" in md
    assert "Produced by `lenslesscam --threads 1 trade" in md
    csv_text = (out / "trade.csv").read_text()
    assert "# command: lenslesscam --threads 1 trade" in csv_text and "# threads: 1" in csv_text
    # trade's own --threads wins over the global one
    code, _, err = run_cli(capsys, "--threads", 2, "trade", *pair, "--threads", 1,
                           "--budgets", "1", "--out", tmp_path / "t2")
    assert code == 0, err
    assert "1 torch thread(s): requested" in (tmp_path / "t2" / "trade.md").read_text()
    assert build_parser().parse_args(["trade", *pair, "--out", "x"]).threads is None


def test_a_trade_begun_with_the_global_threads_before_resumes(pair, small_grid, tmp_path,
                                                              capsys, monkeypatch,
                                                              keep_torch_threads):
    """An earlier release keyed `lenslesscam --threads 1 trade ...`'s journal with threads 0
    (trade's own default won); the same command must still go on where it stopped."""
    import recon.trade as rt

    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    out = tmp_path / "t"
    real = rt.run_trade

    def one_setting_then_interrupted(case, grid, **kw):
        seen: list[str] = []
        for row in real(case, grid, **kw):
            if row.setting not in seen:
                seen.append(row.setting)
                if len(seen) == 2:
                    raise KeyboardInterrupt
            yield row

    monkeypatch.setattr(rt, "run_trade", one_setting_then_interrupted)
    # as the earlier release ran it: the request recorded as 0
    assert run_cli(capsys, "trade", *pair, "--budgets", "1", "--out", out)[0] == 130
    monkeypatch.setattr(rt, "run_trade", real)
    code, _, err = run_cli(capsys, "--threads", 1, "trade", *pair, "--budgets", "1",
                           "--out", out)
    assert code == 0, err
    assert "1 settings already measured" in err


def test_trade_refuses_a_udn_run_folder(pair, small_grid, tmp_path, capsys):
    """`trade --out RUN` on a UDN run folder said 'another trade is writing this folder'
    while the job ran (trade took the job's run.lock), and wrote beside the run's files
    once it had ended."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "run.json").write_text(json.dumps({"format": "lenslesscam.udn_run",
                                              "format_version": FORMAT_VERSION,
                                              "status": "running"}))
    before = sorted(p.name for p in run.iterdir())
    with RunLock(run):  # the job holds its lock
        code, stdout, err = run_cli(capsys, "trade", *pair, "--out", run, "--overwrite")
    assert code == 2 and stdout == ""
    assert len(err.strip().splitlines()) == 1
    assert f"--out {run} writes into the UDN run folder {run}" in err
    assert "another trade" not in err
    code, _, err = run_cli(capsys, "trade", *pair, "--out", run)  # the job has ended
    assert code == 2 and "writes into the UDN run folder" in err
    assert sorted(p.name for p in run.iterdir()) == [*before, "run.lock"]


def test_a_busy_trade_folder_names_the_trade_that_holds_it(pair, small_grid, tmp_path, capsys):
    """The lock is the trade's own (trade.lock), and the refusal names its holder; a folder
    with a run.lock held by someone else (a batch driver, say) is no trade's."""
    out = tmp_path / "t"
    with RunLock(out, name="trade.lock"):
        code, _, err = run_cli(capsys, "trade", *pair, "--budgets", "1", "--out", out)
    assert code == 2
    assert f"another trade is writing this folder (pid {os.getpid()} on " in err
    assert "trade.lock is held" in err
    other = tmp_path / "o"
    with RunLock(other):  # run.lock: not a trade's lock
        code, _, err = run_cli(capsys, "trade", *pair, "--budgets", "1", "--out", other)
    assert code == 0, err
    # the lock file stays, as every RunLock's (removing it would let two writers lock two
    # different files)
    assert {"trade.lock", "trade.csv"} <= {p.name for p in other.iterdir()}


def test_trade_help_states_the_budgets_default(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["trade", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "(default 0.5,2,10,60)" in text
    assert "lenslesscam --threads N" in text


# -- plan --trade --------------------------------------------------------------------------------


def _write_trade(path):

    def row(setting, method, tau, precision, its, wall, q, channels=0):
        return TradeRow("c", setting, method, tau, precision, 1, channels, its, wall, 4.0, q,
                        0.01)

    rows = [row("fista tau=1e-05", "fista", 1e-5, "float32", 50, 0.1, 30.0),
            row("fista tau=0.0003", "fista", 3e-4, "float32", 200, 0.8, 32.0),
            row("fista tau=0.0001 float64", "fista", 1e-4, "float64", 200, 0.9, 35.0),
            row("udn ch32 bf16", "udn", 0.0, "bf16", 100, 0.05, 36.0, channels=32)]
    _write_rows(path, rows)


def _write_rows(path, rows):
    """A trade.csv as ``lenslesscam trade`` writes it (DictWriter over TradeRow.as_dict)."""
    import csv

    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0].as_dict()))
        w.writeheader()
        for r in rows:
            w.writerow(r.as_dict())


@pytest.fixture
def plan_inputs(tmp_path):
    psf = synthetic_psf((48, 64), seed=1)
    meas = np.random.default_rng(0).random((48, 64)).astype(np.float32)
    np.save(tmp_path / "psf.npy", psf)
    np.save(tmp_path / "meas.npy", meas)
    _write_trade(tmp_path / "trade.csv")
    return ["--psf", str(tmp_path / "psf.npy"), "--meas", str(tmp_path / "meas.npy")]


def test_plan_chooses_among_settings_its_run_reproduces(plan_inputs, tmp_path, capsys):
    """`plan --trade --budget 1s` chose 'fista tau=0.0001 float64', but a plan has no
    precision: recon auto ran it in float32. A UDN row that does not record the network it
    ran (a trade.csv of an older release) is no plan's either."""
    trade = tmp_path / "trade.csv"
    code, stdout, err = run_cli(capsys, "plan", *plan_inputs, "--trade", trade, "--budget", "1s",
                                "--json", "--no-probe")
    assert code == 0, err
    plan = json.loads(stdout)
    assert plan["method"] == "fista-tv" and plan["tau"] == pytest.approx(3e-4)
    assert plan["iterations"] == 200
    why = plan["reasons"]["method"]
    assert ("the best of 2 measured settings a float32 plan reproduces within 1 s was fista "
            "tau=0.0003") in why
    assert ("udn ch32 bf16 (36.00 dB) was better but its trade.csv row does not record the "
            "network settings it ran") in why
    # recon auto --float64 computes in float64: the float64 setting is its to take
    code, stdout, err = run_cli(capsys, "recon", "auto", *plan_inputs, "--trade", trade,
                                "--budget", "1s", "--float64", "--quiet",
                                "--out", tmp_path / "r.tif")
    assert code == 0, err
    from recon.io import read_reconstruction

    _, meta = read_reconstruction(tmp_path / "r.tif")
    assert meta["plan"]["tau"] == pytest.approx(1e-4)
    assert "settings a float64 plan reproduces" in meta["plan"]["reasons"]["method"]
    # a budget only another precision fits: refused, saying why
    code, _, err = run_cli(capsys, "plan", *plan_inputs, "--trade", trade, "--budget", "0.07s",
                           "--no-probe")
    assert code == 2
    assert ("no measured setting fits the budget of 0.07 s in float32 (its float64 settings are "
            "not candidates: the plan runs in float32); udn ch32 bf16 fits but its trade.csv "
            "row does not record the network settings it ran") in err


def test_plan_trade_names_a_folder_in_one_line(plan_inputs, tmp_path, capsys):
    """`plan --trade DIR` said '[Errno 21] Is a directory'."""
    folder = tmp_path / "tr"
    folder.mkdir()
    for cmd in (["plan"], ["recon", "auto", "--out", tmp_path / "x.tif"]):
        code, _, err = run_cli(capsys, *cmd, *plan_inputs, "--trade", folder, "--budget", "1s")
        assert code == 2 and len(err.strip().splitlines()) == 1
        assert f"--trade {folder} is a folder, not a trade.csv" in err and "Errno" not in err
    (folder / "trade.csv").write_text((tmp_path / "trade.csv").read_text())
    code, _, err = run_cli(capsys, "plan", *plan_inputs, "--trade", folder, "--budget", "1s")
    assert code == 2 and f"(--trade {folder / 'trade.csv'})" in err


def test_a_float32_udn_setting_stays_a_candidate_under_float64(tmp_path):
    """With recon auto --float64 only float64 rows were candidates, though a plan's UDN runs
    its network in the precision its row measured whatever the flag says (the plan carries
    the row's settings, a bf16 one's precision among them)."""

    from app.commands.plan import plan_from_trade
    from recon.trade import udn_settings, write_trade_csv

    net32 = udn_settings(Config("udn", channels=32))
    rows = [TradeRow("c", "fista tau=0.0001 float64", "fista", 1e-4, "float64", 1, 0, 200,
                     0.9, 4.0, 35.0, 0.01),
            TradeRow("c", "udn ch32", "udn", 0.0, "float32", 1, 32, 100, 0.5, 4.0, 40.0, 0.01,
                     udn_settings=net32)]
    path = write_trade_csv(tmp_path / "trade.csv", rows, [])
    from recon.plan import Plan

    base = Plan(model="2d", k=1, sensor=(48, 64), field=(48, 64), region=(0, 0, 48, 64),
                downsample=1, method="fista-tv", iterations=300, budget_s=1.0)
    for precision in ("float64", "float32"):
        plan = plan_from_trade(base, path, None, precision=precision)
        assert plan.method == "udn" and plan.udn == net32
    net16 = udn_settings(Config("udn", channels=32, precision="bf16"))
    rows.append(TradeRow("c", "udn ch32 bf16", "udn", 0.0, "bf16", 1, 32, 100, 0.4, 4.0, 41.0,
                         0.01, udn_settings=net16))
    path = write_trade_csv(tmp_path / "trade.csv", rows, [])
    plan = plan_from_trade(base, path, None)
    assert plan.udn["config"]["precision"] == "bf16" and plan.udn == net16


@pytest.mark.parametrize("value", [0.0, 0.5])
def test_a_constant_truth_is_refused_before_any_setting_runs(pair, small_grid, tmp_path,
                                                             capsys, value):
    """`trade --truth` with an all-zero or constant truth ran its first setting, then stopped
    with "ref is constant ... pass data_range explicitly" (no file named, an option trade does
    not have), leaving trade.partial.jsonl and trade.lock; a UDN run scored it only at its end
    ("not scored"). The problem loader refuses it, naming the file."""
    np.save(tmp_path / "t.npy", np.full((24, 32), value, np.float32))
    code, _, err = run_cli(capsys, "trade", *pair, "--truth", tmp_path / "t.npy", "--quick",
                           "--no-udn", "--out", tmp_path / "out")
    assert code == 2
    assert f"truth file {tmp_path / 't.npy'} is constant (every value is {value:g}" in err
    assert "data_range" not in err and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()


def test_a_trade_that_measured_nothing_leaves_nothing(pair, small_grid, tmp_path, capsys):
    """A trade refused at its first setting (4 measured pixels: "the held-out proxy needs at
    least 20") left trade.partial.jsonl and trade.lock in the folder it made; the next trade of
    other data into that folder was refused as "the partial result of another trade"."""
    np.save(tmp_path / "p2.npy", np.random.default_rng(0).random((2, 2)).astype(np.float32))
    np.save(tmp_path / "m2.npy", np.random.default_rng(1).random((2, 2)).astype(np.float32))
    tiny = ["--psf", tmp_path / "p2.npy", "--meas", tmp_path / "m2.npy", "--quick", "--no-udn"]
    code, _, err = run_cli(capsys, "trade", *tiny, "--out", tmp_path / "new")
    assert code == 2 and "held-out proxy needs at least 20" in err
    assert not (tmp_path / "new").exists()  # the folder it made, gone with it
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    code, _, err = run_cli(capsys, "trade", *tiny, "--out", tmp_path / "mine")
    assert code == 2
    assert not (tmp_path / "mine" / "trade.partial.jsonl").exists()
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep"
    code, _, err = run_cli(capsys, "trade", *pair, "--quick", "--no-udn", "--out",
                           tmp_path / "mine")
    assert code == 0, err
    assert (tmp_path / "mine" / "trade.csv").is_file()


def test_a_csv_field_over_csvs_limit_is_a_format_error(tmp_path, capsys):
    """(GUI review) A trade.csv with a field over csv's 128 KiB limit raised csv.Error, no
    ValueError: every guard let it through (the app's New UDN job did nothing, a traceback on
    stderr; Load trade.csv… kept the previous file's error); a batch manifest likewise."""
    from recon.formats import FormatError
    from recon.suggest import find_suggestions  # noqa: F401  (its guard catches ValueError)
    from recon.trade import read_trade_csv

    big = tmp_path / "trade.csv"
    big.write_text("case,setting\nim65,\"" + "x" * 200_000 + "\"\n")
    with pytest.raises(FormatError, match=r"trade\.csv: not a readable trade\.csv \(line \d+: "
                                          r"field larger than field limit"):
        read_trade_csv(big)
    manifest = tmp_path / "m.csv"
    manifest.write_text("measurement,psf,method\n\"" + "x" * 200_000 + "\",p.npy,fista\n")
    code, _, err = run_cli(capsys, "batch", "run", manifest, "--out", tmp_path / "b")
    assert code == 2 and "not readable as CSV (field larger than field limit" in err, err
    assert "Traceback" not in err and not (tmp_path / "b").exists()
