"""The speed/accuracy trade: rows, held-out proxy honesty, summaries and the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.stats import spearmanr

from app.cli import main
from recon.formats import FORMAT_VERSION, FormatError, array_hash, file_hash
from recon.models import build_model
from recon.simulate import simulate, synthetic_psf
from recon.trade import (
    Case,
    Config,
    TradeRow,
    best_for_budgets,
    case_differences,
    case_record,
    pareto_front,
    rank_correlation,
    read_trade,
    read_trade_csv,
    run_trade,
    write_trade_csv,
)


def _case(erasure=0.5, seed=0, corrupt_holdout=None):
    psf = synthetic_psf((24, 32), seed=seed)
    scene = np.zeros((1, 1, 24, 32), np.float32)
    scene[..., 5:15, 6:20] = 1.0
    scene[..., 12:20, 14:28] += 0.5
    sim = simulate(build_model("2d", psf), scene, erasure=erasure, noise=0.01, seed=seed)
    return Case("tiny", psf[None], sim.meas, sim.mask, sim.truth)


GRID = [
    Config("fista", 1e-4, (10, 40)),
    Config("admm", 1e-4, (10, 40)),
    Config("fista", 1e-4, (10,), precision="float64"),
    Config("fista", 1e-4, (10,), downsample=2),
    Config("udn", checkpoints=(3, 6), channels=4, scales=2),
]


def test_rows_for_every_setting_and_checkpoint():
    rows = list(run_trade(_case(), GRID))
    assert len(rows) == sum(len(c.checkpoints) for c in GRID)
    assert {r.method for r in rows} == {"fista", "admm", "udn"}
    for r in rows:
        assert np.isfinite(r.heldout_psnr) and np.isfinite(r.psnr) and 0 <= r.residual < 10
        assert r.wall_s >= 0 and (r.peak_mem_mb is None or r.peak_mem_mb >= 0)
    by = {(r.setting, r.iterations): r for r in rows}
    assert by[("fista tau=0.0001", 40)].wall_s >= by[("fista tau=0.0001", 10)].wall_s
    assert by[("fista tau=0.0001", 40)].psnr > by[("fista tau=0.0001", 10)].psnr


def test_held_out_pixels_are_hidden_from_the_reconstruction():
    """Changing the held-out pixels' values changes the proxy but not the reconstruction."""
    case = _case()
    grid = [Config("fista", 1e-4, (30,))]
    first = next(run_trade(case, grid, seed=3))
    # find the held-out pixels the same way run_trade does, and corrupt them
    measured = np.flatnonzero(case.mask > 0)
    rng = np.random.default_rng(3)
    n_hold = max(1, round(0.05 * measured.size), min(200, measured.size // 4))
    hold = rng.choice(measured, n_hold, replace=False)
    bad = case.meas.copy().reshape(1, -1)
    bad[0, hold] += 5.0
    second = next(run_trade(Case("tiny", case.psf, bad.reshape(case.meas.shape), case.mask,
                                 case.truth), grid, seed=3))
    assert second.psnr == pytest.approx(first.psnr, abs=1e-9)
    assert second.heldout_psnr < first.heldout_psnr - 10


def test_proxy_ranks_like_true_psnr_on_a_simulated_case():
    grid = [Config("fista", t, (5, 20, 80)) for t in (1e-5, 1e-3, 3e-2)]
    rows = list(run_trade(_case(erasure=0.0), grid))
    rho = rank_correlation([r.heldout_psnr for r in rows], [r.psnr for r in rows])
    assert rho > 0.5, rho


def test_summaries():
    def row(w, q):
        return TradeRow("c", f"s{w}", "fista", 0, "float32", 1, 0, 1, w, None, q, 0.1, psnr=q)

    rows = [row(1, 10), row(2, 9), row(3, 12), row(4, 12), row(5, 15)]
    assert [r.wall_s for r in pareto_front(rows)] == [1, 3, 5]
    best = best_for_budgets(rows, [0.5, 2, 10])
    assert best[0.5] is None and best[2].wall_s == 1 and best[10].wall_s == 5
    a, b = [1, 2, 3, 4, 5, 5], [2, 1, 4, 3, 6, 6]
    assert rank_correlation(a, b) == pytest.approx(spearmanr(a, b).statistic)
    with pytest.raises(ValueError):
        rank_correlation([1, 2], [1, 2])


def test_cli_writes_csv_markdown_and_plot(tmp_path, capsys):
    case = _case()
    np.save(tmp_path / "psf.npy", case.psf[0])
    np.save(tmp_path / "meas.npy", case.meas)
    np.save(tmp_path / "mask.npy", case.mask)
    np.save(tmp_path / "truth.npy", case.truth)
    code = main(["trade", "--meas", str(tmp_path / "meas.npy"), "--psf", str(tmp_path / "psf.npy"),
                 "--mask", str(tmp_path / "mask.npy"), "--truth", str(tmp_path / "truth.npy"),
                 "--quick", "--no-udn", "--out", str(tmp_path / "out")])
    assert code == 0
    out = capsys.readouterr().out
    assert "Spearman rank correlation" in out and "Best setting per time budget" in out
    text = (tmp_path / "out" / "trade.csv").read_text()
    assert text.startswith(f"# format: lenslesscam.trade\n# format_version: {FORMAT_VERSION}\n")
    header = next(ln for ln in text.splitlines() if not ln.startswith("#")).split(",")
    assert {"wall_s", "peak_mem_mb", "heldout_psnr", "psnr"} <= set(header)
    # the header records the case it was measured on, as the loader gave it to the solvers
    trade = read_trade(tmp_path / "out" / "trade.csv")
    assert trade.format_version == FORMAT_VERSION and len(trade.cases) == 1
    rec = trade.cases[0]
    assert rec["shape"] == [1, 24, 32] and rec["field"] == [24, 32] and rec["truth"] is True
    assert rec["psf_hash"] == array_hash(case.psf)
    assert rec["erasure"] == pytest.approx(0.5, abs=0.02)
    assert rec["source"]["psf_file_hash"] == file_hash(tmp_path / "psf.npy")
    assert trade.meta["command"].startswith("lenslesscam trade") and "created_utc" in trade.meta
    png = (tmp_path / "out" / "trade_pareto.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000
    # the plot and inputs.json say what they are (they had no format, version or provenance)
    from PIL import Image

    with Image.open(tmp_path / "out" / "trade_pareto.png") as im:
        tag = json.loads(im.text["lenslesscam"])
    assert tag["format"] == "lenslesscam.trade_plot" and tag["format_version"] == FORMAT_VERSION
    assert "versions" in tag["provenance"]
    inputs = json.loads((tmp_path / "out" / "inputs.json").read_text())
    assert inputs["format"] == "lenslesscam.trade_inputs"
    assert inputs["format_version"] == FORMAT_VERSION and inputs["measurement"]
    json.dumps(out)  # printable


def test_cli_on_a_colour_pair_in_the_dataset_layout_scores_the_sensor_field(tmp_path, capsys):
    """A padded-grid PSF, a sensor-size measurement and truth, stored BGR and upside-down (the
    DiffuserCam MirFlickr layout): trade reconstructs the sensor's field, as recon fista does,
    in colour, and scores it against the truth (it used to reconstruct the padded grid and stop
    on the shapes)."""
    from tests.scenes import dataset_layout_pair

    dataset_layout_pair(tmp_path)
    code = main(["trade", "--meas", str(tmp_path / "meas.npy"), "--psf", str(tmp_path / "psf.npy"),
                 "--truth", str(tmp_path / "truth.npy"), "--rgb", "--channel-order", "bgr",
                 "--flip-rows", "--quick", "--no-udn", "--out", str(tmp_path / "out")])
    assert code == 0, capsys.readouterr().err
    capsys.readouterr()
    from recon.trade import read_trade_csv

    best = max(r.psnr or 0.0 for r in read_trade_csv(tmp_path / "out" / "trade.csv"))
    assert best > 20, best  # the scene is found: the truth's frame and channels match


def test_a_csv_that_is_not_a_trade_is_named(tmp_path):
    """The trade panel showed only "could not convert string to float: ''"."""
    from recon.trade import read_trade_csv

    (tmp_path / "x.csv").write_text("a,b\n1,2\n")
    with pytest.raises(ValueError, match=r"not a trade\.csv from lenslesscam trade \(no column "
                                         r"case, setting"):
        read_trade_csv(tmp_path / "x.csv")
    import dataclasses

    header = ",".join(f.name for f in dataclasses.fields(TradeRow) if f.name != "extra")
    (tmp_path / "t.csv").write_text(header + "\n" + ",".join(["c", "s", "fista", "oops"]
                                                             + ["1"] * 10) + "\n")
    with pytest.raises(ValueError, match=r"t\.csv line 2: column tau is 'oops', not a number"):
        read_trade_csv(tmp_path / "t.csv")


@pytest.mark.parametrize(("budgets", "message"), [
    ("0", "finite and > 0"), ("1,nan", "finite and > 0"), ("abc", "seconds separated"),
])
def test_bad_budgets_are_refused_before_any_work(tmp_path, capsys, budgets, message):
    assert main(["trade", "--sample", "tutorial", "--quick", "--no-udn", "--budgets", budgets,
                 "--out", str(tmp_path / "t")]) == 2
    assert f"--budgets must be {message}" in capsys.readouterr().err
    assert not (tmp_path / "t").exists()


def _rows(case_name="c"):
    return [TradeRow(case_name, "fista tau=1e-05", "fista", 1e-5, "float32", 1, 0, 50, 0.1, 4.0,
                     30.0, 0.01, psnr=20.5, ssim=0.5),
            TradeRow(case_name, "udn ch16", "udn", 0.0, "bf16", 2, 16, 100, 3.0, None, 31.0,
                     0.02)]


def test_trade_csv_header_round_trip(tmp_path):
    """Format, version, provenance and a case line per case; rows read back unchanged, a
    '#' in a cell quoted (pandas' comment="#" would cut an unquoted row there)."""
    case = _case()
    rows = _rows("scene #2, left")
    path = write_trade_csv(tmp_path / "trade.csv", rows, [case], command="lenslesscam trade x")
    lines = path.read_text().splitlines()
    assert lines[:2] == ["# format: lenslesscam.trade", f"# format_version: {FORMAT_VERSION}"]
    assert "# command: lenslesscam trade x" in lines
    table = [ln for ln in lines if not ln.startswith("#")]
    assert table[0].startswith("case,setting,") and len(table) == 3
    assert all(ln.startswith('"scene #2, left","') for ln in table[1:])
    trade = read_trade(path)
    assert [r.as_dict() for r in trade.rows] == [r.as_dict() for r in rows]
    assert trade.cases == [json.loads(json.dumps(case_record(case)))]
    assert trade.meta["command"] == "lenslesscam trade x" and trade.format_version == 1


def test_a_trade_csv_with_a_nan_score_or_negative_time_is_named(tmp_path):
    """A NaN PSNR won every budget in plan --trade ('... at 30 iterations (0.02 s, nan dB)');
    a negative wall time was taken as fast."""
    import dataclasses

    rows = _rows()
    for bad, words in ((dataclasses.replace(rows[0], psnr=float("nan")), "column psnr is 'nan'"),
                       (dataclasses.replace(rows[0], wall_s=-1.0), "a negative wall time")):
        path = write_trade_csv(tmp_path / "trade.csv", [bad, *rows[1:]], [_case()])
        with pytest.raises(ValueError, match=words):
            read_trade(path)


def test_old_trade_csv_without_header_is_still_read(tmp_path):
    """Files written before the header (on users' disks): version 0, no cases."""
    import csv

    rows = _rows()
    with open(tmp_path / "trade.csv", "w", newline="") as fh:  # the old writer, verbatim
        w = csv.DictWriter(fh, fieldnames=list(rows[0].as_dict()))
        w.writeheader()
        for r in rows:
            w.writerow(r.as_dict())
    trade = read_trade(tmp_path / "trade.csv")
    assert trade.format_version == 0 and trade.cases == [] and trade.meta == {}
    assert [r.as_dict() for r in trade.rows] == [r.as_dict() for r in rows]
    assert [r.as_dict() for r in read_trade_csv(tmp_path / "trade.csv")] == [
        r.as_dict() for r in rows]


def test_a_newer_or_foreign_trade_csv_is_refused_in_one_line(tmp_path):
    path = write_trade_csv(tmp_path / "trade.csv", _rows(), [_case()])
    text = path.read_text()
    path.write_text(text.replace(f"# format_version: {FORMAT_VERSION}\n",
                                 f"# format_version: {FORMAT_VERSION + 1}\n"))
    with pytest.raises(FormatError) as err:
        read_trade(path)
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg
    assert f"format version {FORMAT_VERSION + 1} is newer than this lenslesscam reads" in msg
    path.write_text(text.replace("# format: lenslesscam.trade", "# format: lenslesscam.other"))
    with pytest.raises(FormatError, match=r"not a trade\.csv \(its format is "
                                          r"'lenslesscam\.other'"):
        read_trade(path)


def test_case_differences_compare_shape_field_and_psf():
    case = _case()
    rec = case_record(case)
    same = case_record(Case("other scene", case.psf, case.meas * 0.5))  # no mask: erasure 0
    assert case_differences(rec, same) == []
    other_psf = case_record(Case("p", synthetic_psf((24, 32), seed=7)[None], case.meas))
    assert case_differences(rec, other_psf) == ["another PSF"]
    # the same PSF file read with other options (another array) is the same PSF
    rec_f = {**rec, "source": {"psf_file_hash": "abc"}}
    assert case_differences(rec_f, {**other_psf, "source": {"psf_file_hash": "abc"}}) == []
    big = case_record(Case("b", synthetic_psf((48, 64), seed=0)[None],
                           np.zeros((1, 48, 64), np.float32)))
    assert case_differences(rec, big) == ["measurement 1x24x32 (here 1x48x64)",
                                          "scene field 24x32 (here 48x64)", "another PSF"]
    full = case_record(Case("f", case.psf, case.meas, field=(48, 64)))
    assert case_differences(rec, full) == ["scene field 24x32 (here 48x64)"]


def _trade_files(tmp_path):
    """The quick trade's command line (no --out) on a case saved as files in ``tmp_path``."""
    case = _case()
    for name, a in (("psf", case.psf[0]), ("meas", case.meas), ("mask", case.mask),
                    ("truth", case.truth)):
        np.save(tmp_path / f"{name}.npy", a)
    return ["trade", *(x for n in ("meas", "psf", "mask", "truth")
                       for x in (f"--{n}", str(tmp_path / f"{n}.npy"))),
            "--quick", "--no-udn", "--threads", "1"]


def _interrupted_at_third(real, ran):
    """``run_trade`` that records the settings it ran in ``ran`` and stops (Ctrl-C) at the
    third setting's first row: two are complete."""
    def interrupted(case, grid, **kw):
        for row in real(case, grid, **kw):
            if row.setting not in ran:
                ran.append(row.setting)
            if len(ran) == 3:
                raise KeyboardInterrupt
            yield row

    return interrupted


def test_an_interrupted_trade_goes_on_where_it_was(tmp_path, capsys, monkeypatch):
    """trade --protocol takes 20 minutes, and an interrupt lost all of it: each measured
    setting is kept in trade.partial.jsonl, and the same command skips what it holds."""
    import recon.trade as rt

    argv = _trade_files(tmp_path)
    real = rt.run_trade
    ran: list[str] = []
    interrupted = _interrupted_at_third(real, ran)

    monkeypatch.setattr(rt, "run_trade", interrupted)
    assert main([*argv, "--out", str(tmp_path / "out")]) == 130
    journal = tmp_path / "out" / "trade.partial.jsonl"
    assert journal.is_file() and not (tmp_path / "out" / "trade.csv").exists()
    first_two = ran[:2]

    ran.clear()

    def counted(case, grid, **kw):
        for row in real(case, grid, **kw):
            if row.setting not in ran:
                ran.append(row.setting)
            yield row

    monkeypatch.setattr(rt, "run_trade", counted)
    capsys.readouterr()
    assert main([*argv, "--out", str(tmp_path / "out")]) == 0
    assert "2 settings already measured" in capsys.readouterr().err
    assert not set(first_two) & set(ran) and len(ran) == 9 - 2  # the quick grid has 9
    assert not journal.exists()
    resumed = read_trade(tmp_path / "out" / "trade.csv")
    assert main([*argv, "--out", str(tmp_path / "whole")]) == 0
    whole = read_trade(tmp_path / "whole" / "trade.csv")
    capsys.readouterr()
    key = [(r.setting, r.iterations) for r in whole.rows]
    assert [(r.setting, r.iterations) for r in resumed.rows] == key  # the grid's order
    # another command's journal in the folder (here: another --dark) is refused, not mixed in
    monkeypatch.setattr(rt, "run_trade", interrupted)
    ran.clear()
    assert main([*argv, "--out", str(tmp_path / "other")]) == 130
    assert main([*argv, "--dark", "0", "--out", str(tmp_path / "other")]) == 2
    assert "is the partial result of another trade" in capsys.readouterr().err
    # a line cut by a kill is dropped (that setting runs again), not appended to
    journal = tmp_path / "other" / "trade.partial.jsonl"
    journal.write_text(journal.read_text() + '{"case": "meas", "setting": "fi')
    monkeypatch.setattr(rt, "run_trade", counted)
    ran.clear()
    assert main([*argv, "--out", str(tmp_path / "other")]) == 0
    assert "2 settings already measured" in capsys.readouterr().err and len(ran) == 7
    # --overwrite discards another command's journal
    monkeypatch.setattr(rt, "run_trade", interrupted)
    ran.clear()
    assert main([*argv, "--out", str(tmp_path / "third")]) == 130
    monkeypatch.setattr(rt, "run_trade", counted)
    ran.clear()
    assert main([*argv, "--dark", "0", "--overwrite", "--out", str(tmp_path / "third")]) == 0
    assert "discarded" in capsys.readouterr().err and len(ran) == 9


def test_a_resumed_trade_reports_the_time_of_every_session(tmp_path, capsys, monkeypatch):
    """trade.md's "produced in N s" counted only the last session of a resumed trade: each
    journal line now says its session and how long that session had run, and the total
    counts the earlier sessions too."""
    import re
    import time
    import types

    import app.commands.trade as trade_cmd
    import recon.trade as rt

    case = _case()
    for name, a in (("psf", case.psf[0]), ("meas", case.meas), ("mask", case.mask)):
        np.save(tmp_path / f"{name}.npy", a)
    argv = ["trade", *(x for n in ("meas", "psf", "mask")
                       for x in (f"--{n}", str(tmp_path / f"{n}.npy"))),
            "--quick", "--no-udn", "--threads", "1", "--out", str(tmp_path / "out")]
    real = rt.run_trade
    # the command's clock; the first session's second setting takes 1000 s (without waiting)
    skew = [0.0]
    monkeypatch.setattr(trade_cmd, "time", types.SimpleNamespace(
        perf_counter=lambda: time.perf_counter() + skew[0]))

    def long_then_interrupted(case, grid, **kw):
        ran: list[str] = []
        for row in real(case, grid, **kw):
            if row.setting not in ran:
                ran.append(row.setting)
                if len(ran) == 2:
                    skew[0] += 1000.0
                if len(ran) == 3:  # two settings are complete
                    raise KeyboardInterrupt
            yield row

    monkeypatch.setattr(rt, "run_trade", long_then_interrupted)
    assert main(argv) == 130
    journal = tmp_path / "out" / "trade.partial.jsonl"
    lines = [json.loads(ln) for ln in journal.read_text().splitlines()[1:]]
    assert len(lines) == 2

    monkeypatch.setattr(rt, "run_trade", real)
    capsys.readouterr()
    t0 = time.perf_counter()
    assert main(argv) == 0
    second = time.perf_counter() - t0
    capsys.readouterr()
    md = (tmp_path / "out" / "trade.md").read_text()
    m = re.search(r"Produced by `lenslesscam trade[^`]*` in (\d+) s", md)
    assert m, md[:300]
    # the first session's 1000 s are in the total (the old text gave this session's alone)
    assert int(m.group(1)) >= 1000, m.group(0)
    # the first session up to its last measured setting, and this one
    assert int(m.group(1)) <= lines[1]["session_s"] + second + 1, m.group(0)
    assert m.group(0) + " over 2 sessions" in md
    # the journal said which session measured each setting and how long it had run
    assert [e["session"] for e in lines] == [0, 0]
    assert lines[1]["session_s"] >= 1000 and lines[1]["setting_s"] >= 1000
    assert lines[1]["session_s"] == pytest.approx(lines[0]["session_s"] + lines[1]["setting_s"],
                                                  abs=0.01)
    # a journal of an older release (no session times): the time says it is this session's
    monkeypatch.setattr(rt, "run_trade", long_then_interrupted)
    skew[0] = 0.0
    assert main([*argv, "--overwrite"]) == 130
    head, *rest = journal.read_text().splitlines()
    old = [{k: v for k, v in json.loads(ln).items()
            if k not in ("session", "session_s", "setting_s")} for ln in rest]
    journal.write_text("\n".join([head, *(json.dumps(e) for e in old)]) + "\n")
    monkeypatch.setattr(rt, "run_trade", real)
    assert main([*argv, "--overwrite"]) == 0
    assert "2 settings already measured" in capsys.readouterr().err
    md = (tmp_path / "out" / "trade.md").read_text()
    assert "in this session of 2 (resumed; the earlier sessions' time is not in" in md
    assert " over 2 sessions" not in md


def test_a_trade_in_one_session_says_no_sessions(tmp_path, capsys):
    case = _case()
    for name, a in (("psf", case.psf[0]), ("meas", case.meas), ("mask", case.mask)):
        np.save(tmp_path / f"{name}.npy", a)
    assert main(["trade", "--meas", str(tmp_path / "meas.npy"), "--psf",
                 str(tmp_path / "psf.npy"), "--mask", str(tmp_path / "mask.npy"), "--quick",
                 "--no-udn", "--threads", "1", "--budgets", "1",
                 "--out", str(tmp_path / "out")]) == 0
    capsys.readouterr()
    md = (tmp_path / "out" / "trade.md").read_text()
    assert "session" not in md and "Produced by `lenslesscam trade" in md


def test_a_udn_row_records_the_settings_it_ran_and_reads_them_back(tmp_path):
    """A UDN row recorded only its width and precision: a plan made from it could not tell
    the scales, skips, learning rate or early stop it measured (it ran its own default)."""
    cfg = Config("udn", checkpoints=(2,), channels=4, scales=2)
    rows = list(run_trade(_case(), [Config("fista", 1e-4, (5,)), cfg], seed=3))
    fista, udn = rows
    assert fista.udn_settings is None
    net, run = udn.udn_settings["network"], udn.udn_settings["config"]
    assert net["scales"] == 2 and net["channels"] == 4 and net["variant"] == "2d"
    assert run["lr"] == 0.01 and run["ema"] == 0.9 and run["precision"] == "float32"
    # not the row's: its count, the budget, the seed, the trade's own stop (no held-out
    # pixels of the network's: a job made from the row keeps its early stop), the machine's
    for key in ("max_iter", "time_limit_s", "seed", "holdout", "patience", "min_iter",
                "min_delta", "compile", "channels_last", "snapshot_every"):
        assert key not in run, key
    path = write_trade_csv(tmp_path / "trade.csv", rows, [_case()])
    assert [r.udn_settings for r in read_trade(path).rows] == [None, udn.udn_settings]
    # a cell that is not the settings object: one line naming the file, line and column
    text = path.read_text()
    cell = text.splitlines()[-1].split(',"', 1)[1].rsplit('"', 1)[0]
    path.write_text(text.replace(cell, "[1, 2]"))
    with pytest.raises(ValueError) as err:
        read_trade(path)
    assert "\n" not in str(err.value) and f"{path} line" in str(err.value)
    assert "column udn_settings is '[1, 2]', not a JSON object" in str(err.value)


def test_a_newer_or_damaged_trade_journal_is_said(tmp_path, capsys, monkeypatch):
    """A journal of a newer format version was resumed (its rows' new fields dropped), and a
    line that could not be read was measured again without a word."""
    import json

    import recon.trade as rt

    argv = [*_trade_files(tmp_path), "--out", str(tmp_path / "out")]
    real = rt.run_trade
    ran: list[str] = []
    interrupted = _interrupted_at_third(real, ran)

    monkeypatch.setattr(rt, "run_trade", interrupted)
    assert main(argv) == 130
    journal = tmp_path / "out" / "trade.partial.jsonl"
    lines = journal.read_text().splitlines(keepends=True)
    head = json.loads(lines[0])
    journal.write_text(json.dumps({**head, "format_version": 9}) + "\n" + "".join(lines[1:]))
    before = journal.read_bytes()
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "has format_version 9, which this release does not read" in err, err
    assert journal.read_bytes() == before
    # --overwrite discards it, as the message says (it refused all the same)
    newer = journal.read_text()
    monkeypatch.setattr(rt, "run_trade", interrupted)
    ran.clear()
    assert main([*argv, "--overwrite"]) == 130
    assert "which this release does not read (--overwrite): discarded" in (
        capsys.readouterr().err)
    assert journal.read_text() != newer
    # a damaged line in the middle: said, and its setting measured again
    journal.write_text(lines[0] + "{not json\n" + "".join(lines[2:]))
    monkeypatch.setattr(rt, "run_trade", real)
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 0, err
    assert "1 line(s) of" in err and "could not be read (damaged)" in err, err
