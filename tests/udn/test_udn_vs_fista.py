"""The UDN vs FISTA-TV comparison (benchmarks/udn_vs_fista.py) end to end on a tiny budget."""

from __future__ import annotations

import argparse

import numpy as np

from benchmarks import udn_vs_fista as bench


def parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    return parser.parse_args(list(argv))


def test_ensemble_curve_choice_and_markdown(tmp_path, capsys):
    """Two seeds on one scene: checkpoints, the held-out choice and the written table agree."""
    args = parse("--scenes", "im65", "--iters", "200", "--seeds", "2", "--channels", "8",
                 "--scales", "3", "--eval-every", "100", "--jobs", "1", "--fista-iters", "50",
                 "--out", str(tmp_path / "cmp.md"))
    psf, sims = bench.make_data(16, ["im65"], 0.99, 0.01)
    assert psf.shape == (75, 100)
    sim = sims["im65"]
    n_measured = int(sim.mask.sum())
    assert abs(n_measured - 0.01 * psf.size) <= 1

    udn = bench.run_udn(sims, args)["im65"]
    assert sorted(udn["curve"]) == [100, 200]
    assert len(udn["members"]) == 2 and len(udn["selected_iterations"]) == 2
    assert all(1 <= t <= 200 for t in udn["selected_iterations"])
    assert udn["fitted_pixels"] + udn["heldout_pixels"] == n_measured
    assert udn["cv_iteration"] in (100, 200) and udn["cv"] == udn["curve"][udn["cv_iteration"]]
    # the ensemble is the mean of the members: rebuild it from two single runs
    members = [bench.udn_member(dict(vars(args), scene="im65", seed=s)) for s in (0, 1)]
    assert not np.array_equal(members[0]["checkpoints"][200], members[1]["checkpoints"][200])
    ens = np.mean([m["checkpoints"][200] for m in members], axis=0)
    pooled = {t: np.mean([m["heldout"][t] for m in members]) for t in (100, 200)}
    assert udn["cv_iteration"] == min(pooled, key=pooled.get)
    assert udn["curve"][200] == bench.score(sim.truth, ens)
    floor = bench.score(sim.truth, np.full_like(sim.truth, sim.truth.mean()) + 1e-3 * ens)
    # better than (almost) a constant image (by 0.5 dB at 200 iterations, 1.0 dB at 300)
    assert udn["curve"][200] > floor

    assert bench.run(args) == 0
    text = (tmp_path / "cmp.md").read_text()
    assert "| im65 |" in text and "held-out choice" in text and "Produced by" in text
    assert text.count("beats best-tau") + text.count("does not beat best-tau") == 3
    out = capsys.readouterr().out
    assert "same rule as FISTA" in out


def test_pick_iteration_maximises_the_mean_over_scenes():
    udn = {"a": {"curve": {100: 10.0, 200: 12.0, 300: 11.0}},
           "b": {"curve": {100: 14.0, 200: 11.0, 300: 13.5}}}
    assert bench.pick_iteration(udn) == 300  # means 12.0, 11.5, 12.25


def test_fista_side_chooses_tau_and_iterations_on_the_mean():
    psf, sims = bench.make_data(16, ["im65", "im740"], 0.99, 0.01)
    best = bench.run_fista(psf, sims, 100, taus=(1e-5, 3e-3))
    assert best["tau"] in (1e-5, 3e-3) and best["iterations"] in (50, 100)
    assert best["mean"] == sum(best["psnr"].values()) / 2
    other = bench.run_fista(psf, sims, 100, taus=(3e-3,) if best["tau"] == 1e-5 else (1e-5,))
    assert best["mean"] >= other["mean"]
