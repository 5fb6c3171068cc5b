"""``lenslesscam bench tau-rules``: both automatic-tau rules on one case, and its table."""

from __future__ import annotations

from benchmarks.tau_rules import GRID, run_case, table
from tests.scenes import disc_case


def test_run_case_scores_both_rules_and_the_oracle_grid() -> None:
    model, meas, truth = disc_case(0.5)
    row = run_case(model, meas, truth, iters=40)
    assert row["1se"]["tau"] >= row["min"]["tau"]
    assert row["oracle"]["tau"] in GRID
    for k in ("min", "1se", "oracle"):
        assert 5.0 < row[k]["psnr"] < 60.0  # a reconstruction, scored against its truth
    text = table([{"case": "sim a 50% noise 0.01", **row},
                  {"case": "real b 0%", **row}])
    assert text.count("| sim a 50% noise 0.01 |") == 1
    d = row["1se"]["psnr"] - row["min"]["psnr"]
    assert "sim (1 cases)" in text and "real (1 cases)" in text
    assert text.count(f"1se - min: mean {d:+.3f} dB") == 2
