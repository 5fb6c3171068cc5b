"""The result checks of the reconstruction commands, and what their messages advise.

Each test is a defect a tester found on the tutorial sample at 1/4 scale (37 x 50,
``lenslesscam simulate --psf sample:tutorial --scene sample:im408 --downsample 4``):

- ``recon auto --budget 0.001s`` ran 1 iteration (residual 0.54 where a flat image gives 0.15)
  without a word, searched tau at 1 iteration per tau, and its plan said both "raised ... so
  the budget allows at least 50 iterations" and "allows only 0 iterations";
- ADMM at a huge tau wrote a non-flat image (objective 2.4e7, a flat image's 6.86) silently,
  and called a run "converged" while its TV splitting was still far from met;
- FISTA's --tol is not reached with the default --prox-iters: runs go to --iters unexplained;
- "(give --tau)" was advised to a command that gave --tau;
- a 1-pixel grid's exact flat fit was reported as beating the result (round-off).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from tests.clirun import run_cli


@pytest.fixture(scope="module")
def tutorial(tmp_path_factory):
    """The tutorial sample simulated at 1/4 scale (37 x 50), as the tester ran it."""
    from app.cli import main

    root = tmp_path_factory.mktemp("tutorial")
    assert main(["simulate", "--psf", "sample:tutorial", "--scene", "sample:im408",
                 "--downsample", "4", "--out", str(root / "sim")]) == 0
    return root / "sim"


def _inputs(sim):
    return ["--psf", sim / "psf.npy", "--meas", sim / "meas.npy"]


def _warnings(err: str) -> list[str]:
    return [ln for ln in err.splitlines() if "warning" in ln]


# ------------------------------------------------------------------------------------------
# 1. recon auto: the same result check as recon fista / admm, and a budget said plainly
# ------------------------------------------------------------------------------------------


def test_recon_auto_on_a_tiny_budget_says_it_is_too_small(tutorial, tmp_path, capsys):
    code, out, err = run_cli(capsys, "recon", "auto", *_inputs(tutorial), "--budget", "0.001s",
                             "--out", tmp_path / "b.tif")
    assert code == 0 and (tmp_path / "b.tif").exists(), err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["iterations"] < 50
    warnings = _warnings(err)
    # the result check every command runs: a flat image explains the measurement better
    flat = [w for w in warnings if "less well than a flat image" in w]
    assert len(flat) == 1 and "recon auto" in flat[0] and "--budget" in flat[0], err
    # the budget, plainly, with the least budget that gives a useful result
    (budget,) = [w for w in warnings if "budget" in w and "flat image" not in w]
    assert "too few to reconstruct anything useful" in budget and "--budget " in budget
    assert "does not even cover the set-up" in budget
    need = float(budget.split("--budget ")[1].split("s ")[0])
    assert need > 0.001
    # the plan does not say the raise reached 50 iterations next to "fewer than 50"
    assert "so the budget allows at least 50 iterations" not in err, err
    assert "still allows fewer than 50 iterations" in err and "1 iterations" not in err, err
    assert f"at least {need:.2g} s affords 50 iterations" in err  # the plan's, the same
    # tau was searched at 50 iterations per tau, not at the budget's 1
    assert "50 iterations per tau, not the budget's" in err, err


def test_recon_auto_without_a_budget_passes_the_check(tutorial, tmp_path, capsys):
    code, _, err = run_cli(capsys, "recon", "auto", *_inputs(tutorial), "--tau", "1e-3",
                           "--quiet", "--out", tmp_path / "ok.tif")
    assert code == 0 and not _warnings(err), err


# ------------------------------------------------------------------------------------------
# 2. ADMM at a huge tau: warned about, and not "converged" while its splitting is off
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("tau", ["10", "1e6"])
def test_admm_at_a_huge_tau_is_warned_about(tutorial, tmp_path, capsys, tau):
    argv = [*_inputs(tutorial), "--tau", tau, "--iters", "300"]
    code, _, err = run_cli(capsys, "recon", "admm", *argv, "--out", tmp_path / "a.tif")
    assert code == 0 and (tmp_path / "a.tif").exists(), err
    (line,) = _warnings(err)
    assert "has not minimised its objective" in line and "flat image" in line, line
    assert "--rho" in line and "recon fista" in line, line
    # FISTA reaches the flat image there: no warning
    code, _, err = run_cli(capsys, "recon", "fista", *argv, "--out", tmp_path / "f.tif")
    assert code == 0 and not _warnings(err), err


def test_admm_converges_only_once_its_splitting_is_met(tutorial):
    """At tau 10 the minimiser is flat. ADMM (rho 1) stopped as "converged" at 386 iterations
    on the change of v alone, its objective 10 % above the flat image's (its TV splitting
    D v = u not met); the primal residuals now have to be below tol too."""
    from recon.admm import Admm
    from recon.problem import ProblemSpec, load_problem
    from recon.tv import TV

    prob = load_problem(ProblemSpec(psf=str(tutorial / "psf.npy"),
                                    meas=str(tutorial / "meas.npy")))
    b = torch.as_tensor(prob.meas, dtype=torch.float32)
    s = Admm(prob.model, b, tau=10.0, max_iter=3000, tol=1e-5, rho=1.0)
    for _ in s.steps():
        pass
    assert s.reason is not None and s.reason.value == "converged"
    a1 = prob.model.op.apply(torch.ones_like(s.x))
    c = max(float((a1 * b).sum() / (a1 * a1).sum()), 0.0)
    flat = 0.5 * float(((c * a1 - b) ** 2).sum())
    obj = 0.5 * float(((prob.model.op.apply(s.x) - b) ** 2).sum()) + 10.0 * TV().value(s.x)
    assert obj <= 1.05 * flat, (s.iteration, obj, flat)


# ------------------------------------------------------------------------------------------
# 3. FISTA's --tol: a run whose change levelled off above it says so
# ------------------------------------------------------------------------------------------


def test_a_run_whose_change_levelled_off_above_tol_says_so(tutorial, tmp_path, capsys):
    argv = [*_inputs(tutorial), "--tau", "1e-4", "--iters", "400"]
    code, out, err = run_cli(capsys, "recon", "fista", *argv, "--out", tmp_path / "a.tif")
    assert code == 0, err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["stop_reason"] == "max_iter"
    detail = summary["stop_detail"]
    assert "levelled off" in detail and "above --tol 1e-05" in detail, detail
    assert "--prox-iters" in detail, detail
    # more inner iterations converge: no detail
    code, out, err = run_cli(capsys, "recon", "fista", *argv, "--prox-iters", "20",
                             "--out", tmp_path / "b.tif")
    summary = json.loads(out.strip().splitlines()[-1])
    assert code == 0 and summary["stop_reason"] == "converged", err
    assert "stop_detail" not in summary


def test_plateau_detail_tells_a_plateau_from_a_slow_decrease():
    from app.commands.recon import plateau_detail

    k = np.arange(1, 1001, dtype=float)
    assert plateau_detail(list(0.05 / k), 1e-5, "fista-tv", 3) is None  # falling as 1/k
    assert plateau_detail(list(0.5 / k**2), 1e-5, "fista-tv", 3) is None
    flat = list(3e-5 * (1 + 0.3 * np.sin(k)))
    text = plateau_detail(flat, 1e-5, "fista-tv", 3)
    assert text is not None and "(3 inner iterations)" in text and "3e-05" in text, text
    assert plateau_detail(flat, 0.0, "fista-tv", 3) is None  # no tolerance to reach
    assert plateau_detail(flat, 1e-4, "fista-tv", 3) is None  # below the tolerance
    assert plateau_detail(flat[:99], 1e-5, "fista-tv", 3) is None  # too short to tell
    assert "--prox-iters" not in (plateau_detail(flat, 1e-5, "admm-tv") or "x")
    # a run at 20 inner iterations was told to try "for example 20"
    assert "for example 40" in (plateau_detail(flat, 1e-5, "fista-tv", 20) or "")


# ------------------------------------------------------------------------------------------
# 4. what to give when there are too few measured pixels
# ------------------------------------------------------------------------------------------


# 37x50 at 18x: the dropped remainder is said (a warning), the refusal is the one error line
@pytest.mark.filterwarnings("ignore:downsampling 18x drops:recon.checks.MeasurementWarning")
@pytest.mark.parametrize(("method", "given", "advice"), [
    ("fista", ["--tau", "1e-4"], "choosing the iteration count from held-out pixels needs at "
     "least 20 (give --iters)"),
    ("fista", ["--iters", "10"], "choosing tau from held-out pixels needs at least 20 "
     "(give --tau)"),
    ("fista", [], "(give --tau and --iters)"),
    ("admm", [], "(give --tau)"),  # ADMM's iteration count is its limit, never searched
])
def test_too_few_pixels_asks_for_what_was_not_given(tutorial, tmp_path, capsys, method, given,
                                                     advice):
    code, _, err = run_cli(capsys, "recon", method, *_inputs(tutorial), "--downsample", "18",
                           *given, "--out", tmp_path / "x.tif")
    assert code == 2 and "only 4 measured pixels" in err and advice in err, err
    assert len(err.strip().splitlines()) == 1


# ------------------------------------------------------------------------------------------
# 5. round-off is not "less well than a flat image"
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("method", ["fista", "admm"])
@pytest.mark.parametrize("precision", [[], ["--float64"]])
# 37x50 at 37x keeps 37x37: that is said (the one warning expected), nothing of round-off
@pytest.mark.filterwarnings("default:downsampling 37x drops:recon.checks.MeasurementWarning")
def test_a_one_pixel_grid_is_not_warned_about(tutorial, tmp_path, capsys, method, precision):
    code, _, err = run_cli(capsys, "recon", method, *_inputs(tutorial), "--downsample", "37",
                           "--tau", "1e-4", "--iters", "100", *precision,
                           "--out", tmp_path / "one.tif")
    assert code == 0, err
    assert [w for w in _warnings(err) if "downsampling 37x drops" not in w] == [], err


def test_the_check_still_warns_beyond_round_off(capsys):
    """check_explains directly: 1e-3 of the measurement's norm above an exact flat fit is a
    real shortfall (float32's round-off is about 1e-4 at most), 1e-6 is not."""
    from app.commands.recon import check_explains
    from recon.models import build_model
    from recon.tv import TV

    psf = np.zeros((5, 5), np.float32)
    psf[2, 2] = 1.0  # an identity: a flat measurement is fitted exactly by a flat image
    model = build_model("2d", psf)
    b = torch.ones(model.meas_shape, dtype=torch.float32)
    kw = dict(method="fista-tv", iterations=10, reason="max_iter", tau=1e-3, tv=TV(),
              refuse_hint="r", flat_hint="more --iters", objective_hint="o")
    for off, warned in ((1e-6, False), (1e-3, True)):
        x = torch.ones(model.scene_shape, dtype=torch.float32)
        x.view(-1)[0] += off * 5.0  # ||A x - b|| / ||b|| = off
        check_explains(x, model, b, **kw)
        err = capsys.readouterr().err
        assert ("less well than a flat image" in err) is warned, (off, err)


def test_the_warning_and_the_plan_agree_on_a_budget_at_the_set_up_edge(capsys):
    """The warning took 25.5 iterations' time as "not even the set-up" while the plan's
    reason said "too few to converge" (and the other way round): one rule now."""
    import types

    from app.commands.plan import warn_small_budget
    from recon.plan.cost import SETUP_ITERS
    from recon.plan.planner import budget_room

    spi = 0.01
    for k in (SETUP_ITERS - 0.5, SETUP_ITERS + 0.5, SETUP_ITERS + 1.5):
        plan = types.SimpleNamespace(method="fista-tv", budget_s=k * spi, iterations=1,
                                     seconds_per_iter=spi, downsample=1)
        warn_small_budget(plan)
        err = capsys.readouterr().err
        setup = budget_room(k * spi, spi) <= 0
        assert ("does not even cover the set-up" in err) == setup, (k, err)


def test_no_budget_warning_when_the_budget_is_not_what_limits_the_count(capsys):
    """A trade's best setting of 30 iterations under a 1 s budget was warned about as "too few
    to converge; give --budget 0.27s or more": a budget below the one given. The warning is
    for counts the budget limits."""
    import types

    from app.commands.plan import warn_small_budget
    from recon.plan.planner import min_useful_budget_s

    spi = 0.004
    need = min_useful_budget_s(spi)
    for budget, warned in ((need * 0.5, True), (need * 2, False)):
        plan = types.SimpleNamespace(method="fista-tv", budget_s=budget, iterations=30,
                                     seconds_per_iter=spi, downsample=1)
        warn_small_budget(plan)
        assert ("too few" in capsys.readouterr().err) is warned, budget
