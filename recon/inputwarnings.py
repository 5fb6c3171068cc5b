"""Warnings about a reconstruction's inputs, kept for the load that raised them.

:func:`recon.problem.load_problem` records the :class:`~recon.checks.MeasurementWarning` s and
:class:`~recon.psfcheck.PsfWarning` s its inputs raise in the problem's metadata. Python's
``warnings.catch_warnings`` cannot do that safely: it swaps process-wide state, so a load in one
thread recorded (and hid) another thread's warnings, and two catches in two threads could leave
the filters of the wrong one in force. Here the emitter itself hands each message to the
collections open *in its own thread* (a context variable), then warns as usual: the warning
filters still decide what is shown, and never what is recorded.
"""

from __future__ import annotations

import sys
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field
from typing import Any


@dataclass
class _Collection:
    messages: list[str] = field(default_factory=list)
    registry: dict[Any, Any] = field(default_factory=dict)  # "once per location": per load
    emit: bool = True  # False: kept here only, not passed to the warning filters


#: the collections open in this thread (and context), innermost last
_OPEN: ContextVar[tuple[_Collection, ...]] = ContextVar("lenslesscam_input_warnings", default=())


def warn_input(message: str, category: type[Warning], stacklevel: int = 1) -> None:
    """``warnings.warn(message, category)``, with ``message`` kept by every open collection.

    ``stacklevel`` as for ``warnings.warn`` from the caller (1: the line that calls this).
    Inside a collection, the warning filters' "once per location" counts per collection (as
    the catch of warnings this replaces did: each load says its warnings again).
    """
    open_ = _OPEN.get()
    for c in open_:
        if message not in c.messages:
            c.messages.append(message)
    if open_ and not open_[-1].emit:
        return
    try:
        frame = sys._getframe(stacklevel)  # as warnings.warn(stacklevel=stacklevel + 1) here
    except ValueError:  # a shallower stack than asked: as warnings.warn does, "sys"
        warnings.warn(message, category, stacklevel=stacklevel + 1)
        return
    g = frame.f_globals
    registry = open_[-1].registry if open_ else g.setdefault("__warningregistry__", {})
    # module_globals lets the warning show its source line; code without a file (python -c,
    # an interactive session) has a loader that cannot give it (ImportError in linecache)
    warnings.warn_explicit(message, category, frame.f_code.co_filename, frame.f_lineno,
                           module=g.get("__name__"), registry=registry,
                           module_globals=g if g.get("__file__") else None)


@contextmanager
def collect_input_warnings(*, emit: bool = True) -> Iterator[list[str]]:
    """Collect what :func:`warn_input` emits in this thread inside the block.

    The list holds each message once, in order, whatever the warning filters say. With
    ``emit=False`` the warnings are not emitted at all (the caller shows them its own way).
    """
    c = _Collection(emit=emit)
    token = _OPEN.set((*_OPEN.get(), c))
    try:
        yield c.messages
    finally:
        _OPEN.reset(token)
