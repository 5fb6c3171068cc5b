"""``lenslesscam app``: the desktop app (PySide6 + pyqtgraph; imported only when it starts)."""

from __future__ import annotations

import argparse
from typing import Any


def register(sub: Any) -> None:
    """Add ``app``."""
    p = sub.add_parser(
        "app",
        help="desktop app: live view, live reconstruction preview, calibration, UDN jobs",
        description="Start the desktop app. With no hardware it opens on the simulated camera "
        "and point source with a bundled scene.",
    )
    p.add_argument("--camera", default=None,
                   help="camera spec to open (sim, genicam:N, v4l2:N); default: the last one")
    p.add_argument("--light-port", default=None,
                   help="point-source port ('sim': simulated on a PTY; '': none)")
    p.add_argument("--jobs-dir", default=None, help="folder of UDN jobs")
    p.add_argument("--reset-settings", action="store_true", help="start from default settings")
    p.add_argument("--screenshot", default=None, help=argparse.SUPPRESS)
    p.add_argument("--screenshot-after", type=float, default=6.0, help=argparse.SUPPRESS)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Start the GUI event loop."""
    try:
        from app.gui import run_app
    except ImportError as exc:  # pragma: no cover - depends on the installation
        raise OSError(f"the app needs the 'gui' extra (PySide6, pyqtgraph): {exc}") from exc
    return run_app(camera=args.camera, light_port=args.light_port, jobs_dir=args.jobs_dir,
                   screenshot=args.screenshot, screenshot_after_s=args.screenshot_after,
                   reset_settings=args.reset_settings)
