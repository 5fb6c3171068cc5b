"""Helpers shared by the CLI subcommands: loading inputs, progress bars, parsing values."""

from __future__ import annotations

import re
import sys
import time
from pathlib import Path
from typing import Any


def parse_dark(value: str | None) -> Any:
    """``--dark``: a number, 'auto', or a dark-frame file."""
    if value is None:
        return None
    if value == "auto":
        return "auto"
    try:
        return float(value)
    except ValueError:
        pass
    p = Path(value)
    if not p.exists():
        raise FileNotFoundError(f"--dark {value}: neither a number, 'auto', nor an existing file")
    return p


def parse_field(value: str | None, sensor: tuple[int, int]) -> tuple[int, int] | None:
    """``--field``: 'sensor' (default), 'full' (2H x 2W) or HxW."""
    if value in (None, "sensor"):
        return None
    if value == "full":
        return (2 * sensor[0], 2 * sensor[1])
    m = re.fullmatch(r"(\d+)x(\d+)", value or "")
    if not m:
        raise ValueError(f"--field must be 'sensor', 'full' or HxW, got {value!r}")
    return (int(m.group(1)), int(m.group(2)))


def parse_duration_us(value: str) -> float:
    """'10ms', '250us', '0.5s' or a bare number of microseconds."""
    m = re.fullmatch(r"\s*([0-9.eE+-]+)\s*(us|µs|ms|s)?\s*", value)
    if not m:
        raise ValueError(f"cannot read {value!r} as a duration (examples: 10ms, 250us, 0.5s)")
    scale = {"us": 1.0, "µs": 1.0, "ms": 1e3, "s": 1e6, None: 1.0}[m.group(2)]
    return float(m.group(1)) * scale


class ProgressBar:
    """A one-line progress bar on stderr when it is a terminal; silent otherwise."""

    def __init__(self, total: int, label: str, enabled: bool | None = None) -> None:
        self.total = max(int(total), 1)
        self.label = label
        self.enabled = sys.stderr.isatty() if enabled is None else enabled
        self._last = 0.0

    def update(self, n: int, extra: str = "") -> None:
        """Redraw at most 10 times a second (always at the end)."""
        if not self.enabled:
            return
        now = time.monotonic()
        if n < self.total and now - self._last < 0.1:
            return
        self._last = now
        frac = min(n / self.total, 1.0)
        bar = "#" * int(30 * frac)
        sys.stderr.write(f"\r{self.label} [{bar:<30}] {n}/{self.total} {extra}   ")
        sys.stderr.flush()

    def close(self) -> None:
        """End the line."""
        if self.enabled:
            sys.stderr.write("\n")
            sys.stderr.flush()


def load_array(path: str, what: str, key: str | None = None) -> Any:
    """Load a raw array (npy, npz, tif, png, mat) with a message naming ``what``."""
    import numpy as np

    from recon.io import load_image

    try:
        return np.asarray(load_image(path, key=key))
    except FileNotFoundError as exc:
        raise FileNotFoundError(f"{what} file not found: {path}") from exc
