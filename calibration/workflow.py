"""Stepwise calibration workflows: progress events, cancellation, refusals.

Every workflow of this package is a generator that yields :class:`Progress` events (a stage,
a message, the overall fraction done, optionally the latest frame) and returns its result.
:class:`Workflow` wraps such a generator for its consumers: the CLI iterates it and draws a
progress bar; the GUI wizard iterates it in a worker thread, turns each event into a Qt signal
and calls :meth:`Workflow.cancel` from the GUI thread. Every ``yield`` is a cancellation
point: a cancel takes effect there, the generator's ``finally`` blocks run (the light source
is switched off, the camera stopped) and :class:`CalibrationCancelled` is raised to the
consumer. Nothing is saved unless a workflow runs to its end.

A workflow that must refuse (a saturated PSF, no light, an off-centre source) raises
:class:`CalibrationError`, whose message says what is wrong and what to change.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Generator, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import numpy as np

__all__ = [
    "CalibrationCancelled",
    "CalibrationError",
    "Progress",
    "Steps",
    "Workflow",
    "scaled",
]

T = TypeVar("T")

#: What a workflow function returns: a generator of progress events whose value is the result.
Steps = Generator["Progress", None, T]


class CalibrationError(ValueError):
    """A calibration refused or failed; the message says what is wrong and what to change.

    ``problem`` is what went wrong, ``hint`` what the user can change, ``stage`` the workflow
    stage it happened in.
    """

    def __init__(self, problem: str, hint: str = "", *, stage: str = "") -> None:
        self.problem = problem
        self.hint = hint
        self.stage = stage
        text = problem if not hint else f"{problem}. {hint}"
        super().__init__(text if text.endswith(".") else text + ".")


class CalibrationCancelled(Exception):
    """The workflow was cancelled at a progress point (nothing was saved)."""


@dataclass(frozen=True)
class Progress:
    """One step of a workflow.

    ``stage`` is a short machine-readable name (``darks``, ``exposure``, ``frames``,
    ``save``...), ``message`` a sentence for people, ``fraction`` the overall fraction done
    in [0, 1]. ``frame`` is the latest image when there is one worth showing (the GUI shows
    it; the CLI ignores it); ``data`` holds stage details (exposure, peak level...).
    """

    stage: str
    message: str
    fraction: float
    frame: np.ndarray | None = field(default=None, repr=False, compare=False)
    data: Mapping[str, Any] = field(default_factory=dict)


def scaled(steps: Steps[T], start: float, stop: float) -> Steps[T]:
    """Run a sub-workflow, mapping its fractions into ``[start, stop]`` of the outer one."""
    span = stop - start
    gen = steps
    try:
        while True:
            try:
                p = next(gen)
            except StopIteration as done:
                return done.value  # type: ignore[no-any-return]
            yield Progress(
                p.stage, p.message, start + span * min(max(p.fraction, 0.0), 1.0), p.frame, p.data
            )
    finally:
        gen.close()


class Workflow(Generic[T]):
    """A running workflow: iterate it for :class:`Progress`, then read :attr:`result`.

    :meth:`run` drives it to the end with an optional callback. :meth:`cancel` may be called
    from any thread; it takes effect at the next progress event.
    """

    def __init__(self, steps: Steps[T], name: str = "calibration") -> None:
        self.name = name
        self._gen = steps
        self._cancel = threading.Event()
        self._done = False
        self._started = False
        self._result: T | None = None
        self.last: Progress | None = None

    def cancel(self) -> None:
        """Ask the workflow to stop at its next progress point (thread-safe)."""
        self._cancel.set()

    @property
    def cancelled(self) -> bool:
        """Whether :meth:`cancel` was called."""
        return self._cancel.is_set()

    @property
    def done(self) -> bool:
        """Whether the workflow ran to its end."""
        return self._done

    @property
    def result(self) -> T:
        """The workflow's result (only after it finished)."""
        if not self._done:
            raise RuntimeError(f"{self.name}: the workflow has not finished")
        return self._result  # type: ignore[return-value]

    def _stop_cancelled(self) -> None:
        msg = f"{self.name} cancelled"
        if self.last is not None:
            msg += f" during {self.last.stage} ({self.last.message})"
        try:
            self._gen.throw(CalibrationCancelled(msg + "; nothing was saved"))
        except StopIteration:  # it ignored the cancel and finished: still a cancel
            pass
        finally:
            self._gen.close()
        raise CalibrationCancelled(msg + "; nothing was saved")

    def __iter__(self) -> Iterator[Progress]:
        if self._started:
            raise RuntimeError(f"{self.name}: a workflow can be iterated only once")
        self._started = True
        try:
            while True:
                if self._cancel.is_set():
                    self._stop_cancelled()
                try:
                    p = next(self._gen)
                except StopIteration as stop:
                    self._result = stop.value
                    self._done = True
                    return
                self.last = p
                yield p
        finally:
            if not self._done:
                self._gen.close()  # consumer stopped iterating: the workflow cleans up

    def run(self, on_progress: Callable[[Progress], None] | None = None) -> T:
        """Drive the workflow to its end, calling ``on_progress`` for every event."""
        for p in self:
            if on_progress is not None:
                on_progress(p)
        return self.result
