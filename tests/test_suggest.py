"""recon.suggest: plans and trades are offered only for the measurement they were made on."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from recon.plan import Plan
from recon.suggest import (
    find_suggestions,
    input_hashes,
    inputs_match,
    write_plan_suggestion,
    write_trade_inputs,
)
from recon.trade import TradeRow


def _plan(method: str = "udn", downsample: int = 3, iterations: int = 700) -> Plan:
    return Plan(model="2d", k=1, sensor=(32, 32), field=(32, 32), region=(0, 0, 32, 32),
                downsample=downsample, method=method, iterations=iterations, budget_s=900.0)


def _inputs(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return (rng.integers(0, 4000, (32, 32)).astype(np.uint16),
            rng.random((32, 32)).astype(np.float32))


def _row(channels: int, its: int, heldout: float, precision: str = "float32",
         method: str = "udn") -> TradeRow:
    return TradeRow(case="current frame", setting=f"{method} ch{channels}", method=method,
                    tau=0.0, precision=precision, downsample=2, channels=channels,
                    iterations=its, wall_s=1.0, peak_mem_mb=None, heldout_psnr=heldout,
                    residual=0.1)


def _write_trade(folder: Path, rows: list[TradeRow]) -> Path:
    """A trade.csv as ``lenslesscam trade`` writes it (DictWriter over TradeRow.as_dict)."""
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "trade.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0].as_dict()))
        w.writeheader()
        for r in rows:
            w.writerow(r.as_dict())
    return folder / "trade.csv"


def test_hashes_follow_the_values_not_the_dtype() -> None:
    meas, psf = _inputs(0)
    h = input_hashes(meas, psf)
    assert h == input_hashes(meas.astype(np.float32), psf)
    other = meas.copy()
    other[0, 0] += 1
    assert input_hashes(other, psf)["measurement"] != h["measurement"]
    assert input_hashes(meas, psf * 2)["psf"] != h["psf"]
    assert inputs_match(h, h)
    assert not inputs_match({"measurement": h["measurement"]}, h)  # the PSF must match too
    assert not inputs_match(None, h)


def test_a_plan_is_offered_for_its_measurement_only(tmp_path: Path) -> None:
    mine, other = input_hashes(*_inputs(0)), input_hashes(*_inputs(1))
    p = write_plan_suggestion(tmp_path, _plan(), mine)
    write_plan_suggestion(tmp_path, _plan(downsample=5), other)
    # a plan written by `lenslesscam plan --out` records no inputs: never offered
    (tmp_path / "bare.json").write_text(json.dumps(_plan(downsample=7).to_json()))
    (tmp_path / "junk.json").write_text("{not json")
    found = find_suggestions([tmp_path, tmp_path / "missing"], mine)
    assert [s.path for s in found] == [p]
    s = found[0]
    assert s.source == "plan"
    assert s.settings == {"downsample": 3, "max_iter": 700, "time_limit_s": 900.0}
    assert s.origin.startswith(f"from plan {p.name}, ")
    assert find_suggestions([tmp_path], other)[0].settings["downsample"] == 5


def test_a_fista_plan_suggests_only_its_downsampling(tmp_path: Path) -> None:
    h = input_hashes(*_inputs(0))
    write_plan_suggestion(tmp_path, _plan(method="fista-tv", downsample=4, iterations=300), h)
    (s,) = find_suggestions([tmp_path], h)
    assert s.settings == {"downsample": 4}


def test_a_trade_offers_its_best_udn_setting(tmp_path: Path) -> None:
    mine, other = input_hashes(*_inputs(0)), input_hashes(*_inputs(1))
    rows = [_row(16, 100, 30.0), _row(32, 250, 33.5, "bf16"), _row(32, 500, 33.0),
            _row(0, 500, 40.0, method="fista")]  # a better FISTA row is not a UDN setting
    csv_path = _write_trade(tmp_path / "trade-a", rows)
    write_trade_inputs(tmp_path / "trade-a", mine)
    _write_trade(tmp_path / "trade-b", rows)
    write_trade_inputs(tmp_path / "trade-b", other)
    _write_trade(tmp_path / "trade-c", rows)  # no inputs.json: not offered
    (s,) = find_suggestions([tmp_path], mine)
    assert s.source == "trade" and s.path == csv_path
    assert s.settings == {"channels": 32, "precision": "bf16", "downsample": 2, "max_iter": 250}
    assert s.origin.startswith("from trade trade-a, ")
    # inputs.json has a format and version: a newer one is not read, an old one (none) is
    rec = json.loads((tmp_path / "trade-a" / "inputs.json").read_text())
    assert rec["format"] == "lenslesscam.trade_inputs"
    (tmp_path / "trade-a" / "inputs.json").write_text(json.dumps({**rec, "format_version": 99}))
    assert find_suggestions([tmp_path], mine) == []
    old = {k: v for k, v in rec.items() if k not in ("format", "format_version")}
    (tmp_path / "trade-a" / "inputs.json").write_text(json.dumps(old))
    assert len(find_suggestions([tmp_path], mine)) == 1


def test_a_trade_without_udn_rows_is_not_offered(tmp_path: Path) -> None:
    h = input_hashes(*_inputs(0))
    _write_trade(tmp_path / "t", [_row(0, 100, 30.0, method="fista")])
    write_trade_inputs(tmp_path / "t", h)
    assert find_suggestions([tmp_path], h) == []


def test_newest_first(tmp_path: Path) -> None:
    h = input_hashes(*_inputs(0))
    for d in (2, 3, 4):
        p = write_plan_suggestion(tmp_path, _plan(downsample=d), h)
        d_json = json.loads(p.read_text())
        d_json["created_utc"] = f"2026-01-0{d}T00:00:00+00:00"
        p.write_text(json.dumps(d_json))
    assert [s.settings["downsample"] for s in find_suggestions([tmp_path], h)] == [4, 3, 2]


def test_plan_file_is_still_a_plan(tmp_path: Path) -> None:
    """The saved suggestion is read back by the planner's own reader (recon auto --plan)."""
    p = write_plan_suggestion(tmp_path, _plan(), input_hashes(*_inputs(0)))
    assert Plan.from_json(json.loads(p.read_text())) == _plan()


@pytest.mark.parametrize("bad", [{"measurement": "x", "psf": ""}, {}, []])
def test_inputs_match_rejects_incomplete_records(bad: object) -> None:
    assert not inputs_match(bad, {"measurement": "x", "psf": ""})


def test_plan_out_with_a_dark_level_does_not_warn_of_none(tmp_path: Path, capsys) -> None:
    """plan --out hashes its inputs for the app's job dialog by reading them again; that read
    warned "raw uint16 data read with no dark level" although --dark was given (pytest turns
    the warning into an error)."""
    from app.cli import main
    from recon.simulate import synthetic_psf

    rng = np.random.default_rng(0)
    frame = (100 + rng.integers(0, 400, (32, 32))).astype(np.uint16)  # black level 100
    np.save(tmp_path / "frame.npy", frame)
    np.save(tmp_path / "psf.npy", synthetic_psf((32, 32), seed=1))
    argv = ["plan", "--psf", str(tmp_path / "psf.npy"), "--meas", str(tmp_path / "frame.npy"),
            "--dark", "100", "--psf-dark", "0", "--no-probe", "--out", str(tmp_path / "p.json")]
    assert main(argv) == 0
    assert "no dark level" not in capsys.readouterr().err
    assert json.loads((tmp_path / "p.json").read_text())["inputs"]["measurement"]


def _recorded(**config: object) -> dict:
    """A UDN row's recorded settings (recon.trade.udn_settings), some changed."""
    from recon.trade import UDN_NOT_RECORDED
    from recon.udn import NetworkConfig, UDNConfig

    run = {k: v for k, v in UDNConfig(precision="bf16").to_dict().items()
           if k not in UDN_NOT_RECORDED}
    run.update(config)
    return {"network": NetworkConfig(scales=4, channels=32, skip_channels=0).to_dict(),
            "config": run}


def test_a_trade_row_s_recorded_udn_settings_are_carried(tmp_path: Path) -> None:
    """The suggestion offered channels and precision only, though the row records every UDN
    setting it ran: now all of them, as job-spec sections; one no spec key takes is named."""
    import dataclasses

    from recon.trade import write_trade_csv

    h = input_hashes(*_inputs(0))
    row = dataclasses.replace(_row(32, 250, 33.5, "bf16"), udn_settings=_recorded(future_knob=1))
    write_trade_csv(tmp_path / "t" / "trade.csv", [row], [])
    write_trade_inputs(tmp_path / "t", h)
    (s,) = find_suggestions([tmp_path], h)
    assert s.settings == {"channels": 32, "precision": "bf16", "downsample": 2, "max_iter": 250}
    assert s.spec["network"]["skip_channels"] == 0 and s.spec["network"]["scales"] == 4
    # the trade's own stop and seed are not the row's settings: the job keeps its own
    assert "holdout" not in s.spec.get("stopping", {}) and "seed" not in s.spec["optimizer"]
    assert s.spec["optimizer"]["gain"] == "auto" and s.spec["device"]["precision"] == "bf16"
    assert "max_iter" not in s.spec.get("stopping", {})  # the row's iterations are max_iter
    assert s.not_carried == ("config.future_knob",)
    assert "not carried" in s.detail and "config.future_knob" in s.detail
    assert "recorded UDN settings" in s.label


def test_a_trade_row_without_recorded_settings_says_what_it_suggests(tmp_path: Path) -> None:
    h = input_hashes(*_inputs(0))
    _write_trade(tmp_path / "t", [_row(32, 250, 33.5, "bf16")])
    write_trade_inputs(tmp_path / "t", h)
    (s,) = find_suggestions([tmp_path], h)
    assert s.spec == {} and s.not_carried == ()
    assert "records no UDN settings" in s.detail and "job's defaults" in s.detail


def test_a_udn_plan_carries_the_settings_it_runs(tmp_path: Path) -> None:
    """A plan from `plan --trade` runs the trade's network (Plan.udn): so does its job."""
    import dataclasses

    h = input_hashes(*_inputs(0))
    plan = dataclasses.replace(_plan(), udn=_recorded())
    write_plan_suggestion(tmp_path, plan, h)
    (s,) = find_suggestions([tmp_path], h)
    assert s.settings == {"downsample": 3, "max_iter": 700, "time_limit_s": 900.0}
    assert s.spec["network"]["channels"] == 32 and "holdout" not in s.spec.get("stopping", {})
