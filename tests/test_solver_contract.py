"""One contract for every stepwise solver in recon (FISTA, ADMM, the UDN runner, and any new one).

The implementations are enumerated from the code (every concrete subclass of
:class:`recon.stepwise.Stepwise` in any ``recon`` module), not from a list kept here: a new
solver without a factory below fails :func:`test_every_solver_has_a_factory`.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
import torch

import recon
from recon.models import build_model
from recon.simulate import simulate, synthetic_psf
from recon.stepwise import RunFinished, Step, Stepwise, StepwiseSolver, StopReason

H, W = 16, 20


def _implementations() -> list[type[Stepwise[Any]]]:
    for mod in pkgutil.walk_packages(recon.__path__, "recon."):
        importlib.import_module(mod.name)
    found: list[type[Stepwise[Any]]] = []
    todo: list[type[Any]] = [Stepwise]
    while todo:
        for sub in todo.pop().__subclasses__():
            todo.append(sub)
            if not inspect.isabstract(sub) and sub.__module__.startswith("recon."):
                found.append(sub)
    return sorted(set(found), key=lambda c: c.__qualname__)


def _problem(seed: int = 0) -> tuple[Any, torch.Tensor]:
    psf = synthetic_psf((H, W), seed=1)
    rng = np.random.default_rng(seed)
    truth = np.zeros((1, 1, H, W), dtype=np.float32)
    truth[0, 0, 4:12, 5:15] = rng.uniform(0.3, 1.0)
    model = build_model("2d", psf)
    sim = simulate(model, truth, noise=0.01, seed=2 + seed)
    return model, torch.as_tensor(sim.meas)


def _fista(max_iter: int) -> Stepwise[Any]:
    from recon.fista import Fista

    model, b = _problem()
    return Fista(model.op, b, tau=1e-3, max_iter=max_iter, tol=0.0)


def _admm(max_iter: int) -> Stepwise[Any]:
    from recon.admm import Admm

    model, b = _problem()
    return Admm(model, b, tau=1e-3, max_iter=max_iter, tol=0.0)


def _udn(max_iter: int) -> Stepwise[Any]:
    from recon.udn.network import NetworkConfig
    from recon.udn.runner import UDNConfig, UDNRunner

    model, b = _problem()
    net = NetworkConfig(scales=2, channels=8, skip_channels=2, input_channels=4)
    return UDNRunner(model, b.numpy(), network=net,
                     config=UDNConfig(max_iter=max_iter, holdout=0.0, seed=0))


#: How to build a tiny instance of each implementation, by class name.
FACTORIES: dict[str, Callable[[int], Stepwise[Any]]] = {
    "Fista": _fista,
    "Admm": _admm,
    "UDNRunner": _udn,
}

IMPLEMENTATIONS = _implementations()


@pytest.fixture(autouse=True)
def _one_thread() -> Iterator[None]:
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def test_every_solver_has_a_factory() -> None:
    names = {c.__name__ for c in IMPLEMENTATIONS}
    assert {"Fista", "Admm", "UDNRunner"} <= names  # the enumeration finds the real ones
    missing = names - set(FACTORIES)
    assert not missing, f"add a factory for {sorted(missing)} to this contract test"


@pytest.fixture(params=[c.__name__ for c in IMPLEMENTATIONS])
def make(request: pytest.FixtureRequest) -> Callable[[int], Stepwise[Any]]:
    """Factory of a tiny instance of each implementation (argument: max_iter)."""
    return FACTORIES[request.param]


class TestSolverContract:
    """Every stepwise solver: step, done, cancel, one StopReason, no stepping after done."""

    def test_step_reports_progress(self, make: Callable[[int], Stepwise[Any]]) -> None:
        s = make(5)
        assert s.iteration == 0 and not s.done and s.reason is None
        step = s.step()
        assert isinstance(step, Step)
        assert step.iteration == s.iteration == 1 and step.elapsed_s >= 0.0

    def test_runs_to_its_limit_then_refuses_to_step(
            self, make: Callable[[int], Stepwise[Any]]) -> None:
        s = make(3)
        seen = [st.iteration for st in s.steps()]
        assert seen == [1, 2, 3]
        assert s.done and s.reason is StopReason.MAX_ITER
        assert isinstance(s.reason, str) and s.reason == "max_iter"  # a str-Enum
        with pytest.raises(RunFinished, match="already stopped \\(max_iter\\)"):
            s.step()
        assert s.iteration == 3 and list(s.steps()) == []  # nothing moved

    def test_cancel_stops_for_good(self, make: Callable[[int], Stepwise[Any]]) -> None:
        s = make(10)
        s.step()
        s.cancel()
        assert s.done and s.reason is StopReason.CANCELLED
        s.cancel()  # idempotent
        assert s.reason is StopReason.CANCELLED
        with pytest.raises(RunFinished, match="cancelled"):
            s.step()
        assert s.iteration == 1

    def test_run_polls_cancel_after_each_step(
            self, make: Callable[[int], Stepwise[Any]]) -> None:
        s = make(10)
        got: list[int] = []
        res = s.run(callback=lambda st: got.append(st.iteration),  # type: ignore[attr-defined]
                    cancel=lambda: len(got) >= 2)
        assert got == [1, 2] and s.iteration == 2
        assert res.reason is StopReason.CANCELLED and res.iterations == 2


@pytest.fixture(params=[c.__name__ for c in IMPLEMENTATIONS if issubclass(c, StepwiseSolver)])
def make_solver(request: pytest.FixtureRequest) -> Callable[[int], Stepwise[Any]]:
    """Factory of each variational solver (those that take a new measurement)."""
    return FACTORIES[request.param]


class TestMeasurementSwap:
    """The public warm-start path of the live preview: replace b, keep the state."""

    def test_new_measurement_keeps_the_iterate_and_resumes(
            self, make_solver: Callable[[int], Stepwise[Any]]) -> None:
        s = make_solver(3)
        assert isinstance(s, StepwiseSolver)
        list(s.steps())
        assert s.reason is StopReason.MAX_ITER
        x = s.x.clone()
        _, b2 = _problem(seed=1)
        s.set_measurement(b2)
        assert not s.done and torch.equal(s.x, x) and torch.equal(s.b, b2)
        step = s.step()
        assert step.iteration == 4 and s.b.dtype == torch.float32
        with pytest.raises(ValueError, match="shape"):
            s.set_measurement(b2[..., :-1])
        with pytest.raises(FloatingPointError, match="NaN/inf"):
            s.set_measurement(torch.full_like(b2, float("nan")))

    def test_cancelled_stays_cancelled(
            self, make_solver: Callable[[int], Stepwise[Any]]) -> None:
        s = make_solver(5)
        assert isinstance(s, StepwiseSolver)
        s.cancel()
        s.set_measurement(s.b.clone())
        assert s.reason is StopReason.CANCELLED
        with pytest.raises(RunFinished):
            s.step()
