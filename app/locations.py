"""Where the app writes when the user names no folder (no Qt here: the CLI uses it too).

Nothing lands in the working folder or straight in the home folder: defaults go under the
user's data folder, ``$LENSLESSCAM_DATA_DIR`` or ``$XDG_DATA_HOME/lenslesscam`` (default
``~/.local/share/lenslesscam``), and every command that uses a default prints where it wrote.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["data_dir", "default_demo_dir", "default_jobs_dir", "default_snaps_dir"]


def data_dir() -> Path:
    """The user's lenslesscam data folder (not created here)."""
    env = os.environ.get("LENSLESSCAM_DATA_DIR")
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "lenslesscam"


def default_demo_dir() -> Path:
    """``lenslesscam demo`` writes here unless ``--out`` is given."""
    return data_dir() / "demo"


def default_snaps_dir() -> Path:
    """Snapshots go here unless the user chose a folder."""
    return data_dir() / "snaps"


def default_jobs_dir() -> Path:
    """Where UDN jobs go unless the user chose another folder.

    ``$LENSLESSCAM_JOBS_DIR``, else the data folder's ``jobs`` (it ignored
    ``$LENSLESSCAM_DATA_DIR``, which moved the demo and the snapshots but not the jobs).
    """
    env = os.environ.get("LENSLESSCAM_JOBS_DIR")
    if env:
        return Path(env).expanduser()
    return data_dir() / "jobs"
