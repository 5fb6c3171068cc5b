"""Qt workers: run blocking device calls, generators and the preview off the GUI thread.

- :class:`TaskQueue`: one QThread that runs submitted callables (or generators) one at a
  time, in order; results, errors and progress come back to the GUI thread as signals of a
  :class:`Task`. One queue per device serialises everything that touches it.
- :class:`PreviewWorker`: a QObject moved to its own QThread that previews the newest frame
  only (:class:`~app.gui.preview_engine.FrameSlot` drops stale ones).

A running QThread is never destroyed (Qt aborts the process: "QThread: Destroyed while thread
is still running"): a thread that does not stop within its timeout is detached, kept alive in
a module-level set until its ``finished`` signal, and waited for at interpreter exit.
"""

from __future__ import annotations

import atexit
import inspect
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from PySide6.QtCore import QObject, QThread, Signal, Slot

from app.gui.preview_engine import (
    FrameSlot,
    PreviewCancelled,
    PreviewEngine,
    PreviewResult,
    frame_keywords,
)

__all__ = ["Cancelled", "PreviewWorker", "Task", "TaskQueue", "detach_thread",
           "detached_threads"]

_log = logging.getLogger(__name__)

#: QThreads that did not stop in time, with the objects living in them: kept alive (destroying
#: a running QThread aborts the process) until they finish
_DETACHED: set[tuple[QThread, QObject]] = set()
_reaper: _Reaper | None = None
#: at interpreter exit, how long to wait for detached threads before leaving without them
EXIT_WAIT_S = 120.0


class _Reaper(QObject):
    """Lives in the GUI thread: drops a detached thread once it has finished."""

    @Slot()
    def reap(self) -> None:
        for item in list(_DETACHED):
            thread = item[0]
            if thread.isFinished() or thread.wait(1000):  # finished is emitted just before
                _DETACHED.discard(item)
                _log.info("detached thread %r has finished", thread.objectName())


def detached_threads() -> list[str]:
    """Names of the detached threads that still run."""
    return [t.objectName() for t, _ in _DETACHED if t.isRunning()]


def detach_thread(thread: QThread, inner: QObject) -> None:
    """Keep ``thread`` (still running) and ``inner`` alive until the thread finishes."""
    global _reaper
    if _reaper is None:
        _reaper = _Reaper()
        atexit.register(_wait_detached)  # runs before PySide destroys its remaining objects
    _DETACHED.add((thread, inner))
    thread.finished.connect(_reaper.reap)  # queued: the reaper lives in the GUI thread
    if thread.isFinished():  # it ended between the timeout and the connection
        _reaper.reap()


def _wait_detached(timeout_s: float | None = None) -> None:
    """At exit: wait for the detached threads (their work was cancelled, so they end soon).

    Python then destroys every QThread; a running one would abort the process, so one that
    still runs after ``timeout_s`` ends the process at once (exit status 1) instead.
    """
    running = [t for t, _ in _DETACHED if t.isRunning()]
    if not running:
        return
    limit = EXIT_WAIT_S if timeout_s is None else timeout_s
    names = ", ".join(repr(t.objectName()) for t in running)
    _log.warning("waiting up to %.0f s for the %s thread to end its cancelled work", limit,
                 names)
    deadline = time.monotonic() + limit
    for t in running:
        t.wait(max(0, int(1000 * (deadline - time.monotonic()))))
    if any(t.isRunning() for t in running):
        import os
        import sys

        _log.error("the %s thread did not end in %.0f s; leaving without it", names, limit)
        logging.shutdown()
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError, AttributeError):
                pass
        os._exit(1)


class Cancelled(Exception):
    """A task was cancelled before or while it ran."""


class Task(QObject):
    """A unit of work for a :class:`TaskQueue`.

    ``fn`` returns a value, or is a generator function whose every ``yield`` is a progress
    report (emitted as :attr:`progress`) and a cancellation point; its return value is the
    result. Signals arrive on the GUI thread.
    """

    finished = Signal(object, object)  # (task, result)
    failed = Signal(object, object)  # (task, exception)
    progress = Signal(object, object)  # (task, event)

    def __init__(self, fn: Callable[[], Any], name: str) -> None:
        super().__init__()
        self.fn = fn
        self.name = name
        self._cancel = threading.Event()
        self.done = False

    def cancel(self) -> None:
        """Ask the task to stop at its next cancellation point (or not to start)."""
        self._cancel.set()

    @property
    def cancelled(self) -> bool:
        """Whether :meth:`cancel` was called."""
        return self._cancel.is_set()


class _Runner(QObject):
    """Lives in the queue's thread and runs tasks."""

    idle = Signal()

    @Slot(object)
    def run(self, task: Task) -> None:
        try:
            if task.cancelled:
                raise Cancelled(f"{task.name}: cancelled")
            out = task.fn()
            if inspect.isgenerator(out):
                gen = out
                try:
                    while True:
                        if task.cancelled:
                            gen.close()
                            raise Cancelled(f"{task.name}: cancelled")
                        event = next(gen)
                        task.progress.emit(task, event)
                except StopIteration as stop:
                    out = stop.value
        except BaseException as exc:  # handed to the GUI, which shows it
            task.done = True
            task.failed.emit(task, exc)
        else:
            task.done = True
            task.finished.emit(task, out)
        self.idle.emit()


class TaskQueue(QObject):
    """Runs tasks one after another on its own QThread."""

    _go = Signal(object)

    def __init__(self, name: str, parent: QObject | None = None) -> None:
        super().__init__(parent)
        self.name = name
        self._thread = QThread()
        self._thread.setObjectName(name)
        self._runner = _Runner()
        self._runner.moveToThread(self._thread)
        self._go.connect(self._runner.run)
        self._runner.idle.connect(self._on_idle)
        self._pending = 0
        self._callbacks: dict[int, tuple[Any, Any, Any]] = {}
        self._tasks: dict[int, Task] = {}
        self._thread.start()

    @property
    def busy(self) -> bool:
        """Whether tasks wait or run."""
        return self._pending > 0

    def submit(
        self,
        fn: Callable[[], Any],
        *,
        name: str = "task",
        on_done: Callable[[Any], None] | None = None,
        on_error: Callable[[BaseException], None] | None = None,
        on_progress: Callable[[Any], None] | None = None,
    ) -> Task:
        """Queue ``fn``; the callbacks run on the GUI thread."""
        task = Task(fn, name)
        key = id(task)
        self._callbacks[key] = (on_done, on_error, on_progress)
        self._tasks[key] = task
        task.finished.connect(self._finished)
        task.failed.connect(self._failed)
        task.progress.connect(self._progress)
        self._pending += 1
        self._go.emit(task)
        return task

    def _take(self, task: Task) -> tuple[Any, Any, Any]:
        self._tasks.pop(id(task), None)
        return self._callbacks.pop(id(task), (None, None, None))

    @Slot(object, object)
    def _finished(self, task: Task, result: Any) -> None:
        on_done, _, _ = self._take(task)
        if on_done is not None:
            on_done(result)

    @Slot(object, object)
    def _failed(self, task: Task, exc: BaseException) -> None:
        _, on_error, _ = self._take(task)
        if on_error is not None:
            on_error(exc)
        elif not task.cancelled:  # an abandoned task's end is nobody's error
            _log.error("%s: task %s failed: %s", self.name, task.name, exc)

    @Slot(object, object)
    def _progress(self, task: Task, event: Any) -> None:
        _, _, on_progress = self._callbacks.get(id(task), (None, None, None))
        if on_progress is not None:
            on_progress(event)

    @Slot()
    def _on_idle(self) -> None:
        self._pending = max(0, self._pending - 1)

    def cancel_all(self) -> None:
        """Cancel every task that waits or runs."""
        for task in list(self._tasks.values()):
            task.cancel()

    def shutdown(self, timeout_ms: int = 10_000) -> bool:
        """Cancel the waiting tasks, let the running one end, stop the thread."""
        self.cancel_all()
        self._thread.quit()
        ok = bool(self._thread.wait(timeout_ms))
        if not ok:  # a hung device call: left to end in the background, never destroyed
            _log.error("%s: worker thread did not stop within %d ms", self.name, timeout_ms)
            detach_thread(self._thread, self._runner)
        return ok

    def abandon(self) -> None:
        """Cancel every task and stop the thread without waiting: the GUI goes on at once.

        A running task that has no cancellation point (a plan's analysis) ends in the
        background; its callbacks are dropped. For work whose result is no longer wanted (a
        dialog closed while it plans); :meth:`shutdown` waits.
        """
        self.cancel_all()
        self._callbacks.clear()
        self._thread.quit()
        if not self._thread.isFinished():
            detach_thread(self._thread, self._runner)


class PreviewWorker(QObject):
    """Previews the newest frame on its own QThread; stale frames are dropped.

    :meth:`submit` (GUI thread) puts the frame into a one-frame slot and wakes the worker;
    the worker takes whatever is newest when it gets to it. Results and errors come back as
    signals on the GUI thread.
    """

    result = Signal(object)
    error = Signal(str)
    _wake = Signal()

    def __init__(self, engine: PreviewEngine) -> None:
        super().__init__()
        self.engine = engine
        # a new worker previews: an earlier worker's stop() cancelled this engine
        resume = getattr(engine, "resume", None)
        if resume is not None:
            resume()
        self.slot = FrameSlot()
        self._thread = QThread()
        self._thread.setObjectName("preview")
        self._inner = _PreviewRunner(self)
        self._inner.moveToThread(self._thread)
        self._wake.connect(self._inner.process)
        self._inner.result.connect(self.result)
        self._inner.error.connect(self.error)
        self._thread.start()

    def submit(self, frame: Any) -> None:
        """Offer a :class:`drivers.camera.Frame` (replaces one still waiting)."""
        self.slot.put(frame.pixels, **frame_keywords(frame))
        self._wake.emit()

    def stop(self, timeout_ms: int = 10_000) -> bool:
        """End the worker thread; returns whether it ended within ``timeout_ms``.

        The frame in progress is cancelled (the engine's ``cancel()``: it stops at its next
        cancellation point) and waited for up to ``timeout_ms``. A thread that did not end (a
        single long computation) is detached, not destroyed: it stays alive until it finishes
        (see the module docstring).
        """
        self.slot.close()
        cancel = getattr(self.engine, "cancel", None)
        if cancel is not None:
            cancel()
        self._thread.quit()
        if self._thread.wait(timeout_ms):
            return True
        _log.error("the preview frame in progress did not stop within %d ms; its thread is "
                   "left to finish in the background", timeout_ms)
        detach_thread(self._thread, self._inner)
        return False


class _PreviewRunner(QObject):
    result = Signal(object)
    error = Signal(str)

    def __init__(self, owner: PreviewWorker) -> None:
        super().__init__()
        self._engine = owner.engine
        self._slot = owner.slot

    @Slot()
    def process(self) -> None:
        if self._slot.closed:
            return  # the worker is stopping
        item = self._slot.take()
        if item is None:
            return  # a newer wake-up already took the frame (it was stale)
        pixels, meta = item
        try:
            res: PreviewResult = self._engine.process(pixels, **meta)
        except PreviewCancelled as exc:  # the worker is stopping: nothing to show
            self._slot.done(exc)
            return
        except Exception as exc:  # shown in the preview panel
            self._slot.done(exc)
            self.error.emit(f"{type(exc).__name__}: {exc}" if not str(exc) else str(exc))
            return
        self._slot.done()
        self.result.emit(res)
