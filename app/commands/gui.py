"""``lenslesscam app``: the desktop app (PySide6 + pyqtgraph; imported only when it starts).

Before Qt is loaded, the X11 libraries Qt's ``xcb`` platform plugin needs and a fresh Debian or
Ubuntu machine lacks are looked up; when one is missing the command prints the one ``apt-get``
line that installs them and exits with status 2, instead of Qt aborting the process; with no
display at all it says so (and how to run it anyway) the same way.
"""

from __future__ import annotations

import argparse
import ctypes.util
import os
import sys
from typing import Any

from app.commands._options import NONNEG

#: Shared libraries the Qt ``xcb`` plugin loads -> the Debian/Ubuntu package that has them.
XCB_LIBRARIES = {
    "xcb-cursor": "libxcb-cursor0",
    "xcb-icccm": "libxcb-icccm4",
    "xcb-keysyms": "libxcb-keysyms1",
}
#: The command that installs them.
APT_COMMAND = "sudo apt-get install -y " + " ".join(XCB_LIBRARIES.values())


def register(sub: Any) -> None:
    """Add ``app``."""
    p = sub.add_parser(
        "app",
        help="desktop app: live view, live reconstruction preview, calibration, UDN jobs",
        description="Start the desktop app. With no hardware it opens on the simulated camera "
        "and point source with a bundled scene. On Linux it needs the X11 libraries of "
        f"Qt's xcb plugin: {APT_COMMAND}",
    )
    p.add_argument("--camera", default=None,
                   help="camera spec to open (sim, genicam:N, v4l2:N); default: the last one")
    p.add_argument("--light-port", default=None,
                   help="point-source port ('sim': simulated on a PTY; '': none)")
    p.add_argument("--jobs-dir", default=None, help="folder of UDN jobs")
    p.add_argument("--reset-settings", action="store_true", help="start from default settings")
    p.add_argument("--screenshot", default=None, help=argparse.SUPPRESS)
    p.add_argument("--screenshot-after", type=NONNEG, default=6.0, help=argparse.SUPPRESS)
    p.set_defaults(func=run)


def uses_xcb() -> bool:
    """Whether Qt will use its X11 (xcb) platform plugin: Linux, no other platform chosen."""
    if not sys.platform.startswith("linux"):
        return False
    platform = os.environ.get("QT_QPA_PLATFORM", "").split(":")[0].strip()
    return platform in ("", "xcb")


def missing_xcb_packages() -> list[str]:
    """Packages of :data:`XCB_LIBRARIES` whose library the dynamic linker cannot find."""
    return [pkg for lib, pkg in XCB_LIBRARIES.items() if ctypes.util.find_library(lib) is None]


def run(args: argparse.Namespace) -> int:
    """Start the GUI event loop."""
    if uses_xcb():
        missing = missing_xcb_packages()
        if missing:
            print(f"lenslesscam app: Qt's X11 plugin needs {', '.join(missing)}, which this "
                  f"machine lacks. Install them with:\n    {APT_COMMAND}\n(or set "
                  "QT_QPA_PLATFORM=offscreen to run without a screen)", file=sys.stderr)
            return 2
        if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
            print("lenslesscam app: no display (DISPLAY is not set): start it on a desktop, "
                  "under xvfb-run, or with QT_QPA_PLATFORM=offscreen", file=sys.stderr)
            return 2
    try:
        from app.gui import run_app
    except ImportError as exc:  # pragma: no cover - depends on the installation
        raise OSError(f"the app needs the 'gui' extra (PySide6, pyqtgraph): {exc}") from exc
    return run_app(camera=args.camera, light_port=args.light_port, jobs_dir=args.jobs_dir,
                   screenshot=args.screenshot, screenshot_after_s=args.screenshot_after,
                   reset_settings=args.reset_settings)
