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
import functools
import json
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

__all__ = ["append_jsonl", "bench_metadata", "bench_threads", "check_appended", "check_outputs",
           "command_line", "hxw", "int_list", "machine_text", "option_defaults", "read_jsonl",
           "read_records", "tagged"]

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
    keeps each finished case, so an interrupted benchmark keeps what it measured.

    A torn last line (an append that was killed: not JSON, not ended by a newline) is cut off
    first, so the new record starts its own line; the line is flushed and fsynced before this
    returns (a crash after it keeps the case).
    """
    if path is None:
        return
    from recon.formats import json_default

    p = Path(path)
    if p.exists():
        _cut_torn_tail(p)
    with open(p, "a", encoding="utf-8") as f:
        f.write(json.dumps(row, default=json_default) + "\n")
        f.flush()
        os.fsync(f.fileno())


def _cut_torn_tail(p: Path) -> None:
    """Cut a torn last line off ``p`` (see :func:`read_jsonl`); a whole last line is kept."""
    with open(p, "rb") as f:  # the last byte first: a whole file is not read at every append
        f.seek(0, os.SEEK_END)
        if f.tell() == 0:
            return
        f.seek(-1, os.SEEK_END)
        if f.read(1) == b"\n":
            return
    data = p.read_bytes()
    start = data.rfind(b"\n") + 1
    try:
        json.loads(data[start:])
    except ValueError:
        with open(p, "r+b") as f:
            f.truncate(start)
            f.flush()
            os.fsync(f.fileno())
        return
    with open(p, "ab") as f:  # a whole record without its newline: end its line
        f.write(b"\n")


def bench_threads(args: argparse.Namespace) -> Any:
    """The torch thread count of a benchmark: its own ``--threads`` when given (a count > 0),
    else the global ``lenslesscam --threads N`` (``args.thread_choice``), else the thread policy
    (:mod:`recon.threads`): the one rule of every ``bench`` subcommand.

    Sets torch's count, stores the choice in ``args.thread_choice`` and its count in
    ``args.threads`` (what the benchmark passes to its worker processes and records), and
    returns the :class:`recon.threads.ThreadChoice`.
    """
    from recon.threads import apply_threads

    local = getattr(args, "threads", None)
    choice = getattr(args, "thread_choice", None)
    if str(local).strip().lower() not in ("none", "0", "auto", "") or choice is None:
        choice = apply_threads(local)  # else main() applied the global choice already
    args.thread_choice = choice
    args.threads = choice.threads
    return choice


def _cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``; else :func:`platform.processor`)."""
    import platform

    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


@functools.cache
def _commit() -> str | None:
    """The source tree's git commit (``-dirty`` when changed), or None outside a checkout."""
    import subprocess

    root = Path(__file__).resolve().parents[1]
    if not (root / ".git").exists():
        return None
    try:
        res = subprocess.run(["git", "describe", "--always", "--dirty", "--abbrev=12"],
                             cwd=root, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return res.stdout.strip() or None if res.returncode == 0 else None


def bench_metadata(name: str, version: int, choice: Any = None) -> dict[str, Any]:
    """What a benchmark's saved file says about itself: its format (``lenslesscam.bench.NAME``)
    and ``format_version``, :func:`recon.formats.provenance` (versions, host, UTC time), the
    source commit, the machine measured (CPU model and counts) and the thread choice."""
    from recon.formats import provenance

    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    meta: dict[str, Any] = {
        "format": f"lenslesscam.bench.{name}", "format_version": version, **provenance(),
        "commit": _commit(),
        "cpu": {"model": _cpu_model(), "count": os.cpu_count(), "usable": usable}}
    if choice is not None:
        meta["threads"] = choice.threads
        meta["threads_reason"] = choice.reason
    return meta


def machine_text(choice: Any = None) -> str:
    """One sentence for a benchmark's Markdown: the machine measured, the threads and the
    software (from :func:`bench_metadata`, measured here, never assumed)."""
    m = bench_metadata("", 0, choice)
    cpu = m["cpu"]
    usable = f", {cpu['usable']} usable" if cpu["usable"] not in (None, cpu["count"]) else ""
    v = m["versions"]
    soft = ", ".join(f"{k} {v[k]}" for k in ("lenslesscam", "torch", "numpy", "python")
                     if k in v)
    threads = f"{choice.reason}; " if choice is not None else ""
    commit = f", commit {m['commit']}" if m["commit"] else ""
    return (f"Measured on {cpu['model']} ({cpu['count']} CPUs{usable}); {threads}"
            f"{soft}{commit}; {m['created_utc']}.")


def option_defaults(add_arguments: Callable[[argparse.ArgumentParser], None]
                    ) -> list[argparse.Action]:
    """The option actions (with their defaults) that ``add_arguments`` adds to a parser."""
    p = argparse.ArgumentParser(add_help=False)
    add_arguments(p)
    return [a for a in p._actions if a.option_strings]


def _arg_text(v: Any) -> str:
    if isinstance(v, tuple) and len(v) == 2 and all(isinstance(x, int) for x in v):
        return f"{v[0]}x{v[1]}"  # an HxW size
    return str(v)


def command_line(name: str, args: argparse.Namespace | dict[str, Any],
                 add_arguments: Callable[[argparse.ArgumentParser], None], *,
                 leave_out: tuple[str, ...] = ()) -> str:
    """The ``lenslesscam bench NAME ...`` command that runs what ``args`` holds.

    Built from the parsed options (never ``sys.argv``): every option of ``add_arguments`` whose
    value differs from its default, in the parser's order (``--threads`` whenever set, as the
    count that ran: :func:`bench_threads`), except the destinations in ``leave_out``. Lists are
    written as the option reads them (``nargs='+'``: spaced; a ``type=`` list: commas).
    """
    import shlex

    values = args if isinstance(args, dict) else vars(args)
    parts = ["lenslesscam", "bench", name]
    for a in option_defaults(add_arguments):
        if a.dest in leave_out or a.dest == "help" or a.dest not in values:
            continue
        v = values[a.dest]
        if v is None or (a.dest != "threads" and v == a.default):
            continue
        flag = a.option_strings[-1] if a.option_strings[-1].startswith("--") else \
            a.option_strings[0]
        if a.nargs == 0:
            if v:
                parts.append(flag)
            continue
        if isinstance(v, (list, tuple)) and a.nargs in ("+", "*"):
            parts += [flag, *(shlex.quote(_arg_text(x)) for x in v)]
        elif isinstance(v, list):
            parts += [flag, shlex.quote(",".join(_arg_text(x) for x in v))]
        else:
            parts += [flag, shlex.quote(_arg_text(v))]
    return " ".join(parts)


def print_and_write(text: str, out: str | os.PathLike[str] | None) -> None:
    """Print a benchmark's Markdown and write it atomically to ``out`` (when given)."""
    print(text)
    if out:
        from recon.atomic import atomic_write_bytes

        atomic_write_bytes(out, text.encode())


def read_jsonl(path: str | os.PathLike[str], option: str, *,
               quiet: bool = False) -> list[dict[str, Any]]:
    """The records of a JSON-lines file (none if it does not exist): :func:`_numbered`."""
    return [row for _i, row in _numbered(path, option, quiet=quiet)]


def _numbered(path: str | os.PathLike[str], option: str, *,
              quiet: bool = False) -> list[tuple[int, dict[str, Any]]]:
    """(line number, record) of each record of a JSON-lines file (none if it does not exist).

    A file that is not JSON lines (a binary file, another format) is a :class:`ValueError`
    with one line naming ``option``, the file and the first bad line. A bad *last* line is the
    torn end of an append that was killed: it is dropped with a warning (unless ``quiet``),
    the records before it are kept (and the next append cuts it off, :func:`append_jsonl`).
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
    lines = [(i, line) for i, line in enumerate(text.splitlines(), 1) if line.strip()]
    rows: list[tuple[int, dict[str, Any]]] = []
    for n, (i, line) in enumerate(lines):
        try:
            row = json.loads(line)
        except json.JSONDecodeError as exc:
            if n == len(lines) - 1 and rows and not text.endswith("\n"):
                if not quiet:
                    import warnings

                    warnings.warn(f"{option} {p}: line {i} is torn (an interrupted append: "
                                  f"{exc.msg}); it is left out, the {len(rows)} record(s) "
                                  "before it are kept", stacklevel=3)
                break
            raise ValueError(f"{option} {p} is not a JSON-lines file (line {i}: {exc.msg}): "
                             "choose another file") from None
        if not isinstance(row, dict):
            raise ValueError(f"{option} {p} is not a JSON-lines file of records (line {i} is "
                             f"a {type(row).__name__}): choose another file")
        rows.append((i, row))
    return rows


def tagged(name: str, version: int, row: dict[str, Any]) -> dict[str, Any]:
    """``row`` with the record format of ``bench NAME`` (``format``, ``format_version``) and
    the software that made it (:func:`recon.formats.provenance`) first."""
    meta = bench_metadata(name, version)
    out = {"format": meta.pop("format"), "format_version": meta.pop("format_version"),
           "provenance": meta}
    out.update((k, v) for k, v in row.items() if k not in out)  # a re-saved record: new tags
    return out


def read_records(path: str | os.PathLike[str], option: str, name: str, version: int,
                 required: tuple[str, ...]) -> list[dict[str, Any]]:
    """The records of ``bench NAME``'s JSON-lines file ``path`` (none if absent), checked.

    A record of another format (another benchmark's file), of a newer ``format_version``, or
    one that lacks a key of ``required`` (a foreign file; an untagged record of an older run
    is read when it has them) is a :class:`ValueError` in one line naming the file, the line
    and what is wrong; a torn last line is dropped (:func:`read_jsonl`).
    """
    numbered = _numbered(path, option)
    want = f"lenslesscam.bench.{name}"
    for line, row in numbered:
        fmt = row.get("format")
        if fmt is not None and fmt != want:
            other = str(fmt).removeprefix("lenslesscam.bench.")
            raise ValueError(f"{option} {path} is a file of bench {other} ({fmt}, line {line}), "
                             f"not of bench {name}: choose another file")
        ver = row.get("format_version", 1)
        if fmt is not None and (not isinstance(ver, int) or ver > version):
            raise ValueError(f"{option} {path} line {line} has format version {ver!r}; this "
                             f"bench {name} reads up to {version}: use a newer lenslesscam")
        missing = [k for k in required if k not in row]
        if missing:
            raise ValueError(f"{option} {path} line {line} is not a record of bench {name}: it "
                             f"has no {', '.join(repr(k) for k in missing)}: choose another file")
    return [row for _i, row in numbered]


def check_appended(appended: Paths) -> None:
    """Refuse, before any work, JSON-lines files to append to that are not JSON lines (an
    existing file of another kind would be corrupted), are folders, or cannot be written."""
    from app.commands._options import check_output_folders

    for option, path in appended.items():
        if path is None:
            continue
        if str(path).strip() == "":
            raise FileExistsError(f"{option}: the path is empty: name a file")
        read_jsonl(path, option, quiet=True)
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
