"""ADMM-TV: the same correctness checks as FISTA, and agreement with FISTA's minimum."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from recon.admm import Admm
from recon.fista import Fista
from recon.models import build_model
from recon.simulate import simulate, synthetic_psf
from recon.stepwise import NumericalError, StopReason
from recon.tv import TV


def _problem(erasure=0.0, field=None, seed=0):
    psf = synthetic_psf((20, 24), seed=seed)
    rng = np.random.default_rng(seed)
    scene = np.zeros((1, 1, *(field or (20, 24))))
    scene[..., 4:12, 5:15] = 1.0
    scene[..., 10:16, 8:20] += 0.5
    sim = simulate(build_model("2d", psf, field=field), scene, erasure=erasure, noise=0.01,
                   seed=int(rng.integers(100)))
    model = build_model("2d", psf, mask=sim.mask, field=field, dtype=torch.float64)
    return model, torch.as_tensor(sim.meas, dtype=torch.float64)


def test_least_squares_limit_matches_dense_solve():
    """tau = 0 and no constraint: ADMM converges to the least-squares solution."""
    rng = np.random.default_rng(0)
    psf = rng.random((6, 5)) + 0.1
    model = build_model("2d", psf, dtype=torch.float64)
    n = int(np.prod(model.scene_shape))
    eye = torch.eye(n, dtype=torch.float64).reshape(n, *model.scene_shape)
    mat = torch.stack([model.apply(e).reshape(-1) for e in eye], dim=1)
    b = torch.as_tensor(rng.random(model.meas_shape))
    x_ls = torch.linalg.lstsq(mat, b.reshape(-1, 1)).solution.reshape(model.scene_shape)
    # with tau = 0 the TV split carries no penalty: a small rho lets v move freely
    a = Admm(model, b, tau=0.0, nonneg=False, max_iter=5000, tol=1e-13, rho=1e-3).run()
    r_ls = float(torch.linalg.vector_norm(mat @ x_ls.reshape(-1) - b.reshape(-1)))
    r_a = float(torch.linalg.vector_norm(model.apply(a.x) - b))
    b_norm = float(torch.linalg.vector_norm(b))
    assert r_ls < 1e-10 * b_norm  # the system is square and invertible: exact fit exists
    assert r_a < 1e-4 * b_norm  # ADMM converges linearly towards it


@pytest.mark.parametrize("isotropic", [True, False])
@pytest.mark.parametrize(("erasure", "field"), [(0.0, None), (0.9, None), (0.5, (24, 28))])
def test_admm_and_fista_reach_the_same_minimum(isotropic, erasure, field):
    model, b = _problem(erasure, field)
    tv = TV(isotropic=isotropic)
    f = Fista(model.op, b, tau=1e-3, tv=tv, max_iter=3000, tol=1e-10, prox_iters=10).run()
    a = Admm(model, b, tau=1e-3, tv=tv, max_iter=3000, tol=1e-10).run()

    def objective(x):
        r = model.apply(x) - b
        return 0.5 * float((r * r).sum()) + 1e-3 * tv.value(x)

    fo, ao = objective(f.x), objective(a.x)
    assert abs(ao - fo) <= 1e-2 * fo, (ao, fo)
    rel = float(torch.linalg.vector_norm(a.x - f.x) / torch.linalg.vector_norm(f.x))
    assert rel < 0.05, rel
    assert float(a.x.min()) >= 0.0


def test_stepwise_cancel_and_errors():
    model, b = _problem()
    calls = []
    res = Admm(model, b, max_iter=50).run(callback=calls.append, cancel=lambda: len(calls) >= 4)
    assert res.reason is StopReason.CANCELLED and res.iterations == 4
    bad = b.clone()
    bad[0, 2, 2] = float("nan")
    with pytest.raises(NumericalError, match="measurement"):
        Admm(model, bad)
    with pytest.raises(ValueError, match="2d model"):
        Admm(build_model("depth", np.stack([synthetic_psf((8, 8), seed=s) for s in range(2)])),
             torch.zeros(1, 8, 8))
    with pytest.raises(ValueError, match="shape"):
        Admm(model, torch.zeros(1, 3, 3, dtype=torch.float64))


@pytest.mark.parametrize("rho", [1e-300, 1e-40, 1e38, 1e300])
def test_a_rho_outside_the_dtypes_range_is_refused_in_one_line(rho):
    """rho 1e-300 stopped on 'value cannot be converted to type float without overflow' (the TV
    threshold tau / (rho max|H|^2) in float32), rho 1e300 on NaN in the first v update."""
    model = build_model("2d", synthetic_psf((20, 24), seed=0))  # float32
    b = _problem()[1].float()
    with pytest.raises(ValueError, match=re.escape(f"rho {rho:g} puts ADMM's penalty") + r".*"
                       + re.escape("outside the range of torch.float32")):
        Admm(model, b, rho=rho)
    if rho == 1e-300:  # in float64, where the numbers fit, it runs
        res = Admm(*_problem(), rho=rho, max_iter=3).run()
        assert bool(torch.isfinite(res.x).all())


@pytest.mark.filterwarnings("default")  # shown on stderr by the CLI, as a user sees it
def test_recon_admm_says_fista_does_better_when_most_pixels_are_erased(tmp_path, capsys):
    """At 90 % erasures and more the command's default run ended 1.2-5.5 dB below recon
    fista's (recon.admm.slow_erasure_note): it says so before it runs, and only then."""
    from app.cli import main

    for erasure, warned in ((0.95, True), (0.5, False)):
        sim = tmp_path / f"sim{erasure}"
        assert main(["simulate", "--psf", "sample:tutorial", "--scene", "sample:im740",
                     "--erasure", str(erasure), "--noise", "0.01", "--seed", "3",
                     "--downsample", "4", "--out", str(sim)]) == 0
        capsys.readouterr()
        argv = ["recon", "admm", "--psf", str(sim / "psf.npy"), "--meas", str(sim / "meas.npy"),
                "--mask", str(sim / "mask.npy"), "--tau", "1e-4", "--iters", "20",
                "--out", str(tmp_path / f"a{erasure}.tif")]
        assert main(argv) == 0
        err = capsys.readouterr().err
        said = re.search(r"9[45] % of the sensor's pixels are erased.*recon fista does better",
                         err)
        assert bool(said) is warned, err
