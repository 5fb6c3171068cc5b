"""Stopping the preview worker while a frame runs: the frame is cancelled, and a thread that
cannot stop in time is detached, never destroyed (Qt aborts the process on a running QThread's
destruction: closing the app after a frame longer than 10 s once ended in SIGABRT)."""

from __future__ import annotations

import gc
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

pytestmark = pytest.mark.gui


def _frame(pixels: np.ndarray | None = None) -> Any:
    """What :func:`app.gui.preview_engine.frame_keywords` reads of a camera frame."""
    px = np.zeros((8, 8), np.uint16) if pixels is None else pixels
    h, w = px.shape
    return SimpleNamespace(pixels=px, frame_id=1, timestamp=time.time(), binning=1,
                           timing=None, sensor=(h, w),
                           roi=SimpleNamespace(x=0, y=0, width=w, height=h))


class _UnstoppableEngine:
    """An engine whose frame is one long computation: ``cancel`` cannot cut it short."""

    def __init__(self) -> None:
        self.started = threading.Event()
        self.release = threading.Event()
        self.cancel_calls = 0

    def process(self, pixels: Any, **meta: Any) -> Any:
        self.started.set()
        self.release.wait(60)
        return None

    def cancel(self) -> None:
        self.cancel_calls += 1


def test_a_worker_stuck_in_a_frame_is_detached_not_destroyed(qtbot: Any) -> None:
    from app.gui import workers

    engine = _UnstoppableEngine()
    worker = workers.PreviewWorker(engine)  # type: ignore[arg-type]
    worker.submit(_frame())
    assert engine.started.wait(10)
    t0 = time.monotonic()
    ended = worker.stop(timeout_ms=200)
    assert ended is False and time.monotonic() - t0 < 5
    assert engine.cancel_calls == 1  # the frame was asked to stop
    assert workers.detached_threads() == ["preview"]
    del worker
    gc.collect()  # the worker goes; its running thread must not (the old code aborted here)
    engine.release.set()
    qtbot.waitUntil(lambda: not workers._DETACHED, timeout=10_000)  # dropped once finished
    assert workers.detached_threads() == []


def test_stopping_cancels_a_long_real_frame_at_its_next_step(monkeypatch: pytest.MonkeyPatch,
                                                             qtbot: Any) -> None:
    """A frame of 200 slow FISTA steps (10 s) ends at the next step when the worker stops."""
    from PySide6.QtCore import QThread

    from app.gui.preview_engine import PreviewEngine, PreviewSettings
    from app.gui.workers import PreviewWorker
    from recon.fista import Fista
    from recon.simulate import synthetic_psf

    steps: list[float] = []
    step = Fista.step

    def slow_step(self: Any) -> Any:
        if QThread.currentThread().objectName() == "preview":  # not another test's estimate
            steps.append(time.monotonic())
            time.sleep(0.05)
        return step(self)

    monkeypatch.setattr(Fista, "step", slow_step)
    psf = synthetic_psf((48, 64), n_points=20, seed=1)
    engine = PreviewEngine(psf, PreviewSettings(iters_per_frame=200, target_fps=0,
                                                tau_auto=False, dark=0.0))
    worker = PreviewWorker(engine)
    errors: list[str] = []
    worker.error.connect(errors.append)
    frame = _frame((np.random.default_rng(0).random((48, 64)) * 1000).astype(np.uint16))
    worker.submit(frame)
    qtbot.waitUntil(lambda: len(steps) >= 2, timeout=20_000)
    t0 = time.monotonic()
    assert worker.stop(timeout_ms=5_000) is True
    assert time.monotonic() - t0 < 2.0
    assert len(steps) < 100 and engine.cancelled
    qtbot.wait(50)
    assert errors == []  # a cancelled frame is not an error to show


def test_a_new_worker_on_a_stopped_engine_previews_again(qtbot: Any) -> None:
    """stop() cancels the engine it shares with the window; a worker started on it later
    (a restart of the preview) showed nothing and said nothing."""
    from app.gui.preview_engine import PreviewEngine, PreviewSettings
    from app.gui.workers import PreviewWorker
    from recon.simulate import synthetic_psf

    engine = PreviewEngine(synthetic_psf((48, 64), n_points=20, seed=1),
                           PreviewSettings(iters_per_frame=3, tau_auto=False, dark=0.0))
    first = PreviewWorker(engine)
    assert first.stop(timeout_ms=5_000) is True and engine.cancelled
    second = PreviewWorker(engine)
    results: list[Any] = []
    second.result.connect(results.append)
    second.submit(_frame((np.random.default_rng(0).random((48, 64)) * 1000).astype(np.uint16)))
    qtbot.waitUntil(lambda: bool(results), timeout=20_000)
    assert second.stop(timeout_ms=5_000) is True


def test_the_process_exits_cleanly_with_a_detached_frame_still_running(tmp_path: Path) -> None:
    """The app closing while a frame runs on past the stop timeout: the process waits for the
    thread at exit instead of aborting ("QThread: Destroyed while thread 'preview' is still
    running", SIGABRT)."""
    script = tmp_path / "close_during_frame.py"
    script.write_text(textwrap.dedent("""
        import threading, time
        from types import SimpleNamespace

        import numpy as np
        from PySide6.QtCore import QCoreApplication

        from app.gui.workers import PreviewWorker

        app = QCoreApplication([])
        started = threading.Event()

        class Engine:
            def process(self, pixels, **meta):
                started.set()
                time.sleep(2.0)  # one long computation that cannot be cut short

            def cancel(self):
                pass

        worker = PreviewWorker(Engine())
        px = np.zeros((4, 4), np.uint16)
        worker.submit(SimpleNamespace(pixels=px, frame_id=0, timestamp=0.0, binning=1,
                                      timing=None, sensor=(4, 4),
                                      roi=SimpleNamespace(x=0, y=0, width=4, height=4)))
        assert started.wait(30)
        print("stopped:", worker.stop(timeout_ms=100), flush=True)
        del worker
        print("leaving", flush=True)
    """))
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                          timeout=120, cwd=str(Path(__file__).resolve().parents[2]))
    assert "stopped: False" in proc.stdout and "leaving" in proc.stdout, proc.stderr
    assert "Destroyed while thread" not in proc.stderr
    assert proc.returncode == 0, (proc.returncode, proc.stderr[-2000:])
