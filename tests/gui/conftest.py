"""GUI test fixtures: offscreen Qt, a private config folder, the app on the simulated bench."""

from __future__ import annotations

import os

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")  # before anything imports Qt

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest


@pytest.fixture(autouse=True)
def _private_dirs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Settings and jobs of each test live in its own temporary folder."""
    monkeypatch.setenv("LENSLESSCAM_CONFIG_DIR", str(tmp_path / "config"))
    monkeypatch.setenv("LENSLESSCAM_JOBS_DIR", str(tmp_path / "jobs"))


@pytest.fixture
def make_window(qtbot: Any, tmp_path: Path) -> Iterator[Any]:
    """Factory: a shown MainWindow on the simulated bench (closed at teardown)."""
    from app.gui.main_window import MainWindow
    from app.gui.settings import AppSettings

    windows: list[Any] = []

    def make(settings: AppSettings | None = None, **kwargs: Any) -> Any:
        # 10 frames/s (the app's default is 20): a smaller workload, frames still arrive fast
        s = settings or AppSettings(frame_rate_hz=10.0)
        s.save_dir = s.save_dir or str(tmp_path / "snaps")
        s.jobs_dir = s.jobs_dir or str(tmp_path / "jobs")
        kwargs.setdefault("reconnect_interval_ms", 300)
        kwargs.setdefault("light_check_interval_ms", 300)
        kwargs.setdefault("jobs_poll_ms", 250)
        w = MainWindow(s, **kwargs)
        qtbot.addWidget(w)
        w.show()
        windows.append(w)
        return w

    yield make
    for w in windows:
        if w.isVisible():
            w.close()


@pytest.fixture
def live_window(make_window: Any, qtbot: Any) -> Any:
    """A window whose simulated camera is live and has shown a few frames (no point source:
    tests that need one use :func:`bench_window`)."""
    from app.gui.settings import AppSettings

    w = make_window(AppSettings(frame_rate_hz=10.0, connect_light=False))
    qtbot.waitUntil(lambda: w.camera_state == "live", timeout=20_000)
    qtbot.waitUntil(lambda: w.frames_shown >= 3, timeout=10_000)
    return w


@pytest.fixture
def bench_window(make_window: Any, qtbot: Any) -> Any:
    """The whole simulated bench: the camera live and the point source (firmware on a PTY)."""
    w = make_window()
    qtbot.waitUntil(lambda: w.camera_state == "live", timeout=20_000)
    qtbot.waitUntil(lambda: w.frames_shown >= 3, timeout=10_000)
    qtbot.waitUntil(lambda: w.light_state == "connected", timeout=15_000)
    return w


@pytest.fixture(autouse=True)
def _collect_in_the_gui_thread() -> Iterator[None]:
    """The app collects garbage on a GUI-thread timer only (``configure_pyqtgraph`` turns
    automatic collection off for the process); the event loop does not run between tests, so
    collect here, in the GUI thread, after each one, and give the tests that follow (not GUI
    tests) automatic collection back. The next window turns it off again."""
    yield
    import gc

    gc.collect()
    gc.enable()
