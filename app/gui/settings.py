"""App settings that persist between sessions: one JSON file in the user's config folder.

The file is ``<config dir>/app-settings.json`` where the config dir is ``$LENSLESSCAM_CONFIG_DIR``
if set, else ``$XDG_CONFIG_HOME/lenslesscam`` (``~/.config/lenslesscam``). It is written
atomically (:func:`recon.atomic.atomic_write_json`) and carries ``format`` and
``format_version``; an unreadable or foreign file is set aside (renamed ``.bad``) and the
defaults are used, so a broken settings file never stops the app from starting.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

from app.locations import default_jobs_dir
from recon.formats import whole_version

__all__ = [
    "SETTINGS_FORMAT",
    "SETTINGS_VERSION",
    "AppSettings",
    "config_dir",
    "default_jobs_dir",
    "load_settings",
    "save_settings",
    "settings_path",
]

_log = logging.getLogger(__name__)

SETTINGS_FORMAT = "lenslesscam.app_settings"
SETTINGS_VERSION = 1


def config_dir() -> Path:
    """The user's lenslesscam config folder (not created)."""
    env = os.environ.get("LENSLESSCAM_CONFIG_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "lenslesscam"


def settings_path() -> Path:
    """Path of the settings file."""
    return config_dir() / "app-settings.json"


@dataclass
class AppSettings:
    """Everything the app remembers. Unknown keys in the file are ignored."""

    camera: str = "sim"
    show_demo_cameras: bool = False
    light_port: str = "sim"
    connect_light: bool = True
    #: the level the point source is switched on at (the Light row's intensity)
    light_intensity: float = 1.0
    sim_scene: str = "im65"
    exposure_us: float = 10_000.0
    gain: float = 1.0
    frame_rate_hz: float = 20.0
    shutter_mode: str = ""
    display_hz: float = 30.0
    show_roi: bool = False
    preview_enabled: bool = True
    preview: dict[str, Any] = field(default_factory=dict)
    psf_path: str = ""
    save_dir: str = ""
    jobs_dir: str = ""
    calibration_dir: str = ""
    window_geometry: str = ""
    window_state: str = ""
    #: the new-job dialog's settings of the last job queued (offered by the next dialog)
    last_job: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON with format keys."""
        return {"format": SETTINGS_FORMAT, "format_version": SETTINGS_VERSION, **asdict(self)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> AppSettings:
        """Settings from a dict; keys of the wrong type keep their defaults."""
        out = cls()
        for f in fields(cls):
            if f.name not in d:
                continue
            default = getattr(out, f.name)
            value = d[f.name]
            if isinstance(default, float) and isinstance(value, int | float):
                value = float(value)
            if type(value) is not type(default):
                _log.warning("settings: ignoring %s=%r (expected %s)", f.name, value,
                             type(default).__name__)
                continue
            if f.name == "sim_scene" and value not in _sim_scenes():
                # a scene that no longer exists would leave the simulated camera unable to
                # connect, with its scene menu disabled while disconnected
                _log.warning("settings: ignoring sim_scene=%r (not a bundled scene)", value)
                continue
            setattr(out, f.name, value)
        return out


def _sim_scenes() -> tuple[str, ...]:
    from app.gui.devices import SCENES

    return tuple(SCENES)


def load_settings(path: Path | None = None) -> AppSettings:
    """Read the settings (defaults when the file is missing or unreadable)."""
    p = path or settings_path()
    try:
        raw = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return AppSettings()
    except (OSError, ValueError, RecursionError) as exc:
        _log.warning("settings file %s is unreadable (%s); using defaults", p, exc)
        with contextlib.suppress(OSError):
            p.replace(p.with_suffix(".json.bad"))
        return AppSettings()
    if not isinstance(raw, dict) or raw.get("format") != SETTINGS_FORMAT:
        _log.warning("%s is not a lenslesscam settings file; set aside as %s, using defaults",
                     p, p.with_suffix(".json.bad").name)
        with contextlib.suppress(OSError):  # the save at exit would write over it
            p.replace(p.with_suffix(".json.bad"))
        return AppSettings()
    raw_version = raw.get("format_version", 0)
    version = whole_version(raw_version)  # 1.0, as some JSON writers put 1, is version 1
    if version is None:
        _log.warning("settings file %s has format_version %r, not a whole number; using "
                     "defaults", p, raw_version)
        with contextlib.suppress(OSError):
            p.replace(p.with_suffix(".json.bad"))
        return AppSettings()
    if version > SETTINGS_VERSION:
        kept = p.with_suffix(f".json.v{version}")
        _log.warning("%s was written by a newer version (format %d); kept as %s, this version "
                     "starts from defaults", p, version, kept.name)
        with contextlib.suppress(OSError):  # the save at exit would write over the newer file
            p.replace(kept)
        return AppSettings()
    return AppSettings.from_dict(raw)


def save_settings(settings: AppSettings, path: Path | None = None) -> Path:
    """Write the settings atomically; returns the path."""
    from recon.atomic import atomic_write_json

    return atomic_write_json(path or settings_path(), settings.to_dict())
