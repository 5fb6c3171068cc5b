"""One thread policy for every command and the app: how many torch CPU threads to use.

Measured on the project's 2-vCPU machines: with the machine busy, torch with 2 intra-op threads
ran FISTA 7-77x slower than with 1 (the threads wait on each other while the other process holds
a core). Extra threads only pay when cores are free. So the policy is:

- an explicit request (``--threads N`` on the command line, a job spec's ``threads``, or the
  ``OMP_NUM_THREADS`` environment variable) wins, as given;
- otherwise the number of *free* cores: the cores this process may run on
  (``os.sched_getaffinity``) minus the 1-minute load average (``os.getloadavg``), rounded to
  the nearest integer, at least 1 and at most ``MAX_AUTO_THREADS`` (small FFTs stop scaling
  well before that).

On a 2-core machine that means 2 threads only when it is nearly idle (load below 0.5), and 1
as soon as anything else runs; never more threads than free cores, so never the collapse above.
:func:`choose_threads` is pure (cores and load can be passed in, for tests);
:func:`apply_threads` also sets torch's thread count and returns what it chose and why, as a
short string for logs and benchmark headers.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

__all__ = ["MAX_AUTO_THREADS", "ThreadChoice", "apply_threads", "choose_threads",
           "machine_state"]

#: Upper bound of the automatic choice (explicit requests are not capped).
MAX_AUTO_THREADS = 8


@dataclass(frozen=True)
class ThreadChoice:
    """The thread count chosen, and the facts it was chosen from."""

    threads: int
    cores: int
    load: float
    source: str  # "requested", "OMP_NUM_THREADS" or "auto"

    @property
    def reason(self) -> str:
        """A short line for logs: the count and why."""
        facts = f"{self.cores} cores, load {self.load:.2f}"
        if self.source == "auto":
            return f"{self.threads} torch thread(s): auto from {facts}"
        return f"{self.threads} torch thread(s): {self.source} ({facts})"

    def __str__(self) -> str:
        return self.reason


def machine_state() -> tuple[int, float]:
    """(usable cores, 1-minute load average) of this machine, as the policy sees them."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        cores = os.cpu_count() or 1
    try:
        load = float(os.getloadavg()[0])
    except (AttributeError, OSError):  # Windows has no load average
        load = 0.0
    return max(1, cores), max(0.0, load)


def _parse_request(value: int | str | None, what: str) -> int | None:
    """An explicit thread count (> 0), or None for 'choose automatically' (None, 0, 'auto')."""
    if value is None:
        return None
    if isinstance(value, str):
        text = value.strip().lower()
        if text in ("", "auto", "0"):
            return None
        try:
            value = int(text)
        except ValueError:
            raise ValueError(f"{what} must be a whole number >= 0 or 'auto', got {value!r}"
                             ) from None
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"{what} must be a whole number >= 0 or 'auto', got {value!r}")
    return value or None


def choose_threads(requested: int | str | None = None, *, cores: int | None = None,
                   load: float | None = None, env: dict[str, str] | None = None
                   ) -> ThreadChoice:
    """Choose torch's thread count (see the module docstring); changes nothing.

    ``requested``: a count > 0 to use as is; None, 0 or ``"auto"`` to choose. ``cores`` and
    ``load`` default to this machine's (:func:`machine_state`); ``env`` to ``os.environ``.
    """
    real_cores, real_load = machine_state()
    cores = real_cores if cores is None else max(1, int(cores))
    load = real_load if load is None else max(0.0, float(load))
    want = _parse_request(requested, "threads")
    if want is not None:
        return ThreadChoice(want, cores, load, "requested")
    env = dict(os.environ) if env is None else env
    omp = env.get("OMP_NUM_THREADS")
    if omp:
        n = _parse_request(omp, "OMP_NUM_THREADS")
        if n is not None:
            return ThreadChoice(n, cores, load, "OMP_NUM_THREADS")
    free = int(cores - load + 0.5)  # round half up; cores - load may be negative
    return ThreadChoice(max(1, min(free, cores, MAX_AUTO_THREADS)), cores, load, "auto")


def apply_threads(requested: int | str | None = None) -> ThreadChoice:
    """Choose (:func:`choose_threads`) and set torch's intra-op thread count; return the choice.

    Call it once at the start of a command, a job or the app (it is process-wide).
    """
    choice = choose_threads(requested)
    import torch  # lazy: the policy itself needs no torch

    if torch.get_num_threads() != choice.threads:
        torch.set_num_threads(choice.threads)
    return choice
