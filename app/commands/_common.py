"""Helpers shared by the CLI subcommands: loading inputs, progress bars, parsing values."""

from __future__ import annotations

import contextlib
import re
import sys
from pathlib import Path
from typing import Any


def parse_dark(value: str | None, option: str = "--dark") -> Any:
    """``--dark`` (or ``option``): a finite number >= 0, 'auto', or a dark-frame file."""
    import math

    if value is None:
        return None
    if value == "auto":
        return "auto"
    try:
        level = float(value)
    except ValueError:
        pass
    else:
        if not (math.isfinite(level) and level >= 0):
            raise ValueError(f"{option} {value}: a dark level must be a finite number >= 0 "
                             "(the sensor's black offset)")
        return level
    p = Path(value)
    if not p.exists():
        raise FileNotFoundError(f"{option} {value}: neither a number, 'auto', nor an existing "
                                "file")
    return p


def parse_duration_us(value: str) -> float:
    """'10ms', '250us', '0.5s' or a bare number of microseconds."""
    m = re.fullmatch(r"\s*([0-9.eE+-]+)\s*(us|µs|ms|s)?\s*", value)
    if not m:
        raise ValueError(f"cannot read {value!r} as a duration (examples: 10ms, 250us, 0.5s)")
    scale = {"us": 1.0, "µs": 1.0, "ms": 1e3, "s": 1e6, None: 1.0}[m.group(2)]
    return float(m.group(1)) * scale


class ProgressBar:
    """A terminal progress bar on stderr (tqdm) when it is a terminal; silent otherwise.

    The one progress bar of the command line (recon, plan, jobs, calibrate; app.batch uses
    tqdm too): ``update(n, extra)`` sets the absolute position and a postfix text.
    """

    def __init__(self, total: int, label: str, enabled: bool | None = None) -> None:
        from tqdm import tqdm

        self.total = max(int(total), 1)
        self.label = label
        self.enabled = sys.stderr.isatty() if enabled is None else enabled
        self._bar = tqdm(total=self.total, desc=label, file=sys.stderr, mininterval=0.1,
                         disable=not self.enabled, dynamic_ncols=True, leave=True)

    def update(self, n: int, extra: str = "") -> None:
        """Move to ``n`` of ``total`` (tqdm redraws at most 10 times a second)."""
        if not self.enabled:
            return
        n = min(int(n), self.total)
        if extra:
            self._bar.set_postfix_str(extra, refresh=False)
        self._bar.update(n - self._bar.n)

    def close(self) -> None:
        """End the line."""
        self._bar.close()


def fit_command_threads(args: Any, scene_shape: tuple[int, ...]) -> None:
    """Fit the thread policy's choice to the built problem, kept in ``args.thread_choice``.

    See :func:`recon.threads.fit_threads`; commands report ``args.thread_choice``.
    """
    from recon.threads import fit_threads

    fitted = fit_threads(scene_shape)
    if fitted is not None:
        args.thread_choice = fitted


class TerminateAsInterrupt:
    """SIGTERM and SIGHUP raise KeyboardInterrupt, as Ctrl-C does (main thread only).

    ``kill``, ``timeout`` or a closed terminal then stop a command through its Ctrl-C path:
    ``calibrate`` switches the light off and stops its firmware; ``batch run`` cancels cleanly
    (exit 130, UDN jobs stop with a final checkpoint), where Ray's handler, which ``ray.init``
    installs, dumped a stack and aborted (exit 134) and left the state "running" (the batch
    calls :meth:`install` again after ``ray.init``). A signal ignored when first installed
    (SIGHUP under ``nohup``) stays ignored, also after ``ray.init``. A context manager too:
    installed within the block, restored after it.
    """

    SIGNALS = ("SIGTERM", "SIGHUP")

    def __init__(self) -> None:
        self.saved: dict[int, Any] = {}

    @staticmethod
    def _interrupt(signum: int, _frame: Any) -> None:
        raise KeyboardInterrupt(f"signal {signum}")

    def install(self) -> None:
        import signal
        import threading

        if threading.current_thread() is not threading.main_thread():
            return
        for name in self.SIGNALS:
            sig = getattr(signal, name, None)
            if sig is None:
                continue
            original = self.saved.get(sig, signal.getsignal(sig))
            # a signal the process was started to ignore (`nohup` ignores SIGHUP, so a batch
            # outlives its terminal) stays ignored: that is what the user asked for
            previous = signal.signal(sig, signal.SIG_IGN if original is signal.SIG_IGN
                                     else self._interrupt)
            self.saved.setdefault(sig, previous)

    def restore(self) -> None:
        import signal

        for sig, handler in self.saved.items():
            with contextlib.suppress(ValueError, TypeError):
                signal.signal(sig, signal.SIG_DFL if handler is None else handler)
        self.saved.clear()

    def __enter__(self) -> TerminateAsInterrupt:
        self.install()
        return self

    def __exit__(self, *_exc: object) -> None:
        self.restore()
