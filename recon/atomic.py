"""Safe writes: every file the project writes goes through these functions.

:func:`atomic_write` and :func:`atomic_open` write to a temporary file in the same folder,
flush, fsync, then ``os.replace`` it onto the target, so a crash or a full disk leaves either the
old file or the new one, never half of one. :func:`atomic_files` does the same for a set of
files written together (a simulation): they are staged in a hidden folder inside the target
and moved in only once all of them are there, leaving every other file of the folder alone.
:func:`check_outputs` refuses, before anything is computed, writes that would overwrite an
input or an existing file. What a saved
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
    "atomic_files",
    "atomic_open",
    "atomic_write",
    "atomic_write_bytes",
    "atomic_write_json",
    "check_outputs",
    "fsync_dir",
    "is_temp_name",
    "temp_files",
    "write_new",
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
def atomic_files(path: str | os.PathLike[str], *, owned: Iterable[str] = (),
                 last: Iterable[str] = ()) -> Iterator[Path]:
    """Write a set of files into the folder ``path`` whole or not at all; touch nothing else.

    Yields a hidden staging folder ``.partial-<pid>-<random>`` inside ``path`` (made, with its
    parents, when missing); write every file of the set into it (files, not folders). When the
    block ends normally each staged file is moved onto its name in ``path`` (one rename each,
    within one file system), the names in ``owned`` that this set does not write (the files of
    an earlier set, listed by its record) are removed, and the names in ``last`` (that record)
    are moved in after all the others. What would make a rename fail is checked before the
    first one: a staged entry that is not a file, a name of the set that is a folder in
    ``path`` (a folder is never replaced; an owned name that is a folder is left). On any
    exception before the renames (``KeyboardInterrupt`` included) the staging folder is
    removed and ``path`` is as it was (removed again, with the parents this call made, when
    it made them and they are empty).

    Entries of ``path`` outside the set (a reconstruction saved beside a simulation, a run
    folder another process is writing into) are never moved, copied or deleted: an earlier
    version swapped the whole folder for a new one, and files other processes wrote into it
    while it was swapped were lost. It also needs no writable parent and works on the current
    folder or a mount point. A kill (or an I/O error) during the final renames, a few system
    calls, can leave some files new and others old, the record last (so it still describes
    the old set); a kill earlier leaves the staging folder (its name starts with
    ``.partial-``), never a partial file.
    """
    given = Path(path)
    target = Path(os.path.realpath(given))  # a symlinked folder is written through the link
    made = [a for a in (target, *target.parents) if not a.exists()]  # deepest first
    target.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".partial-{os.getpid()}-", dir=target))
    try:
        yield stage
        staged = sorted(p.name for p in stage.iterdir())
        for name in staged:
            if not (stage / name).is_file() or (stage / name).is_symlink():
                raise ValueError(f"{stage / name} is not a file: only files are written as a "
                                 "set")
            if (target / name).is_dir() and not (target / name).is_symlink():
                raise IsADirectoryError(errno.EISDIR, "a folder of that name is in the way "
                                        "(it is never replaced by a file)", str(target / name))
        records = [n for n in staged if n in set(last)]
        for name in staged:
            if name not in records:
                os.replace(stage / name, target / name)
        for stale in sorted(set(owned) - set(staged)):
            old = target / stale
            if not old.is_dir() or old.is_symlink():  # a folder of that name is not ours
                with contextlib.suppress(FileNotFoundError):
                    old.unlink()
        for name in records:
            os.replace(stage / name, target / name)
        stage.rmdir()
        fsync_dir(target)
    except BaseException as exc:
        shutil.rmtree(stage, ignore_errors=True)
        for folder in made:  # only when empty: nothing else is ever removed
            with contextlib.suppress(OSError):
                folder.rmdir()
        full = _short_write(exc, given)
        if full is not None:
            raise full from exc
        _name_target(exc, given)
        raise


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


def _claim(tmp: Path, target: Path) -> bool:
    """Give the finished file ``tmp`` the name ``target`` unless a file has it (then False).

    A hard link refuses an existing name atomically. Where the file system has no hard links,
    the name is reserved by an exclusive create and the file moved onto that placeholder
    (which is ours: nothing of anyone else's is replaced).
    """
    try:
        os.link(tmp, target)
    except FileExistsError:
        return False
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EMLINK,
                             errno.ENOSYS):
            raise
        try:
            fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:
            return False
        os.close(fd)
        try:
            os.replace(tmp, target)
        except BaseException:
            target.unlink(missing_ok=True)  # our empty placeholder, not a file of anyone's
            raise
        return True
    tmp.unlink()
    return True


def write_new(save: Callable[[Path], Any], folder: Path, stem: str, suffix: str) -> Path:
    """Write a file with ``save(path)`` as ``folder/stem+suffix`` (or ``stem-2``, ``-3``...).

    Never replaces a file (another save in the same second, another window or bench writing
    to the folder, the preview's PSF): the file is written whole under a temporary name, then
    given the first name that no file has, by an operation that refuses an existing name.
    Returns the path written.
    """
    folder.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{stem}.", suffix=f".tmp{suffix}", dir=folder)
    os.close(fd)
    tmp = Path(name)
    try:
        save(tmp)
        os.chmod(tmp, _umask_mode())  # as a plain open() would make it (mkstemp: 0600)
        with open(tmp, "rb") as fh:  # on disk before it has its name
            os.fsync(fh.fileno())
        n = 1
        while True:
            target = folder / (f"{stem}{suffix}" if n == 1 else f"{stem}-{n}{suffix}")
            if _claim(tmp, target):
                fsync_dir(folder)
                return target
            n += 1
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
