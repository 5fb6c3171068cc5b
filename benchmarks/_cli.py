"""Command-line pieces shared by the benchmarks: option types and the check of their outputs.

Every benchmark that writes files adds ``--overwrite`` (:func:`app.commands._options.
add_overwrite_option`) and calls :func:`check_outputs` before any work: the files it will
write go through :func:`app.commands._options.check_command_outputs`, the rule of every other
writer command (an output that exists needs ``--overwrite``, an output may not be an input or
a folder, its folder must be writable). JSON-lines files a benchmark appends to (its resumable
cache, ``--results``) are not replaced, so they need no ``--overwrite``; they are checked to be
JSON lines (or absent) and writable, and no output may be one of them.
"""

from __future__ import annotations

import argparse
import json
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

__all__ = ["check_appended", "check_outputs", "hxw", "int_list", "read_jsonl"]

Paths = Mapping[str, "str | os.PathLike[str] | None"]


def hxw(min_side: int) -> Callable[[str], tuple[int, int]]:
    """A ``type=`` for a size ``HxW`` with both sides at least ``min_side`` (the commands' one
    parser, :func:`app.commands._options.parse_hw`)."""
    from app.commands._options import parse_hw

    what = f"HxW with both sides >= {min_side}"

    def parse(text: str) -> tuple[int, int]:
        try:
            return parse_hw(text, "the size", (min_side, min_side))
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc).removeprefix("the size ")) from None

    parse.__name__ = what
    return parse


def int_list(item: Callable[[str], int]) -> Callable[[str], list[int]]:
    """A ``type=`` for a comma-separated list of integers, each checked by ``item`` (one of
    the range-checked types of :mod:`app.commands._options`); at least one."""
    what = getattr(item, "range_text", "an integer")

    def parse(text: str) -> list[int]:
        parts = [s.strip() for s in text.split(",") if s.strip()]
        values = []
        for s in parts:
            try:
                v = item(s)
            except argparse.ArgumentTypeError:
                raise argparse.ArgumentTypeError(
                    f"must be a comma-separated list, each {what}, got {text!r}") from None
            if v in values:  # a repeat would be measured twice, as two (bogus) rows
                raise argparse.ArgumentTypeError(f"lists {v} twice, got {text!r}")
            values.append(v)
        if not values:
            raise argparse.ArgumentTypeError(f"must list at least one value, got {text!r}")
        return values

    parse.__name__ = f"list of {what}"
    return parse


def append_jsonl(path: str | os.PathLike[str] | None, row: dict[str, Any]) -> None:
    """Append ``row`` as one JSON line to ``path`` (nothing when None): a results file that
    keeps each finished case, so an interrupted benchmark keeps what it measured."""
    if path is None:
        return
    import json

    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps(row) + "\n")


def print_and_write(text: str, out: str | os.PathLike[str] | None) -> None:
    """Print a benchmark's Markdown and write it atomically to ``out`` (when given)."""
    print(text)
    if out:
        from recon.atomic import atomic_write_bytes

        atomic_write_bytes(out, text.encode())


def read_jsonl(path: str | os.PathLike[str], option: str) -> list[dict[str, Any]]:
    """The records of a JSON-lines file (none if it does not exist).

    A file that is not JSON lines (a binary file, another format) is a :class:`ValueError`
    with one line naming ``option``, the file and the first bad line.
    """
    p = Path(path)
    if p.is_dir():
        raise FileExistsError(f"{option} {p} is a folder: name a JSON-lines file")
    if not p.exists():
        return []
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ValueError(f"{option} {p} is not a JSON-lines file (it is not text): choose "
                         "another file") from None
    rows = []
    for i, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{option} {p} is not a JSON-lines file (line {i}: {exc.msg}): "
                             "choose another file") from None
        if not isinstance(row, dict):
            raise ValueError(f"{option} {p} is not a JSON-lines file of records (line {i} is "
                             f"a {type(row).__name__}): choose another file")
        rows.append(row)
    return rows


def check_appended(appended: Paths) -> None:
    """Refuse, before any work, JSON-lines files to append to that are not JSON lines (an
    existing file of another kind would be corrupted), are folders, or cannot be written."""
    from app.commands._options import check_output_folders

    for option, path in appended.items():
        if path is None:
            continue
        if str(path).strip() == "":
            raise FileExistsError(f"{option}: the path is empty: name a file")
        read_jsonl(path, option)
        try:
            check_output_folders([path])
        except PermissionError as exc:
            raise PermissionError(f"{option}: {exc}") from None


def check_outputs(args: argparse.Namespace, outputs: Paths, *, appended: Paths | None = None,
                  inputs: Paths | None = None) -> None:
    """Refuse, before any work, outputs that would lose data or cannot be written.

    ``outputs`` maps an option (``--out``) to the file it names (None: not given); they are
    checked by :func:`app.commands._options.check_command_outputs` (exist without
    ``--overwrite``, an input of the command, a folder, an unwritable folder). Two outputs may
    not be the same file, and none may be an ``appended`` JSON-lines file (checked by
    :func:`check_appended`) or one of the benchmark's own ``inputs`` (option -> path).
    """
    from app.commands._options import check_command_outputs
    from recon.atomic import check_outputs as check_atomic

    named = {k: v for k, v in outputs.items() if v is not None}
    seen: dict[str, str] = {}
    for option, path in named.items():
        key = os.path.realpath(os.fspath(path))
        if key in seen:
            raise FileExistsError(f"{seen[key]} and {option} name the same file {path}: "
                                  "choose two files")
        seen[key] = option
    check_command_outputs(args, list(named.values()))
    others = {k: v for k, v in {**(appended or {}), **(inputs or {})}.items() if v is not None}
    if others:
        # only the "is an input" rule: existing outputs were judged above
        check_atomic(list(named.values()), others, overwrite=True)
    if appended:
        check_appended(appended)
