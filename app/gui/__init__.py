"""The desktop app (PySide6 + pyqtgraph): live view, live preview, calibration, UDN jobs.

Importing this package does not import Qt; :func:`run_app` does. The Qt-free parts
(:mod:`app.gui.preview_engine`, :mod:`app.gui.bench`, :mod:`app.gui.settings`,
:mod:`app.gui.jobs_core`, :mod:`app.gui.snapshots`) are usable without a display.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

__all__ = ["run_app"]


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
    win.show()
    if screenshot is not None:
        out = Path(screenshot)

        def shoot() -> None:
            out.parent.mkdir(parents=True, exist_ok=True)
            win.grab().save(str(out))
            win.close()

        QTimer.singleShot(int(screenshot_after_s * 1000), shoot)
    return int(app.exec())
