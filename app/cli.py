"""The ``lenslesscam`` command line.

Each subcommand lives in its own module under ``app/commands`` with a
``register(subparsers)`` function that adds its parser and sets ``func`` (a callable taking the
parsed namespace and returning an exit code). Heavy libraries (torch, Qt) are imported inside
those functions, never at module import, so ``lenslesscam --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

#: Subcommand modules, in the order ``--help`` lists them.
COMMAND_MODULES: tuple[str, ...] = (
    "app.commands.demo",
    "app.commands.simulate",
    "app.commands.recon",
    "app.commands.plan",
    "app.commands.trade",
    "app.commands.jobs",
    "app.commands.metrics",
    "app.commands.bench",
    "app.commands.devices",
    "app.commands.calibrate",
    "app.commands.gui",
)


class CliError(Exception):
    """A user-facing error: printed as one line, exit code 2, no traceback."""


def build_parser() -> argparse.ArgumentParser:
    """Parser with every registered subcommand."""
    parser = argparse.ArgumentParser(
        prog="lenslesscam",
        description="Lensless compressive camera: capture, calibrate, reconstruct.",
    )
    parser.add_argument("--version", action="store_true", help="print the version and exit")
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
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("lenslesscam: interrupted", file=sys.stderr)
        return 130
    except (CliError, ValueError, FileNotFoundError, OSError) as exc:
        # Errors from the library carry a message naming the problem; show it without a trace.
        print(f"lenslesscam {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
