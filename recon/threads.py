"""One thread policy for every command and the app: how many torch CPU threads to use.

Measured on the project's 2-vCPU machines: with the machine busy, torch with 2 intra-op threads
ran FISTA 7-77x slower than with 1 (the threads wait on each other while the other process holds
a core). Extra threads only pay when cores are free. So the policy is:

- an explicit request (``--threads N`` on the command line, a job spec's ``threads``, or the
  ``OMP_NUM_THREADS`` environment variable) wins, up to ``MAX_THREADS_PER_CORE`` threads per
  core (a request above that is an error; an ``OMP_NUM_THREADS`` above it, often set by a
  scheduler for another machine, is cut to it with a note);
- otherwise the number of *free* cores: the cores this process may run on
  (``os.sched_getaffinity``) minus the 1-minute load average (``os.getloadavg``), rounded to
  the nearest integer, at least 1 and at most ``MAX_AUTO_THREADS`` (small FFTs stop scaling
  well before that).

On a 2-core machine that means 2 threads only when it is nearly idle (load below 0.5), and 1
as soon as anything else runs; never more threads than free cores, so never the collapse above.

Small problems do not pay for a second thread even on an idle machine: an FFT solver's step on
a small grid is dozens of short elementwise passes, and waking threads for each costs more than
it saves. Measured on the idle 2-core machine, FISTA-TV per step, 2 threads / 1 thread
(interleaved, ``lenslesscam bench fista --threads-check``): 1.18 at a 96^2 scene, 1.13 at 128^2,
1.20 at 192^2, 0.93 at 256^2, 0.72 at 384^2, 0.63 at 512^2. So an automatic choice for an FFT
solver (FISTA, ADMM, the live preview) is also capped at one thread per
``FFT_PIXELS_PER_THREAD`` (2^16) scene pixels, channels and slices included
(:func:`fit_threads`, called once the problem is built): one thread up to a 256^2 scene.

:func:`choose_threads` is pure (cores, load and work can be passed in, for tests);
:func:`apply_threads` also sets torch's thread count and returns what it chose and why, as a
short string for logs and benchmark headers.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

__all__ = ["FFT_PIXELS_PER_THREAD", "MAX_AUTO_THREADS", "ThreadChoice", "apply_threads",
           "choose_threads", "fit_threads", "machine_state", "max_requested_threads"]

#: Upper bound of the automatic choice (explicit requests: ``MAX_THREADS_PER_CORE``).
MAX_AUTO_THREADS = 8

#: Scene pixels (channels x slices x rows x columns) per thread of an FFT solver (see above).
FFT_PIXELS_PER_THREAD = 1 << 16

#: The process's last choice made by :func:`apply_threads` without a work size (what
#: :func:`fit_threads` refines); None until something applied the policy.
_process_choice: ThreadChoice | None = None


@dataclass(frozen=True)
class ThreadChoice:
    """The thread count chosen, and the facts it was chosen from."""

    threads: int
    cores: int
    load: float
    source: str  # "requested", "OMP_NUM_THREADS" or "auto"
    work: int | None = None  # scene pixels of the FFT solver it was fitted to, if any

    @property
    def reason(self) -> str:
        """A short line for logs: the count and why."""
        facts = f"{self.cores} cores, load {self.load:.2f}"
        if self.work is not None and self.source == "auto":
            facts += f", {self.work} scene pixels"
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


#: a requested thread count may be at most this many times the machine's cores (more only
#: slows the work down; tens of thousands made the OpenMP runtime hang, fail or crash)
MAX_THREADS_PER_CORE = 4


def _limit(cores: int) -> int:
    return MAX_THREADS_PER_CORE * max(1, cores)


def max_requested_threads(cores: int | None = None) -> int:
    """The most threads a request may name on this machine (``cores``: its own by default).

    :data:`MAX_THREADS_PER_CORE` per core. A job dialog's range ends there.
    """
    return _limit(machine_state()[0] if cores is None else int(cores))


def _bounded(n: int, cores: int, name: str) -> int:
    limit = _limit(cores)
    if n > limit:
        raise ValueError(f"{name} {n} is more than {MAX_THREADS_PER_CORE}x this machine's "
                         f"{cores} cores ({limit}); use 0 to choose")
    return n


def choose_threads(requested: int | str | None = None, *, cores: int | None = None,
                   load: float | None = None, env: dict[str, str] | None = None,
                   work: int | None = None) -> ThreadChoice:
    """Choose torch's thread count (see the module docstring); changes nothing.

    ``requested``: a count > 0 to use as is; None, 0 or ``"auto"`` to choose. ``cores`` and
    ``load`` default to this machine's (:func:`machine_state`); ``env`` to ``os.environ``.
    ``work``: the scene pixels of the FFT solver to run (channels x slices x rows x columns),
    which caps an automatic choice at one thread per :data:`FFT_PIXELS_PER_THREAD`.
    """
    real_cores, real_load = machine_state()
    cores = real_cores if cores is None else max(1, int(cores))
    load = real_load if load is None else max(0.0, float(load))
    want = _parse_request(requested, "threads")
    if want is not None:
        return ThreadChoice(_bounded(want, cores, "threads"), cores, load, "requested")
    env = dict(os.environ) if env is None else env
    omp = env.get("OMP_NUM_THREADS")
    if omp:
        n = _parse_request(omp, "OMP_NUM_THREADS")
        if n is not None:
            if n > _limit(cores):
                return ThreadChoice(_limit(cores), cores, load,
                                    f"OMP_NUM_THREADS {n} cut to {MAX_THREADS_PER_CORE}x cores")
            return ThreadChoice(n, cores, load, "OMP_NUM_THREADS")
    free = int(cores - load + 0.5)  # round half up; cores - load may be negative
    n = min(free, cores, MAX_AUTO_THREADS)
    if work is not None:
        n = min(n, int(work) // FFT_PIXELS_PER_THREAD)
    return ThreadChoice(max(1, n), cores, load, "auto", None if work is None else int(work))


def apply_threads(requested: int | str | None = None) -> ThreadChoice:
    """Choose (:func:`choose_threads`) and set torch's intra-op thread count; return the choice.

    Call it once at the start of a command, a job or the app (it is process-wide).
    """
    global _process_choice
    choice = choose_threads(requested)
    _process_choice = choice
    _set_torch_threads(choice.threads)
    return choice


def fit_threads(scene_shape: tuple[int, ...] | list[int]) -> ThreadChoice | None:
    """Fit the process's automatic choice to an FFT solver of this scene shape, and set it.

    Called by the commands and the preview once the problem is built. The choice
    :func:`apply_threads` made is capped at one thread per :data:`FFT_PIXELS_PER_THREAD` scene
    pixels (a later, larger problem gets the uncapped count back); an explicit request or
    ``OMP_NUM_THREADS`` is kept as given. Returns the choice in force, or None (and changes
    nothing) when the policy was never applied in this process (library use).
    """
    base = _process_choice
    if base is None:
        return None
    if base.source != "auto":
        return base
    # the same cores and load as the process's choice: only the work cap is new
    choice = choose_threads(None, cores=base.cores, load=base.load, env={},
                            work=math.prod(int(n) for n in scene_shape))
    _set_torch_threads(choice.threads)
    return choice


def _set_torch_threads(n: int) -> None:
    import torch  # lazy: the policy itself needs no torch

    if torch.get_num_threads() != n:
        torch.set_num_threads(n)
