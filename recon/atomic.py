"""Safe writes: every file the project writes goes through these functions.

:func:`atomic_write` and :func:`atomic_open` write to a temporary file in the same folder,
flush, fsync, then ``os.replace`` it onto the target, so a crash or a full disk leaves either the
old file or the new one, never half of one. :func:`atomic_folder` does the same for a folder of
files written together (a simulation): they are written into a temporary sibling folder that
takes the folder's place only once all of them are there. :func:`check_outputs` refuses, before
anything is computed, writes that would overwrite an input or an existing file. What a saved
file contains (format versions, provenance, hashes) is :mod:`recon.formats`.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import IO, Any

from recon.formats import json_default

__all__ = [
    "atomic_folder",
    "atomic_open",
    "atomic_write",
    "atomic_write_bytes",
    "atomic_write_json",
    "check_outputs",
    "folder_swap_problem",
    "fsync_dir",
    "is_temp_name",
    "temp_files",
]


def _umask_bits() -> int:
    """The process's umask (read by setting it and setting it back)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _umask_mode() -> int:
    """Permissions a plain ``open()`` would give a new file (mkstemp makes them 0600)."""
    return 0o666 & ~_umask_bits()


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike[str], mode: str = "wb") -> Iterator[IO[Any]]:
    """Open a temporary file beside ``path``; on success it replaces ``path`` atomically.

    On any exception the temporary file is removed and ``path`` is left untouched.
    """
    if "w" not in mode:
        raise ValueError(f"atomic_open writes only, got mode {mode!r}")
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, _umask_mode())
        os.replace(tmp, target)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        full = _short_write(exc, target)
        if full is not None:
            raise full from exc
        _name_target(exc, target)
        raise


@contextlib.contextmanager
def atomic_folder(path: str | os.PathLike[str], *, owned: Iterable[str] = ()) -> Iterator[Path]:
    """Build a folder in a temporary sibling; on success it takes the place of ``path``.

    Yields the temporary folder ``.<name>.partial-<pid>-<random>`` (same parent, so the final
    rename stays on one file system); write every file into it. When the block ends normally,
    the entries of an existing ``path`` that the caller does not own (names not in ``owned``
    and not written into the new folder, for example a reconstruction saved beside a
    simulation) are carried over as hard links (copies where links fail), the old folder is
    renamed aside, the new one renamed in, and the old one deleted. On any exception
    (``KeyboardInterrupt`` included) the temporary folder is removed and ``path`` is left as
    it was. Whether an existing ``path`` may be replaced is the caller's to check first
    (:func:`check_outputs`).

    A kill between the two renames (a window of two system calls) leaves the old folder
    complete under its aside name ``.<name>.old-<pid>-<random>``; a kill with SIGKILL during
    the writes leaves the hidden partial folder, never a partial ``path``.
    """
    given = Path(path)
    target = Path(os.path.realpath(given)) if given.is_symlink() else given
    parent = target.parent
    parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.partial-{os.getpid()}-", dir=parent))
    aside: Path | None = None
    try:
        yield tmp
        if target.is_dir():
            skip = set(owned)
            for entry in sorted(target.iterdir()):
                if entry.name not in skip and not os.path.lexists(tmp / entry.name):
                    _carry(entry, tmp / entry.name)
            shutil.copymode(target, tmp)
        else:
            os.chmod(tmp, 0o777 & ~_umask_bits())  # mkdtemp makes it 0700
        fsync_dir(tmp)
        if target.is_dir():
            aside = parent / f".{target.name}.old-{os.getpid()}-{os.urandom(4).hex()}"
            os.rename(target, aside)
        os.rename(tmp, target)
    except BaseException as exc:
        if aside is not None and aside.is_dir() and not os.path.lexists(target):
            os.rename(aside, target)  # put the old folder back
        shutil.rmtree(tmp, ignore_errors=True)
        full = _short_write(exc, target)
        if full is not None:
            raise full from exc
        _name_target(exc, target)
        raise
    fsync_dir(parent)
    if aside is not None:
        shutil.rmtree(aside, ignore_errors=True)


def folder_swap_problem(path: str | os.PathLike[str]) -> str | None:
    """Why :func:`atomic_folder` cannot replace the folder ``path`` whole (None: it can).

    It renames the folder aside and a new one in: not possible for a mount point, not
    wanted for the current folder or one above it (the shell would be left in a deleted
    folder; ``.`` cannot be renamed at all), and not allowed when the folder's parent is not
    writable (its sibling cannot be made). A caller then writes the files one by one, each
    atomically. Ask before the work: the answer may need a probe of the parent.
    """
    given = Path(os.path.abspath(path))
    target = Path(os.path.realpath(given))
    if not target.is_dir():
        return None  # a new folder: made in its parent, which the output checks probe
    if os.path.ismount(target):
        return f"{given} is a mount point"
    try:
        cwd = Path.cwd().resolve()
    except OSError:
        cwd = None
    if cwd is not None and (cwd == target or target in cwd.parents):
        return f"{given} holds the current folder"
    try:
        os.rmdir(tempfile.mkdtemp(prefix=f".{target.name}.probe-", dir=target.parent))
    except OSError as exc:
        return f"its parent {target.parent} is not writable ({exc.strerror or exc})"
    return None


def _carry(src: Path, dst: Path) -> None:
    """Carry ``src`` into a new folder: a hard link (a copy where linking fails), recursively."""
    if src.is_symlink():
        os.symlink(os.readlink(src), dst)
    elif src.is_dir():
        shutil.copytree(src, dst, symlinks=True, copy_function=_link_or_copy)
    else:
        _link_or_copy(str(src), str(dst))


def _link_or_copy(src: str, dst: str) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def is_temp_name(name: str) -> bool:
    """Whether ``name`` is a temporary file of :func:`atomic_open` / :func:`atomic_write`.

    Their names are ``.<target name>.<random>.tmp`` and ``.<target stem>.<random>.tmp<suffix>``;
    one left behind means a process died while writing (the target is intact).
    """
    return name.startswith(".") and ".tmp" in name and len(name) > 5


def temp_files(folder: str | os.PathLike[str]) -> list[Path]:
    """Temporary files of interrupted atomic writes directly in ``folder`` (sorted)."""
    d = Path(folder)
    if not d.is_dir():
        return []
    return sorted(p for p in d.iterdir() if is_temp_name(p.name) and p.is_file())


def fsync_dir(folder: str | os.PathLike[str]) -> None:
    """Make renames in ``folder`` durable (a no-op where directories cannot be opened)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write(path: str | os.PathLike[str], writer: Callable[[Path], None]) -> Path:
    """Call ``writer(tmp_path)`` to produce the file, then move it to ``path`` atomically.

    Use this for libraries that want a filename (tifffile, Pillow, numpy, torch.save).
    The temporary name keeps the target's suffix so format detection by extension works.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(
        prefix=f".{target.stem}.", suffix=f".tmp{target.suffix}", dir=target.parent
    )
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        writer(tmp)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, _umask_mode())
        os.replace(tmp, target)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        full = _short_write(exc, target)
        if full is not None:
            raise full from exc
        _name_target(exc, target)
        raise
    return target


#: NumPy's message for a write that stored fewer bytes than asked (``ndarray.tofile``), an
#: OSError without an error number
_SHORT_WRITE = re.compile(r"^\d+ requested and \d+ written$")


def _short_write(exc: BaseException, target: Path) -> OSError | None:
    """NumPy's short write as the full disk it is (ENOSPC, naming the file), else None.

    A regular file takes fewer bytes than written only when its device is full (or a quota
    is reached); NumPy says "30000 requested and 17952 written", naming neither.
    """
    if isinstance(exc, OSError) and exc.errno is None and _SHORT_WRITE.match(str(exc)):
        return OSError(errno.ENOSPC, f"No space left on device ({exc})", str(target))
    return None


def _name_target(exc: BaseException, target: Path) -> None:
    """Give an OSError raised by a write (``fh.write`` names no file) the file it was for."""
    if (isinstance(exc, OSError) and exc.filename is None and exc.errno is not None
            and exc.strerror):  # (an OSError built from a message alone would print badly)
        exc.filename = str(target)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    with atomic_open(path, "wb") as fh:
        fh.write(data)
    return Path(path)


def atomic_write_json(path: str | os.PathLike[str], obj: Any) -> Path:
    """Write ``obj`` as indented JSON atomically."""
    text = json.dumps(obj, indent=2, sort_keys=False, default=json_default) + "\n"
    return atomic_write_bytes(path, text.encode("utf-8"))


def check_outputs(
    outputs: Iterable[str | os.PathLike[str]],
    inputs: Mapping[str, str | os.PathLike[str] | None] | None = None,
    *,
    overwrite: bool = False,
) -> None:
    """Refuse, before anything is computed, writes that would lose data.

    ``outputs`` are the files a command is about to write; ``inputs`` maps an input's name (the
    option, e.g. ``--meas``) to its path (None: not given). An output that is the same file as
    an input (same resolved path, or ``os.path.samefile`` for links) is always refused; an
    output that exists already is refused unless ``overwrite``. Raises :class:`FileExistsError`
    with a one-line message naming the file and what to do.
    """
    named = [(k, Path(v)) for k, v in (inputs or {}).items() if v is not None]
    for o in outputs:
        if str(o).strip() == "":
            raise FileExistsError("the output path is empty: name a file")
        out = Path(o)
        if out.is_dir():
            raise FileExistsError(f"{out} is a folder: name a file (for example {out / 'x'}"
                                  f"{out.suffix or ''})")
        for parent in out.parents:
            if parent.exists():
                if not parent.is_dir():
                    raise FileExistsError(f"cannot write {out}: {parent} is a file, not a folder")
                break
        for key, src in named:
            same = out.resolve() == src.resolve()
            if not same and out.exists() and src.exists():
                with contextlib.suppress(OSError):
                    same = os.path.samefile(out, src)
            if same:
                raise FileExistsError(
                    f"refusing to write {out}: it is the input {key} of this command "
                    "(choose another output name)")
            # a folder input (a PSF stack's planes) reads the files directly in it
            if src.is_dir() and Path(os.path.abspath(out)).parent.resolve() == src.resolve():
                raise FileExistsError(
                    f"refusing to write {out} inside the input folder {key} {src}: every file "
                    "there is read as input (choose another folder)")
        if out.exists() and not overwrite:
            raise FileExistsError(
                f"{out} exists: pass --overwrite to replace it, or choose another output")
