"""The desktop app (PySide6 + pyqtgraph): live view, live preview, calibration, UDN jobs.

Importing this package does not import Qt; :func:`run_app` does. SIGTERM, SIGINT and SIGHUP
close the window cleanly (devices closed, the simulated point-source process stopped,
settings saved), as the window's close button does. The Qt-free parts
(:mod:`app.gui.preview_engine`, :mod:`app.gui.devices`, :mod:`app.gui.settings`,
:mod:`app.gui.jobs_core`, :mod:`app.gui.snapshots`) are usable without a display.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

__all__ = ["close_on_signals", "run_app"]

_log = logging.getLogger(__name__)


def run_app(
    argv: Sequence[str] | None = None,
    *,
    camera: str | None = None,
    light_port: str | None = None,
    jobs_dir: str | Path | None = None,
    screenshot: str | Path | None = None,
    screenshot_after_s: float = 6.0,
    reset_settings: bool = False,
) -> int:
    """Start the app and run the Qt event loop until the window closes; returns the exit code.

    ``camera`` / ``light_port`` override the saved choices (``light_port=""``: no source).
    ``screenshot``: save a PNG of the window after ``screenshot_after_s`` seconds and quit.
    """
    import sys

    from PySide6.QtCore import QTimer
    from PySide6.QtWidgets import QApplication

    from app.gui.image_view import configure_pyqtgraph
    from app.gui.main_window import MainWindow
    from app.gui.settings import AppSettings, load_settings

    app = QApplication.instance() or QApplication(list(argv or sys.argv[:1]))
    configure_pyqtgraph()
    settings = AppSettings() if reset_settings else load_settings()
    if camera is not None:
        settings.camera = camera
    if light_port is not None:
        settings.light_port = light_port
        settings.connect_light = bool(light_port)
    if jobs_dir is not None:
        settings.jobs_dir = str(jobs_dir)
    win = MainWindow(settings, save_settings_on_close=screenshot is None)
    stop_signals = close_on_signals(win)
    win.show()
    if screenshot is not None:
        out = Path(screenshot)

        def shoot() -> None:
            out.parent.mkdir(parents=True, exist_ok=True)
            win.grab().save(str(out))
            win.close()

        QTimer.singleShot(int(screenshot_after_s * 1000), shoot)
    try:
        return int(app.exec())
    finally:
        win.close()  # every exit path stops the devices and the child processes
        stop_signals()


def close_on_signals(win: Any) -> Callable[[], None]:
    """Close ``win`` (and quit) on SIGTERM, SIGINT or SIGHUP; returns a function that undoes it.

    Python runs signal handlers only between bytecodes, never while Qt's event loop waits in C;
    the signal is therefore written to a socket (:func:`signal.set_wakeup_fd`) that a
    ``QSocketNotifier`` watches, and the window is closed from the event loop.
    """
    import signal
    import socket

    from PySide6.QtCore import QSocketNotifier
    from PySide6.QtWidgets import QApplication

    rsock, wsock = socket.socketpair()
    rsock.setblocking(False)
    wsock.setblocking(False)
    previous_fd = signal.set_wakeup_fd(wsock.fileno())
    signals = [signal.SIGTERM, signal.SIGINT, signal.SIGHUP]
    previous = {sig: signal.signal(sig, lambda _n, _f: None) for sig in signals}
    notifier = QSocketNotifier(rsock.fileno(), QSocketNotifier.Type.Read)

    def on_signal() -> None:
        try:
            got = rsock.recv(64)
        except OSError:
            return
        names = ", ".join(signal.Signals(b).name for b in got if b in set(signals))
        _log.warning("%s: closing the app", names or "signal")
        win.close()
        app = QApplication.instance()
        if app is not None:
            app.quit()

    notifier.activated.connect(on_signal)

    def undo() -> None:
        notifier.setEnabled(False)
        signal.set_wakeup_fd(previous_fd)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        rsock.close()
        wsock.close()

    return undo
