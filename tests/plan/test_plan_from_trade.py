"""`plan --trade trade.csv --budget B`: method, tau and iterations come from the trade."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from app.cli import main
from recon.formats import FORMAT_VERSION
from recon.simulate import synthetic_psf
from recon.trade import TradeRow


def _write_trade(path):
    def row(setting, method, tau, its, wall, q):
        return TradeRow("c", setting, method, tau, "float32", 1, 0, its, wall, 4.0, q, 0.01)

    rows = [row("fista tau=1e-05", "fista", 1e-5, 50, 0.1, 30.0),
            row("admm tau=0.0003", "admm", 3e-4, 200, 0.8, 34.0),
            row("fista tau=0.0001", "fista", 1e-4, 500, 3.0, 36.0)]
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0].as_dict()))
        w.writeheader()
        for r in rows:
            w.writerow(r.as_dict())


def test_plan_takes_the_best_setting_within_the_budget(tmp_path, capsys):
    psf = synthetic_psf((48, 64), seed=1)
    meas = np.random.default_rng(0).random((48, 64)).astype(np.float32)
    np.save(tmp_path / "psf.npy", psf)
    np.save(tmp_path / "meas.npy", meas)
    _write_trade(tmp_path / "trade.csv")
    base = ["plan", "--psf", str(tmp_path / "psf.npy"), "--meas", str(tmp_path / "meas.npy"),
            "--trade", str(tmp_path / "trade.csv"), "--json", "--no-probe"]
    assert main([*base, "--budget", "1s"]) == 0
    plan = json.loads(capsys.readouterr().out)
    # the ADMM row (34 dB) is better within 1 s, but a plan runs FISTA-TV, which at 200
    # iterations is another image: it took that row's tau and count (and reason) before
    assert plan["method"] == "fista-tv" and plan["tau"] == pytest.approx(1e-5)
    assert plan["iterations"] == 50
    why = plan["reasons"]["method"]
    assert "from the trade" in why and "admm tau=0.0003 (34.00 dB) was better but" in why
    assert "recon admm --tau 0.0003 --iters 200 runs it" in why
    assert plan["overridden"] == []  # measured, not set by the user: no [user] tag
    assert main([*base, "--budget", "10s"]) == 0
    plan = json.loads(capsys.readouterr().out)
    assert plan["tau"] == pytest.approx(1e-4) and plan["iterations"] == 500
    assert main([*base, "--budget", "0.01s"]) == 2
    assert "no measured setting fits" in capsys.readouterr().err
    # only the ADMM row fits: refused, and the row named with why
    assert main([*base, "--budget", "0.9s", "--trade", str(_only_admm(tmp_path))]) == 2
    err = capsys.readouterr().err
    assert "no measured setting fits the budget of 0.9 s" in err
    assert "admm tau=0.0003 fits but is ADMM-TV, which a plan does not run" in err


def _only_admm(tmp_path):
    """A trade.csv whose one row within 0.9 s is ADMM-TV (the others take longer)."""
    path = tmp_path / "admm.csv"
    _write_trade(tmp_path / "all.csv")
    with open(tmp_path / "all.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(r for r in rows if r["method"] == "admm" or float(r["wall_s"]) > 1)
    return path


def _save_pair(folder, shape, seed):
    folder.mkdir(parents=True, exist_ok=True)
    np.save(folder / "psf.npy", synthetic_psf(shape, seed=seed))
    np.save(folder / "meas.npy", np.random.default_rng(seed).random(shape).astype(np.float32))
    return folder / "psf.npy", folder / "meas.npy"


def _plan_stderr(capsys, psf, meas, trade):
    assert main(["plan", "--psf", str(psf), "--meas", str(meas), "--trade", str(trade),
                 "--budget", "10s", "--json", "--no-probe"]) == 0
    cap = capsys.readouterr()
    assert json.loads(cap.out)["reasons"]["method"].startswith("from the trade")
    return [ln for ln in cap.err.splitlines() if "warning" in ln]


def test_plan_warns_when_the_trade_was_measured_on_other_data(tmp_path, capsys):
    """The trade's header records its case; plan compares shape, field and PSF with its own
    data and warns in one line (the plan is still made), and is silent when they match."""
    psf, meas = _save_pair(tmp_path / "a", (32, 40), 1)
    assert main(["trade", "--meas", str(meas), "--psf", str(psf), "--quick", "--no-udn",
                 "--budgets", "10", "--out", str(tmp_path / "t")]) == 0
    capsys.readouterr()
    trade = tmp_path / "t" / "trade.csv"
    # the data it was measured on (another scene of the same size and PSF matches too)
    assert _plan_stderr(capsys, psf, meas, trade) == []
    np.save(tmp_path / "a" / "scene2.npy",
            np.random.default_rng(9).random((32, 40)).astype(np.float32))
    assert _plan_stderr(capsys, psf, tmp_path / "a" / "scene2.npy", trade) == []
    # another PSF of the same size
    other_psf, _ = _save_pair(tmp_path / "b", (32, 40), 2)
    warn = _plan_stderr(capsys, other_psf, meas, trade)
    assert warn == [f"lenslesscam plan: warning: {trade} was measured on other data than this "
                    "plan's (case 'meas': another PSF); its timings and tau may not hold here"]
    # other data: another size (and so another PSF)
    psf_c, meas_c = _save_pair(tmp_path / "c", (48, 64), 3)
    warn = _plan_stderr(capsys, psf_c, meas_c, trade)
    assert len(warn) == 1
    assert "measurement 1x32x40 (here 1x48x64), scene field 32x40 (here 48x64), another PSF" \
        in warn[0]


def test_plan_on_an_old_or_newer_trade_csv(tmp_path, capsys):
    """A trade.csv from before the header is used, with a note that it cannot be checked; a
    newer format version is refused with a one-line error naming the file."""
    psf, meas = _save_pair(tmp_path, (48, 64), 1)
    _write_trade(tmp_path / "trade.csv")
    warn = _plan_stderr(capsys, psf, meas, tmp_path / "trade.csv")
    assert len(warn) == 1 and "records no data it was measured on" in warn[0]
    text = (tmp_path / "trade.csv").read_text()
    (tmp_path / "new.csv").write_text(f"# format: lenslesscam.trade\n# format_version: "
                                      f"{FORMAT_VERSION + 1}\n" + text)
    assert main(["plan", "--psf", str(psf), "--meas", str(meas), "--trade",
                 str(tmp_path / "new.csv"), "--budget", "10s", "--json", "--no-probe"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"lenslesscam plan: error: {tmp_path / 'new.csv'}: trade.csv format version "
                   f"{FORMAT_VERSION + 1} is newer than this lenslesscam reads "
                   f"({FORMAT_VERSION}); update lenslesscam to read it")


def _udn_trade(folder, settings_of=None):
    """psf.npy, meas.npy and a trade.csv of one small UDN setting measured on them."""
    from recon.trade import Case, Config, run_trade, write_trade_csv

    psf_file, meas_file = _save_pair(folder, (24, 32), 1)
    case = Case("meas", np.load(psf_file)[None], np.load(meas_file)[None])
    rows = list(run_trade(case, [Config("udn", checkpoints=(3,), channels=4, scales=2)],
                          seed=2))
    if settings_of is not None:
        for r in rows:
            r.udn_settings = settings_of(r.udn_settings)
    trade = write_trade_csv(folder / "trade.csv", rows, [case])
    return ["--psf", str(psf_file), "--meas", str(meas_file), "--trade", str(trade)]


def test_a_udn_setting_of_the_trade_runs_the_network_it_measured(tmp_path, capsys,
                                                                  monkeypatch):
    """`plan --trade` chose 'udn ch4' and the plan ran the planner's default network (32
    channels, 5 scales, a 5 % held-out early stop): not what the trade measured."""
    import recon.udn
    from recon.io import read_reconstruction
    from recon.udn import UDNConfig

    args = _udn_trade(tmp_path)
    assert main(["plan", *args, "--budget", "100s", "--no-probe", "--out",
                 str(tmp_path / "p.json")]) == 0
    text = capsys.readouterr().out
    assert "udn, 3 iterations; network variant 2d, scales 2, channels 4" in text
    saved = json.loads((tmp_path / "p.json").read_text())
    assert saved["method"] == "udn" and saved["iterations"] == 3
    net, run = saved["udn"]["network"], saved["udn"]["config"]
    assert (net["scales"], net["channels"]) == (2, 4)
    assert run["precision"] == "float32" and "holdout" not in run and "seed" not in run
    # a release that reads only version 1 refuses the plan instead of running its default
    assert saved["format_version"] == 2
    assert "the plan runs the network it measured" in saved["reasons"]["method"]

    built = []
    real = recon.udn.UDNRunner

    class Spy(real):
        def __init__(self, *a, **kw):
            super().__init__(*a, **kw)
            built.append((self.network_config, self.config))

    monkeypatch.setattr(recon.udn, "UDNRunner", Spy)
    assert main(["recon", "auto", *args[:4], "--plan", str(tmp_path / "p.json"), "--quiet",
                 "--out", str(tmp_path / "r.tif")]) == 0
    capsys.readouterr()
    [(network, config)] = built
    assert (network.scales, network.channels) == (2, 4)
    # the trade ran without an early stop (it hides its own pixels); the plan's run keeps its
    # held-out stop (it turned it off when the trade's holdout 0 was carried)
    assert (config.holdout, config.max_iter) == (UDNConfig().holdout, 3) and config.holdout > 0
    _, meta = read_reconstruction(tmp_path / "r.tif")
    assert meta["parameters"]["network"]["channels"] == 4
    assert meta["parameters"]["holdout"] > 0 and meta["plan"]["udn"] == saved["udn"]


def test_a_udn_setting_the_plan_cannot_run_is_named_not_replaced(tmp_path, capsys):
    """A trade row with a setting this release does not know (or none recorded) is no
    candidate: the plan says so rather than run a network with a default in its place."""
    from recon.plan import Plan

    def unknown(s):
        return {**s, "network": {**s["network"], "attention": True}}

    args = _udn_trade(tmp_path, unknown)
    assert main(["plan", *args, "--budget", "100s", "--no-probe"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert ("no measured setting fits the budget of 100 s in float32; udn ch4 fits but its "
            "UDN network setting attention is not one this lenslesscam can run") in err
    args = _udn_trade(tmp_path / "old", lambda s: None)  # a trade.csv of an older release
    assert main(["plan", *args, "--budget", "100s", "--no-probe"]) == 2
    assert "does not record the network settings it ran" in capsys.readouterr().err
    # a plan edited by hand: one line at run time, naming the field
    plan = Plan(model="2d", k=1, sensor=(24, 32), field=(24, 32), region=(0, 0, 24, 32),
                downsample=1, method="udn", iterations=3,
                udn={"network": {"channels": 4, "attention": True}, "config": {}})
    (tmp_path / "p.json").write_text(json.dumps(plan.to_json()))
    assert main(["recon", "auto", *args[:4], "--plan", str(tmp_path / "p.json"), "--quiet",
                 "--out", str(tmp_path / "r.tif")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("lenslesscam recon: error: plan field 'udn': UDN network setting "
                          "attention is not one this lenslesscam can run"), err
    assert len(err.splitlines()) == 1 and not (tmp_path / "r.tif").exists()
