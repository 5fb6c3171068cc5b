"""One contract for long work in recon: stepwise objects with one vocabulary of stop reasons.

Every long computation (FISTA, ADMM, the UDN runner) is a :class:`Stepwise` object:

- :meth:`Stepwise.step` does one iteration and returns its progress report (a :class:`Step`:
  at least ``iteration`` and ``elapsed_s``); it is the cancellation point. Calling it once the
  run is :attr:`~Stepwise.done` raises :class:`RunFinished` (a finished run is never silently
  continued: a harness that kept stepping a finished FISTA once ran for 24 minutes);
- :attr:`Stepwise.done` is True once :attr:`Stepwise.reason` (a :class:`StopReason`) is set;
- :meth:`Stepwise.cancel` stops the run as ``cancelled`` (the estimate so far stays);
- :meth:`Stepwise.steps` is a generator of steps until done (stop iterating to pause).

The variational solvers (FISTA, ADMM) share :class:`StepwiseSolver`, which adds ``run`` with a
:class:`SolverResult` and :meth:`StepwiseSolver.set_measurement`, the public way to replace the
measurement between steps (a new camera frame for the warm-started live preview).
Nothing here prints; progress leaves as return values.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from enum import Enum
from typing import Any, Generic, Protocol, TypeVar, runtime_checkable

import torch

__all__ = [
    "NumericalError",
    "RunFinished",
    "SolverResult",
    "SolverStep",
    "Step",
    "Stepwise",
    "StepwiseSolver",
    "StopReason",
    "check_finite",
]


class NumericalError(FloatingPointError):
    """A solver produced NaN or inf; the message says where."""


class RunFinished(RuntimeError):
    """:meth:`Stepwise.step` was called after the run stopped (its reason is in the message)."""


class StopReason(str, Enum):
    """Why a long run stopped: the one vocabulary of every solver and the UDN runner."""

    CONVERGED = "converged"  # relative change below the tolerance
    MAX_ITER = "max_iter"  # iteration limit
    TIME_LIMIT = "time_limit"  # wall-time limit
    STOPPED_EARLY = "stopped_early"  # early stopping on held-out pixels (UDN)
    STALLED = "stalled"  # repeated failed steps (FISTA's inexact prox)
    CANCELLED = "cancelled"  # cancel() or the run's cancel callback


@runtime_checkable
class Step(Protocol):
    """What every progress report carries."""

    @property
    def iteration(self) -> int:
        """1-based number of the iteration this step reports."""

    @property
    def elapsed_s(self) -> float:
        """Seconds spent in steps so far."""


StepT = TypeVar("StepT", bound=Step)


def check_finite(t: torch.Tensor, where: str, it: int, solver: str = "FISTA") -> None:
    """Raise :class:`NumericalError` naming ``where`` if ``t`` holds NaN or inf."""
    if not bool(torch.isfinite(t).all()):
        n_bad = int((~torch.isfinite(t)).sum())
        raise NumericalError(
            f"{solver}: {n_bad} NaN/inf values appeared in {where} at iteration {it}"
        )


class Stepwise(ABC, Generic[StepT]):
    """Base of long work: ``step() -> Step``, ``done``, ``cancel()``, ``steps()``.

    Subclasses set ``iteration`` (0 before the first step) and ``reason`` (None while running),
    implement :meth:`step`, and call :meth:`_check_running` first thing in it.
    """

    iteration: int
    reason: StopReason | None

    @abstractmethod
    def step(self) -> StepT:
        """Do one iteration and report it (raises :class:`RunFinished` once done)."""

    @property
    def done(self) -> bool:
        """True once a stop criterion was met (or the run was cancelled)."""
        return self.reason is not None

    def _check_running(self) -> None:
        if self.reason is not None:
            raise RunFinished(
                f"{type(self).__name__}: the run has already stopped ({self.reason.value}) "
                f"after {self.iteration} iterations; start a new one to continue"
            )

    def cancel(self) -> None:
        """Stop the run as ``cancelled`` (no-op once stopped); the estimate so far stays."""
        if self.reason is None:
            self.reason = StopReason.CANCELLED

    def steps(self) -> Iterator[StepT]:
        """Generator of steps until done; stop iterating to pause, :meth:`cancel` to stop."""
        while not self.done:
            yield self.step()

    def _drive(self, steps: Iterator[StepT], callback: Callable[[StepT], None] | None,
               cancel: Callable[[], bool] | None) -> list[StepT]:
        """Consume ``steps`` with a callback and a cancel poll after each; return the history."""
        history: list[StepT] = []
        for s in steps:
            history.append(s)
            if callback is not None:
                callback(s)
            if cancel is not None and cancel():
                self.cancel()
                break
        return history


@dataclass(frozen=True)
class SolverStep:
    """Progress after one iteration of a variational solver (FISTA, ADMM)."""

    iteration: int
    objective: float
    data_term: float
    residual: float
    rel_change: float
    elapsed_s: float
    restarted: bool


@dataclass
class SolverResult:
    """Outcome of :meth:`StepwiseSolver.run`."""

    x: torch.Tensor
    reason: StopReason
    history: list[SolverStep]
    iterations: int
    elapsed_s: float
    params: dict[str, Any]


class StepwiseSolver(Stepwise[SolverStep]):
    """Shared driver of the variational solvers (FISTA, ADMM).

    Subclasses implement ``step``, ``params`` and ``_replace_measurement``, and set ``x``
    (the current estimate), ``iteration``, ``max_iter``, ``reason``, ``b`` (the
    measurement) and ``_elapsed``.
    """

    x: torch.Tensor
    b: torch.Tensor
    max_iter: int
    _elapsed: float

    @property
    @abstractmethod
    def params(self) -> dict[str, Any]:
        """Solver settings, for run records and metadata."""

    @abstractmethod
    def _replace_measurement(self, b: torch.Tensor) -> None:
        """Swap in ``b`` (already checked, converted) and update what depends on it."""

    def set_measurement(self, b: torch.Tensor) -> None:
        """Use the measurement ``b`` (same shape) from the next step on, keeping the state.

        The iterate (and momentum, duals) carry over, so a slowly changing scene converges as
        if it were one long run (the live preview's warm start). A run stopped by a criterion
        (converged, stalled, iteration limit) resumes (a reached iteration limit is extended
        by ``max_iter``); a cancelled run stays cancelled.
        """
        if tuple(b.shape) != tuple(self.b.shape):
            raise ValueError(f"measurement has shape {tuple(b.shape)}, the model expects "
                             f"{tuple(self.b.shape)}")
        new = b.to(dtype=self.b.dtype, device=self.b.device)
        check_finite(new, "the new measurement", self.iteration, type(self).__name__)
        self._replace_measurement(new)
        if self.reason is not StopReason.CANCELLED:
            self.reason = None
            if self.iteration >= self.max_iter:
                self.max_iter = self.iteration + max(1, self.max_iter)

    def run(
        self,
        callback: Callable[[SolverStep], None] | None = None,
        cancel: Callable[[], bool] | None = None,
    ) -> SolverResult:
        """Run to a stop criterion (or until ``cancel()`` returns True) and return the result."""
        history = self._drive(self.steps(), callback, cancel)
        reason = self.reason if self.reason is not None else StopReason.CANCELLED
        return SolverResult(self.x, reason, history, self.iteration, self._elapsed, self.params)
