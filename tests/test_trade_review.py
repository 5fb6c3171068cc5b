"""``trade`` and ``trade.csv``: findings of a hostile review of the app's trade panel (the old
behaviour in each test's docstring)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from recon.trade import Case, TradeRow, read_trade, write_trade_csv
from tests.clirun import run_cli


def _rows() -> list[TradeRow]:
    return [TradeRow("c", "fista tau=1e-05", "fista", 1e-5, "float32", 1, 0, 50, 0.1, 4.0,
                     30.0, 0.01),
            TradeRow("c", "admm tau=0.001", "admm", 1e-3, "float32", 1, 0, 50, 0.2, 4.0,
                     31.0, 0.01)]


def _case() -> Case:
    z = np.full((1, 8, 8), 1 / 64, np.float32)
    return Case("c", z, z)


@pytest.mark.parametrize("tau", [-5.0, 1e300, 2.0])
def test_a_trade_csv_row_with_tau_out_of_range_is_named(tmp_path, tau):
    """A row with tau -5 or 1e300 was read, suggested and applied to the preview silently."""
    rows = _rows()
    path = write_trade_csv(tmp_path / "trade.csv", [rows[0], dataclasses.replace(rows[1],
                                                                               tau=tau)],
                           [_case()])
    with pytest.raises(ValueError, match=r"trade\.csv line \d+: column tau is .* not in 0\.\.1") \
            as info:
        read_trade(path)
    assert "\n" not in str(info.value)


def test_a_trade_csv_row_with_a_nan_tau_is_named(tmp_path):
    rows = _rows()
    path = write_trade_csv(tmp_path / "trade.csv",
                           [dataclasses.replace(rows[0], tau=float("nan"))], [_case()])
    with pytest.raises(ValueError, match=r"line \d+: column tau is 'nan'"):
        read_trade(path)


def test_tau_zero_and_one_are_read(tmp_path):
    rows = [dataclasses.replace(_rows()[0], tau=0.0), dataclasses.replace(_rows()[1], tau=1.0)]
    path = write_trade_csv(tmp_path / "trade.csv", rows, [_case()])
    assert [r.tau for r in read_trade(path).rows] == [0.0, 1.0]


def test_trade_takes_psf_dark(tmp_path, capsys, monkeypatch):
    """The loader tells a trade user to pass --psf-dark ('... unless a PSF dark is given
    (--psf-dark, psf_dark; 0: none)'), but trade said 'unrecognized arguments: --psf-dark'."""
    import recon.trade as rt

    monkeypatch.setattr(rt, "default_grid",
                        lambda quick=False, with_udn=True: [rt.Config("fista", 1e-4, (3,))])
    rng = np.random.default_rng(0)
    np.save(tmp_path / "psf.npy", (rng.random((16, 20)) ** 4).astype(np.float32))  # max < 1
    np.save(tmp_path / "meas.npy", (200 + 100 * rng.random((16, 20))).astype(np.float32))
    argv = ["trade", "--meas", tmp_path / "meas.npy", "--psf", tmp_path / "psf.npy",
            "--dark", "100", "--budgets", "1"]
    code, _, err = run_cli(capsys, *argv, "--out", tmp_path / "a")
    assert code != 0 and "--psf-dark" in err  # what the message asks the user to give
    code, _, err = run_cli(capsys, *argv, "--psf-dark", "0", "--out", tmp_path / "b")
    assert code == 0, err
    trade = read_trade(tmp_path / "b" / "trade.csv")
    assert trade.cases[0]["source"]["psf_dark"] == 0.0
    assert trade.cases[0]["source"]["dark"] == 100.0
