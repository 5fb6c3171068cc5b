"""``lenslesscam bench tau-rules``: both automatic-tau rules on one case, and its table."""

from __future__ import annotations

import numpy as np
import torch

from benchmarks.tau_rules import GRID, run_case, table
from recon.models import build_model
from recon.simulate import simulate, synthetic_psf


def test_run_case_scores_both_rules_and_the_oracle_grid() -> None:
    h, w = 40, 48
    y, x = np.mgrid[0:h, 0:w] / w
    scene = (0.2 + 0.6 * ((x - 0.4) ** 2 + (y - 0.4) ** 2 < 0.05))[None, None]
    psf = synthetic_psf((h, w), seed=3)
    sim = simulate(build_model("2d", psf), scene.astype(np.float32), erasure=0.5, noise=0.01,
                   seed=0)
    model = build_model("2d", psf, mask=sim.mask)
    row = run_case(model, torch.as_tensor(sim.meas), sim.truth, iters=40)
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
