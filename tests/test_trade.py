"""The speed/accuracy trade: rows, held-out proxy honesty, summaries and the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.stats import spearmanr

from app.cli import main
from recon.models import build_model
from recon.simulate import simulate, synthetic_psf
from recon.trade import (
    Case,
    Config,
    TradeRow,
    best_for_budgets,
    pareto_front,
    rank_correlation,
    run_trade,
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
    header = (tmp_path / "out" / "trade.csv").read_text().splitlines()[0].split(",")
    assert {"wall_s", "peak_mem_mb", "heldout_psnr", "psnr"} <= set(header)
    png = (tmp_path / "out" / "trade_pareto.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000
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
