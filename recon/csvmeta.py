"""CSV tables that carry their metadata: leading ``# key: value`` lines, then the table.

A table file (``trade.csv``, a batch's ``summary.csv``) starts with its format, format version
and metadata as comment lines, followed by an ordinary CSV table (one header row)::

    # format: lenslesscam.trade
    # format_version: 1
    # created_utc: 2026-01-01T12:00:00+00:00
    # case: {"name": "im408 90%", "shape": [1, 150, 200], ...}
    case,setting,method,...
    im408 90%,fista tau=1e-05,fista,...

A value is JSON where it parses as JSON (numbers, lists, objects, quoted strings), else the
text itself; so ``lenslesscam.trade`` is a string and ``1`` a number, and a string that would
read as JSON is written quoted. pandas reads the table with ``pd.read_csv(path, comment="#")``;
a data row with a ``#`` in a cell is written with every cell quoted, so pandas keeps the whole
row. Comment lines that are not ``key: value`` are allowed and ignored.

A file without a ``format`` line is read as version 0 (written before the header existed);
another ``format``, or a ``format_version`` newer than the reader's, is refused with a
:class:`recon.formats.FormatError` naming the file. Each file kind keeps its one reader (which
calls :func:`read_table`) and its one writer (which calls :func:`format_table`).
"""

from __future__ import annotations

import csv
import io
import json
import os
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from recon.formats import FormatError, json_default, read_utf8

__all__ = ["Table", "format_table", "read_table"]

_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_.-]*")


def _encode(value: Any) -> str:
    """The text of a header value: a plain string as itself where that reads back, else JSON."""
    if isinstance(value, str) and value == value.strip() and "\n" not in value \
            and "\r" not in value:
        try:
            json.loads(value)
        except ValueError:
            return value
    return json.dumps(value, default=json_default, ensure_ascii=False)


def _decode(text: str) -> Any:
    try:
        return json.loads(text)
    except ValueError:
        return text


def format_table(fmt: str, version: int, meta: Iterable[tuple[str, Any]],
                 fieldnames: Sequence[str], rows: Iterable[Mapping[str, Any]]) -> str:
    """The text of a table file: ``format``, ``format_version``, ``meta`` lines, the table.

    ``meta`` is (key, value) pairs in the order written; a key may repeat (one line each).
    """
    lines = [f"# format: {_encode(fmt)}", f"# format_version: {int(version)}"]
    for key, value in meta:
        if not _KEY.fullmatch(key) or key in ("format", "format_version"):
            raise ValueError(f"not a header key: {key!r}")
        lines.append(f"# {key}: {_encode(value)}")
    buf = io.StringIO()
    plain = csv.DictWriter(buf, fieldnames=list(fieldnames), lineterminator="\n")
    quoted = csv.DictWriter(buf, fieldnames=list(fieldnames), lineterminator="\n",
                            quoting=csv.QUOTE_ALL)
    plain.writeheader()
    for row in rows:
        # a '#' outside quotes starts a comment for pandas (comment="#"): quote the row
        hashed = any("#" in str(v) for v in row.values() if v is not None)
        (quoted if hashed else plain).writerow(row)
    return "\n".join(lines) + "\n" + buf.getvalue()


@dataclass
class Table:
    """A table file as read: its header, its columns and its rows with their line numbers."""

    format_version: int  # 0: no header (a file written before the header existed)
    meta: dict[str, Any]  # header values (a repeated key: the list of its values)
    fieldnames: list[str]
    rows: list[tuple[int, dict[str, str]]] = field(default_factory=list)  # (file line, row)


def read_table(path: str | os.PathLike[str], fmt: str, version: int, what: str,
               repeated: Sequence[str] = ()) -> Table:
    """Read a table file of format ``fmt`` that this release writes at ``version``.

    ``what`` names the file kind in messages (``"trade.csv"``); ``repeated``: keys that may
    appear on several lines (their values come as a list, even when there is one).
    """
    text = read_utf8(path, error=FormatError, what=f"not a {what}: ")
    meta: dict[str, Any] = {k: [] for k in repeated}
    pos, line = 0, 0
    while text.startswith("#", pos):
        end = text.find("\n", pos)
        end = len(text) if end < 0 else end
        body = text[pos + 1:end].rstrip("\r").strip()
        pos, line = end + 1, line + 1
        key, sep, value = body.partition(":")
        key = key.strip()
        if not sep or not _KEY.fullmatch(key):
            continue  # a free comment
        val = _decode(value.strip())
        if key in repeated:
            meta[key].append(val)
        elif key in meta:
            raise FormatError(f"{path} line {line}: header key {key!r} given twice")
        else:
            meta[key] = val
    found = meta.get("format")
    file_version = 0
    if found is not None:
        if found != fmt:
            raise FormatError(f"{path}: not a {what} (its format is {found!r}, expected "
                              f"{fmt!r})")
        v = meta.get("format_version")
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise FormatError(f"{path}: not a {what}: format_version {v!r} is not a whole "
                              "number >= 1")
        file_version = v
        if file_version > version:
            raise FormatError(f"{path}: {what} format version {file_version} is newer than "
                              f"this lenslesscam reads ({version}); update lenslesscam to "
                              "read it")
    reader = csv.DictReader(io.StringIO(text[pos:], newline=""))
    try:  # csv.Error is no ValueError: a field over csv's limit escaped every caller's guard
        fieldnames = list(reader.fieldnames or [])
        rows = [(line + reader.line_num, rec) for rec in reader]
    except csv.Error as exc:
        raise FormatError(f"{path}: not a readable {what} (line {line + reader.line_num}: "
                          f"{exc})") from None
    return Table(file_version, meta, fieldnames, rows)
