"""`plan --trade trade.csv --budget B`: method, tau and iterations come from the trade."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from app.cli import main
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
    assert plan["method"] == "fista-tv" and plan["tau"] == pytest.approx(3e-4)
    assert plan["iterations"] == 200
    assert "from the trade" in plan["reasons"]["method"] and "admm" in plan["reasons"]["method"]
    assert plan["overridden"] == []  # measured, not set by the user: no [user] tag
    assert main([*base, "--budget", "10s"]) == 0
    plan = json.loads(capsys.readouterr().out)
    assert plan["tau"] == pytest.approx(1e-4) and plan["iterations"] == 500
    assert main([*base, "--budget", "0.01s"]) == 2
    assert "no measured setting fits" in capsys.readouterr().err
