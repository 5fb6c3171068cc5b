"""What every saved artifact carries: a format version, provenance metadata, content hashes.

Every artifact carries ``format`` (what it is) and ``format_version`` (how to read it) in its
metadata, plus :func:`provenance`; a file that is not what it claims raises
:class:`FormatError`. Writing files safely (atomic writes, refusing to overwrite inputs) is
:mod:`recon.atomic`.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import os
import platform
from typing import Any

__all__ = [
    "FORMAT_VERSION",
    "INT_LIMIT",
    "FormatError",
    "NewerFormat",
    "NotOurFile",
    "array_hash",
    "file_hash",
    "json_default",
    "provenance",
    "software_version",
    "whole_version",
]

#: Version of the on-disk formats written by this release (bumped on incompatible changes).
FORMAT_VERSION = 1
#: the largest magnitude of any integer a user gives (an option, a job spec's or a plan's
#: value, a dialog's box): an int64 with room, beyond which NumPy and torch counters overflow
INT_LIMIT = 2**62


class FormatError(ValueError):
    """A file exists but is not what it claims to be (corrupt, wrong format or version)."""


class NewerFormat(FormatError):
    """A file of ours written by a newer release (its ``format_version`` is above ours).

    Never passed over as damaged, never overwritten: the release that wrote it reads it.
    """


class NotOurFile(FormatError):
    """A file that does not claim to be one of ours (no metadata, or another format's).

    The one :class:`FormatError` a caller may answer by reading the file as a plain image; a
    file of ours that is newer, of another kind or corrupt is refused instead.
    """


def software_version() -> str:
    """Version of the installed ``lenslesscam`` distribution (or 'unknown' from a bare tree)."""
    try:
        from importlib.metadata import version

        return version("lenslesscam")
    except Exception:  # not installed: running from a source tree
        return "unknown"


def provenance() -> dict[str, Any]:
    """Metadata every artifact carries: software versions, host and UTC time."""
    import numpy as np

    versions: dict[str, str] = {
        "lenslesscam": software_version(),
        "python": platform.python_version(),
        "numpy": np.__version__,
    }
    import sys

    if "torch" in sys.modules:  # never import torch just to write metadata
        versions["torch"] = str(sys.modules["torch"].__version__)
    return {
        "versions": versions,
        "host": platform.node(),
        "created_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
    }


def json_default(o: Any) -> Any:
    """``default=`` for json.dumps: numpy scalars and arrays, paths, enums, ``to_dict()``."""
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, os.PathLike):
        return os.fspath(o)
    if hasattr(o, "value"):  # Enum
        return o.value
    if hasattr(o, "to_dict"):  # SensorTiming, Roi, ...
        return o.to_dict()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def array_hash(a: Any) -> str:
    """SHA-256 (first 16 hex digits) of an array's dtype, shape and bytes."""
    import numpy as np

    arr = np.ascontiguousarray(a)
    h = hashlib.sha256()
    h.update(str(arr.dtype).encode())
    h.update(str(arr.shape).encode())
    h.update(arr.tobytes())
    return h.hexdigest()[:16]


def file_hash(path: str | os.PathLike[str]) -> str:
    """SHA-256 (first 16 hex digits) of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()[:16]


def read_utf8(path: str | os.PathLike[str], *, error: type[Exception] = ValueError,
              what: str = "", hint: str = "") -> str:
    """A text file's contents: UTF-8, with or without an editor's byte-order mark.

    Text that is not UTF-8 raises ``error`` in one line: ``PATH: WHATnot UTF-8 text (byte
    0xE9 at offset N)HINT`` (the one decoding rule of the project's text files: specs,
    manifests, records, table files).
    """
    with open(path, "rb") as fh:
        data = fh.read()
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise error(f"{path}: {what}not UTF-8 text (byte {data[exc.start]:#04x} at offset "
                    f"{exc.start}){hint}") from None


def whole_version(value: Any) -> int | None:
    """A file's ``format_version`` as an integer, or None when it is not a whole number.

    The one rule every reader of a versioned file uses: an int (not a bool), or a float that
    is a whole number (``1.0``: some JSON writers put 1 so).
    """
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return None
