"""``lenslesscam bench admm-penalty``: one case's runs, scored against FISTA-TV's minimum."""

from __future__ import annotations

from benchmarks.admm_penalty import MARKS, run_case, table
from tests.scenes import disc_case


def test_run_case_scores_both_penalties_against_the_minimum() -> None:
    model, meas, truth = disc_case(0.9)
    row = run_case(model, meas, truth)
    assert 0 < row["penalty"] < 1  # 90 % erased: below the former fixed scale
    for key in ("fista", "admm_auto", "admm_fixed"):
        assert len(row[key]["gap"]) == len(row[key]["psnr"]) == len(MARKS)
        assert min(row[key]["gap"]) >= 0  # the reference is the lowest objective seen
        assert 5.0 < row[key]["psnr"][-1] < 60.0
    # the automatic penalty ends nearer the minimum than the fixed one on an erased sensor
    assert row["admm_auto"]["gap"][1] < 0.05 < row["admm_fixed"]["gap"][1]  # at 200
    text = table([{"case": "sim a 90% noise 0.01", "erasure": 0.9, **row},
                  {"case": "real b 90%", "erasure": 0.9, **row}])
    assert text.count("| sim a 90% noise 0.01 |") == 1
    assert "| sim 90% | 1 |" in text and "| real 90% | 1 |" in text
