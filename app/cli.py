"""The ``lenslesscam`` command line.

Each subcommand lives in its own module under ``app/commands`` with a
``register(subparsers)`` function that adds its parser and sets ``func`` (a callable taking the
parsed namespace and returning an exit code). Heavy libraries (torch, Qt) are imported inside
those functions, never at module import, so ``lenslesscam --help`` stays fast.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import os
import re
import sys
import warnings
from collections.abc import Sequence
from typing import Any, NoReturn

from app.commands._options import NONNEG_INT

#: Subcommand modules, in the order ``--help`` lists them.
COMMAND_MODULES: tuple[str, ...] = (
    "app.commands.demo",
    "app.commands.simulate",
    "app.commands.recon",
    "app.commands.plan",
    "app.commands.trade",
    "app.commands.jobs",
    "app.commands.batch",
    "app.commands.metrics",
    "app.commands.bench",
    "app.commands.devices",
    "app.commands.calibrate",
    "app.commands.gui",
)


#: Commands that never run torch: they skip the thread policy (and torch's import time).
NO_TORCH_COMMANDS = frozenset({"devices", "snap", "metrics"})


class CliError(Exception):
    """A user-facing error: printed as one line, exit code 2, no traceback."""


class Parser(argparse.ArgumentParser):
    """argparse with a one-line error: the problem and where the usage is (not the usage).

    A value such as ``-1e30`` or ``-5s`` is read as a negative number, as ``-5`` and
    ``-0.5`` are (argparse's own rule has no exponent and no unit, so ``--dark -1e30`` and
    ``--budget -5s`` were "expected one argument"): the option's own check then says why.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(
            r"^-(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?([a-zA-Zµ]{1,3})?$")

    def error(self, message: str) -> NoReturn:
        """Exit 2 with one line: the problem and where the usage is."""
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")

    def parse_known_args(self, args: Any = None, namespace: Any = None) -> Any:
        """Also note in the namespace the innermost (sub)command's parser that read it."""
        ns, extras = super().parse_known_args(args, namespace)
        if not hasattr(ns, _INNERMOST):  # a subcommand's parser ran inside this one and set it
            setattr(ns, _INNERMOST, (self, list(extras)))
        return ns, extras

    def parse_args(self, args: Any = None, namespace: Any = None) -> Any:  # type: ignore[override]
        """An unknown option is named with its subcommand's help and the closest option.

        argparse reports it from the top parser ("see 'lenslesscam --help'"), whose help does
        not list the options of ``recon udn``.
        """
        import difflib

        ns, extras = self.parse_known_args(args, namespace)
        inner, theirs = vars(ns).pop(_INNERMOST, (self, extras))
        if extras:
            mine = list(extras)
            for e in theirs:  # what the subcommand left is its own; the rest came before it
                if e in mine:
                    mine.remove(e)
            if mine:
                inner, extras = self, mine
            message = f"unrecognized arguments: {' '.join(extras)}"
            options = [o for o in inner._option_string_actions if o.startswith("--")]
            close = [m for e in extras if e.startswith("--")
                     for m in difflib.get_close_matches(e.split("=")[0], options, n=1, cutoff=0.75)]
            if close:
                message += f"; did you mean {', '.join(dict.fromkeys(close))}?"
            inner.error(message)
        return ns


#: namespace attribute of the innermost parser (removed before the namespace is returned)
_INNERMOST = "_lenslesscam_innermost_parser"


def build_parser() -> argparse.ArgumentParser:
    """Parser with every registered subcommand (their parsers are the same class)."""
    parser = Parser(
        prog="lenslesscam",
        description="Lensless compressive camera: capture, calibrate, reconstruct.",
    )
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    parser.add_argument(
        "--threads", dest="global_threads", type=NONNEG_INT, default=None, metavar="N",
        help="torch CPU threads for this command (default: chosen from the free cores and the "
        "load, recon.threads; 0 = choose)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.version:
        from recon.formats import software_version

        print(software_version())
        return 0
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    saved_show = warnings.showwarning
    warnings.showwarning = _show_warning
    log_handler = _log_warnings_as_lines()
    try:
        needs_torch = args.command not in NO_TORCH_COMMANDS and not getattr(args, "no_torch", False)
        if needs_torch or args.global_threads is not None:
            from recon.threads import apply_threads

            # an OMP_NUM_THREADS that is not a number is a one-line error too
            args.thread_choice = apply_threads(args.global_threads)
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("lenslesscam: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError as exc:
        if not _stdout_gone():  # a pipe of the work itself (a worker, a subprocess) broke
            print(f"lenslesscam {args.command}: error: {one_line(exc)}", file=sys.stderr)
            return 2
        # the reader of our output went away (``lenslesscam metrics ... | head``): not an error
        # of ours; stop quietly, as a shell tool does, and keep Python from printing another
        with contextlib.suppress(OSError, ValueError):
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        return 141
    except FloatingPointError as exc:
        # recon.stepwise.NumericalError: a solver met NaN/inf; its message says where
        print(f"lenslesscam {args.command}: error: {one_line(exc)}", file=sys.stderr)
        return 2
    except MemoryError as exc:
        # recon.memory.ProblemTooLarge (the estimate says it will not fit) or a real failure
        print(f"lenslesscam {args.command}: error: {one_line(exc) or 'out of memory'}",
              file=sys.stderr)
        return 2
    except RuntimeError as exc:
        if _device_error(exc):  # a camera or point source refused or failed: its message
            print(f"lenslesscam {args.command}: error: {one_line(exc)}", file=sys.stderr)
            return 2
        if not is_allocation_failure(exc):
            raise
        print(f"lenslesscam {args.command}: error: out of memory: {one_line(exc)} (the "
              "estimate said it would fit; downsample, use a smaller --field or float32)",
              file=sys.stderr)
        return 2
    except (CliError, ValueError, FileNotFoundError, OSError) as exc:
        # Errors from the library carry a message naming the problem; show it without a trace.
        print(f"lenslesscam {args.command}: error: {exc}", file=sys.stderr)
        return 2
    finally:
        warnings.showwarning = saved_show
        for name in _OUR_LOGGERS:
            logging.getLogger(name).removeHandler(log_handler)


#: The packages whose log warnings a command prints (their records still propagate).
_OUR_LOGGERS = ("app", "benchmarks", "calibration", "drivers", "recon")


def _log_warnings_as_lines() -> logging.Handler:
    """Print our packages' log warnings as the command's warnings are printed: one line each.

    Without a handler Python printed them bare ("could not switch the point source off: ...",
    under the CLI's own "lenslesscam calibrate: error: ..." line), unlike every other line the
    command prints. Installed for the command's duration only.
    """
    handler = logging.StreamHandler(_StderrNow())
    handler.setLevel(logging.WARNING)
    handler.setFormatter(_OneLineFormatter())
    for name in _OUR_LOGGERS:
        logging.getLogger(name).addHandler(handler)
    return handler


class _StderrNow:
    """``sys.stderr`` as it is when written to (a test's capture replaces it)."""

    def write(self, text: str) -> int:
        return sys.stderr.write(text)

    def flush(self) -> None:
        sys.stderr.flush()


class _OneLineFormatter(logging.Formatter):
    """The record's first line, prefixed as a command's warnings are (no traceback)."""

    def format(self, record: logging.LogRecord) -> str:
        lines = record.getMessage().splitlines()
        return f"lenslesscam: warning: {lines[0] if lines else ''}"


def _device_error(exc: BaseException) -> bool:
    """Whether ``exc`` is a driver's error (a camera's or a point source's), said in one line.

    Every command that opens a device gets it (``calibrate`` printed a traceback for "cannot
    open v4l2 device" and "feature 'exposure' is not available"); the drivers are looked up
    only where the command imported them.
    """
    for module, name in (("drivers.camera", "CameraError"),
                         ("drivers.lightsource", "LightSourceError")):
        cls = getattr(sys.modules.get(module), name, None)
        if isinstance(cls, type) and isinstance(exc, cls):
            return True
    return False


def _stdout_gone() -> bool:
    """Whether standard output is a pipe whose reader has closed it."""
    import select

    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        return any(ev & select.POLLERR for _fd, ev in poller.poll(0))
    except (OSError, ValueError, AttributeError):  # not a real file (a test's capture)
        return False


def _show_warning(message: Warning | str, category: type[Warning], filename: str,
                  lineno: int, file: Any = None, line: str | None = None) -> None:
    """Warnings on the command line: one line each on stderr, no source location."""
    print(f"lenslesscam: warning: {message}", file=sys.stderr)


#: Texts of torch's allocation failures (CPU allocator, CUDA caching allocator, MPS).
ALLOCATION_FAILURE_TEXTS = ("not enough memory", "DefaultCPUAllocator", "out of memory",
                            "can't allocate memory")


def is_allocation_failure(exc: BaseException) -> bool:
    """True for torch's "could not allocate" errors (a RuntimeError, not a MemoryError)."""
    text = str(exc)
    return any(t.lower() in text.lower() for t in ALLOCATION_FAILURE_TEXTS)


def one_line(exc: BaseException) -> str:
    """The first non-empty line of an exception's message (the CLI's one-line errors)."""
    return next((ln.strip() for ln in str(exc).splitlines() if ln.strip()), "")


if __name__ == "__main__":
    sys.exit(main())
