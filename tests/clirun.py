"""Run the ``lenslesscam`` command line in-process for a test: the one helper of the tests."""

from __future__ import annotations

from typing import Any


def run_cli(capsys: Any, *argv: Any) -> tuple[int, str, str]:
    """``(exit code, stdout, stderr)`` of ``lenslesscam ARGV`` (arguments made strings)."""
    from app.cli import main

    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err
