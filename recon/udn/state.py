"""The vocabulary of UDN jobs: where a run stands and how it ended.

:class:`JobState` and :class:`FinishReason` are str-Enums, so a member equals its string
(``JobState.RUNNING == "running"``), is written to JSON as that string and reads back with
``JobState(text)``. Why a *solver* stopped (iteration limit, early stop, ...) is the solver's
stop reason (:class:`recon.stepwise.StopReason`); a job maps it onto a :class:`FinishReason`
and keeps the solver's words in the record's ``detail``.

This module itself imports only :mod:`enum` (the package ``recon.udn`` imports torch in its
``__init__``).
"""

from __future__ import annotations

import enum

__all__ = ["FinishReason", "JobState"]


class JobState(enum.StrEnum):
    """Where a job stands.

    ``STARTING``, ``RUNNING`` and ``FINISHED`` are written in the run record (``status``);
    ``INTERRUPTED`` is what a reader concludes when the record says running but its process is
    gone; ``QUEUED`` is a job an application holds back until a device is free (never in a run
    record).
    """

    QUEUED = "queued"
    STARTING = "starting"
    RUNNING = "running"
    INTERRUPTED = "interrupted"
    FINISHED = "finished"

    @property
    def active(self) -> bool:
        """Whether a process works on the run (or is about to)."""
        return self in (JobState.STARTING, JobState.RUNNING)


class FinishReason(enum.StrEnum):
    """How a finished job ended (the record's ``finish_reason``)."""

    COMPLETED = "completed"  # iteration or wall-time limit reached (``detail`` says which)
    STOPPED_EARLY = "stopped_early"  # the held-out error stopped improving
    CANCELLED = "cancelled"  # SIGTERM / SIGINT, ``jobs cancel`` or the caller
    FAILED = "failed"  # an error (``error`` in the record: type and message)

    @property
    def resumable(self) -> bool:
        """Whether ``jobs resume`` may continue such a run without raising its limits."""
        return self in (FinishReason.CANCELLED, FinishReason.FAILED)
