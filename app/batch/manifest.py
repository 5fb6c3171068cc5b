"""Batch manifests: read a CSV or TOML manifest into checked items, and hash each item's inputs.

CSV: one item per row; the header names the columns. The simplest manifest is::

    measurement,psf,method
    meas/*.npy,psf.npy,fista

TOML: ``[defaults]`` (columns every item gets unless it sets them) and ``[[item]]`` tables::

    [defaults]
    psf = "psf.npy"
    method = "fista"
    tau = 1e-4

    [[item]]
    measurement = "meas/*.npy"

    [[item]]
    measurement = "best/scene1.npy"
    method = "udn"
    spec = "overnight.toml"

Columns:

- ``measurement`` (required): a file, or a glob (``*``, ``?``, ``[``) that expands to one item
  per matching file, in sorted order. A glob that matches nothing is an error; a file whose
  name is the cell itself (``e[1]/a.npy``) is that file, not a glob.
- ``method`` (required): a method of ``lenslesscam recon`` (``fista``, ``auto``, ``udn``, ...).
- ``name``: the item's id (default: the measurement's stem and the method); with a glob, the
  stem is appended.
- ``truth``: a ground-truth scene; the summary then has metrics (PSNR/SSIM after a
  least-squares gain fit, as ``lenslesscam metrics --gain-fit``).
- ``spec`` (``udn`` only): a job spec (TOML) to start from; the item's data columns
  (measurement, psf, mask, shutter, filters, dark, downsample, rgb, channel_order, flip_rows,
  ...) replace the same keys of its ``[data]``; the spec's other keys (its dark, say) stay.
- every other column is an option of ``lenslesscam recon METHOD`` with ``-`` written as ``_``
  (``psf``, ``mask``, ``shutter``, ``filters``, ``dark``, ``downsample``, ``tau``, ``iters``,
  ``model``, ...); flags take ``true``/``false``. An empty CSV cell means "not set"; a TOML
  ``[defaults]`` key that an item's method does not take is left out for that item (the same
  key written in the item is an error; a key that no method takes is an error). A default
  replaces a ``spec``'s ``[data]`` keys, never its solver's (``iters``, ``seed``: only the
  item's own columns replace ``max_iter`` and ``seed``).

Relative paths are relative to the manifest's folder. Every item is checked when the manifest
is read (with the very parser of ``lenslesscam recon METHOD``), so a bad row stops the batch
before anything runs, with one line naming the row and the problem.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import dataclasses
import glob
import hashlib
import io
import json
import re
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

__all__ = ["Item", "item_hash", "method_parser", "read_manifest"]

#: Columns the batch itself reads (the others are options of ``lenslesscam recon METHOD``).
BATCH_COLUMNS = ("measurement", "method", "name", "truth", "spec")
#: Columns that name files (resolved against the manifest's folder, hashed for reruns).
PATH_COLUMNS = ("measurement", "psf", "psf_stack", "mask", "shutter", "filters", "truth", "spec",
                "timing", "plan", "trade")
#: Columns whose value may be a file or a value (a number, ``auto``).
MAYBE_PATH_COLUMNS = ("dark", "psf_dark")
#: ``udn`` items with a ``spec``: column -> (section, key) of the job spec it replaces.
SPEC_COLUMNS: dict[str, tuple[str, str]] = {
    "psf": ("data", "psf"), "psf_stack": ("data", "psf"), "mask": ("data", "mask"),
    "shutter": ("data", "shutter"), "filters": ("data", "filters"), "dark": ("data", "dark"),
    "psf_dark": ("data", "psf_dark"), "downsample": ("data", "downsample"),
    "model": ("data", "model"), "field": ("data", "field"), "truth": ("data", "truth"),
    "iters": ("stopping", "max_iter"), "seed": ("optimizer", "seed"),
    "channel_order": ("data", "channel_order"), "flip_rows": ("data", "flip_rows"),
}
_GLOB = re.compile(r"[*?\[]")
#: the longest item id (bytes of UTF-8): its file names and their temporary names (about 30
#: bytes more) stay within the 255 bytes of a file name
MAX_ID_BYTES = 200
#: characters an item id keeps (letters and digits of any script, . _ -); others become _
_SAFE = re.compile(r"[^\w.-]+")


@dataclass(frozen=True)
class Item:
    """One reconstruction of a batch.

    ``argv`` are the options of ``lenslesscam recon METHOD`` (without ``--out``; paths
    absolute); ``spec`` is the job spec a ``udn`` item starts from (None: built from ``argv``
    as ``recon udn`` builds it); ``spec_data`` are the ``[section] key = value`` pairs that
    replace the spec's. ``inputs`` names every input file (for the item's hash).
    """

    id: str
    method: str
    argv: tuple[str, ...]
    source: str  # "manifest.csv:3" (for messages)
    truth: str | None = None
    spec: str | None = None
    spec_data: tuple[tuple[str, str, Any], ...] = ()
    inputs: tuple[tuple[str, str], ...] = field(default=())

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (as recorded in the item's record)."""
        return {"id": self.id, "method": self.method, "argv": list(self.argv),
                "source": self.source, "truth": self.truth, "spec": self.spec,
                "spec_data": [list(t) for t in self.spec_data],
                "inputs": dict(self.inputs)}


# --------------------------------------------------------------------------------------------
# The recon parser (the same one ``lenslesscam recon`` uses)
# --------------------------------------------------------------------------------------------


@lru_cache(maxsize=1)
def _recon_parser() -> tuple[argparse.ArgumentParser, dict[str, argparse.ArgumentParser]]:
    from app.cli import Parser  # the command line's parser class: the same reading of values
    from app.commands import recon

    top = Parser(prog="lenslesscam")
    sub = top.add_subparsers(dest="command")
    recon.register(sub)
    methods: dict[str, argparse.ArgumentParser] = {}
    recon_p = sub.choices["recon"]
    for action in recon_p._actions:
        if isinstance(action, argparse._SubParsersAction):
            methods = dict(action.choices)
    return top, methods


def method_parser(method: str) -> argparse.ArgumentParser:
    """The parser of ``lenslesscam recon METHOD`` (ValueError naming the methods if unknown)."""
    _, methods = _recon_parser()
    if method not in methods:
        raise ValueError(f"method {method!r} is not a method of 'lenslesscam recon' "
                         f"(use one of: {', '.join(sorted(methods))})")
    return methods[method]


def parse_recon_args(method: str, argv: list[str]) -> argparse.Namespace:
    """Parse ``lenslesscam recon METHOD ARGV`` exactly as the command line does.

    A usage error becomes a ValueError with argparse's one-line message.
    """
    top, _ = _recon_parser()
    method_parser(method)
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            return top.parse_args(["recon", method, *argv])
    except SystemExit:
        lines = [ln for ln in err.getvalue().strip().splitlines() if ln.strip()]
        msg = lines[-1] if lines else "invalid options"
        msg = re.sub(r"^lenslesscam recon \S+: error: ", "", msg)
        msg = re.sub(r" \(see 'lenslesscam recon \S+ --help'\)$", "", msg)
        raise ValueError(msg) from None


def option_names(method: str) -> set[str]:
    """The long options of ``lenslesscam recon METHOD`` (``-`` written ``_``)."""
    return set(_options(method))


def _options(method: str) -> dict[str, argparse.Action]:
    """``dest`` -> action of the method's long options."""
    out: dict[str, argparse.Action] = {}
    for action in method_parser(method)._actions:
        for opt in action.option_strings:
            if opt.startswith("--"):
                out[opt[2:].replace("-", "_")] = action
    return out


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------


def _read_rows(path: Path) -> list[tuple[str, dict[str, Any], frozenset[str]]]:
    """(where, columns, names that come from [defaults] only) per manifest row."""
    if not path.is_file():
        raise FileNotFoundError(f"manifest not found: {path}")
    from recon.formats import read_utf8

    text = read_utf8(path, hint="; save the manifest as UTF-8")
    suffix = path.suffix.lower()
    if suffix == ".csv":
        reader = _CheckedCsv(csv.DictReader(io.StringIO(text)), path)
        if not reader.fieldnames:
            raise ValueError(f"{path}: empty CSV manifest (the header names the columns, e.g. "
                             "measurement,psf,method)")
        names = [n.strip() for n in reader.fieldnames]
        if len(set(names)) != len(names):
            raise ValueError(f"{path}: a column appears twice in the header: {', '.join(names)}")
        rows: list[tuple[str, dict[str, Any], frozenset[str]]] = []
        for i, raw in enumerate(reader, start=2):
            if None in raw:
                raise ValueError(f"{path}:{i}: more cells than columns in the header")
            row = {k.strip(): (v or "").strip() for k, v in raw.items()}
            if not any(row.values()):
                continue  # a blank line
            rows.append((f"{path.name}:{i}", {k: v for k, v in row.items() if v != ""},
                         frozenset()))
        return rows
    if suffix == ".toml":
        import tomllib

        try:
            doc = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"{path}: not valid TOML: {exc}") from None
        unknown = sorted(set(doc) - {"defaults", "item"})
        if unknown:
            raise ValueError(f"{path}: unknown table(s) {', '.join(unknown)}; a manifest has "
                             "[defaults] and [[item]] tables")
        defaults = doc.get("defaults", {})
        items = doc.get("item", [])
        if not isinstance(defaults, dict) or not isinstance(items, list):
            raise ValueError(f"{path}: [defaults] must be a table and [[item]] an array of "
                             "tables")
        _check_defaults(path, defaults)
        return [(f"{path.name}:item {i + 1}", {**defaults, **it},
                 frozenset(set(defaults) - set(it))) for i, it in enumerate(items)]
    raise ValueError(f"{path}: a manifest is a .csv or .toml file")


def _check_defaults(path: Path, defaults: dict[str, Any]) -> None:
    """Refuse a ``[defaults]`` key that no item could take (a typo: ``tua``), in one line.

    A key that some method takes is left out of the items whose method does not; a key no
    method takes was left out of every item without a word.
    """
    _, methods = _recon_parser()
    known = set(BATCH_COLUMNS) | set(SPEC_COLUMNS) | {"rgb"}
    for method in methods:
        known |= option_names(method)
    known -= {"out", "meas", "help"}
    for key in defaults:
        if key not in known:
            import difflib

            near = difflib.get_close_matches(key, sorted(known), n=1)
            hint = f"; did you mean {near[0]!r}?" if near else ""
            raise ValueError(f"{path.name}: [defaults]: {key!r} is not a column of any item (an "
                             f"option of no method of 'lenslesscam recon'){hint}")


def _resolve(base: Path, value: Any) -> str:
    p = Path(str(value)).expanduser()
    return str(p if p.is_absolute() else (base / p).resolve())


def _maybe_path(base: Path, value: Any) -> str:
    text = str(value)
    if text == "auto":
        return text
    try:
        float(text)
    except ValueError:
        return _resolve(base, text)
    return text


def _flag(value: Any, where: str, col: str) -> bool:
    if isinstance(value, bool):
        return value
    text = str(value).strip().lower()
    if text in ("1", "true", "yes", "on"):
        return True
    if text in ("0", "false", "no", "off"):
        return False
    raise ValueError(f"{where}: column {col!r} is a flag: write true or false, got {value!r}")


def _is_flag_text(value: Any) -> bool:
    """Whether a cell says true or false (as :func:`_flag` reads it)."""
    return isinstance(value, bool) or str(value).strip().lower() in (
        "1", "true", "yes", "on", "0", "false", "no", "off")


def _expand(base: Path, pattern: str, where: str) -> tuple[list[str], bool]:
    """The files of a ``measurement`` cell, and whether it was read as a glob.

    A file of that very name wins over a glob (``e[1]/a.npy`` that exists is that file, not
    ``e1/a.npy``); the manifest's folder is never part of the pattern (a folder named
    ``scan[2024]`` holds its manifest's measurements like any other).
    """
    full = _resolve(base, pattern)
    if not _GLOB.search(pattern) or Path(full).is_file():
        return [full], False
    given = Path(pattern).expanduser()
    spec = str(given) if given.is_absolute() else str(Path(glob.escape(str(base))) / given)
    matches = sorted({str(Path(m).parent.resolve() / Path(m).name) for m in glob.glob(spec)
                      if Path(m).is_file()})
    if not matches:
        raise ValueError(f"{where}: measurement glob {pattern!r} matches no file")
    return matches, True


def _item_from(row: dict[str, Any], meas: str, base: Path, where: str, name: str,
               from_defaults: frozenset[str] = frozenset()) -> Item:
    method = str(row["method"]).strip()
    try:
        opts = _options(method)
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None
    spec = row.get("spec")
    if spec is not None and method != "udn":
        raise ValueError(f"{where}: column 'spec' is for method udn (this item is {method})")
    truth = _resolve(base, row["truth"]) if row.get("truth") is not None else None
    inputs: dict[str, str] = {"measurement": meas}
    if truth:
        inputs["truth"] = truth
    argv: list[str] = ["--meas", meas]
    spec_data: list[tuple[str, str, Any]] = []
    if spec is not None:
        spec = _resolve(base, spec)
        inputs["spec"] = spec
        spec_data.append(("data", "measurement", meas))
        if truth:
            spec_data.append(("data", "truth", truth))
    for col, value in row.items():
        if col in BATCH_COLUMNS:
            continue
        if col in PATH_COLUMNS:
            value = _resolve(base, value)
            inputs[col] = value
        elif col in MAYBE_PATH_COLUMNS:
            value = _maybe_path(base, value)
            if value != "auto" and Path(value).is_absolute():
                inputs[col] = value
        if spec is not None:
            if col == "rgb":
                spec_data.append(("data", "color", "rgb" if _flag(value, where, col) else "gray"))
                continue
            if col in from_defaults and SPEC_COLUMNS.get(col, ("",))[0] != "data":
                # a default for the other methods' items, or for their solver (FISTA's iters
                # and seed are not the spec's max_iter and seed): only the item's own columns
                # replace the spec's [stopping] and [optimizer] keys
                continue
            if col not in SPEC_COLUMNS:
                raise ValueError(f"{where}: column {col!r} cannot change a job spec: set it in "
                                 f"the spec file (the columns that can: "
                                 f"{', '.join(sorted(SPEC_COLUMNS))}, rgb)")
            sec, key = SPEC_COLUMNS[col]
            if key in ("downsample", "max_iter", "seed"):
                value = _whole(value, col, where)
            if key == "flip_rows":
                value = _flag(value, where, col)
            if col in MAYBE_PATH_COLUMNS and value != "auto" and not Path(value).is_absolute():
                value = float(value)  # a level, not a file name (the spec reads text as a path)
            if col == "psf_stack":
                spec_data.append(("data", "model", "depth"))
            spec_data.append((sec, key, value))
            continue
        action = opts.get(col)
        if action is None and col in from_defaults:
            continue  # a default for the other methods' items
        if action is None or col in ("out", "meas"):
            known = [*sorted(set(opts) - {"out", "meas", "help"}), "name", "truth"]
            if method == "udn":
                known.append("spec")
            raise ValueError(f"{where}: column {col!r} is not an option of 'lenslesscam recon "
                             f"{method}' (columns: measurement, method, {', '.join(known)})")
        if isinstance(action, argparse._StoreTrueAction):
            if _flag(value, where, col):
                argv.append(f"--{col.replace('_', '-')}")
        elif isinstance(action, argparse.BooleanOptionalAction):
            # with_fista = false is --no-with-fista (it went on as '--with-fista false',
            # "unrecognized arguments: false"); no_with_fista = true likewise
            positive = action.option_strings[0]
            on = _flag(value, where, col) != col.startswith("no_")
            both = [c for c in row if c != col and opts.get(c) is action]
            if both:  # the last one won without a word
                raise ValueError(f"{where}: columns {col!r} and {both[0]!r} both set "
                                 f"{positive}: give one of them")
            argv.append(positive if on else "--no-" + positive[2:])
        elif action.nargs == "?" and _is_flag_text(value):
            # an option with an optional value (--compile [MODE]): true is the option alone
            # (it was 'invalid choice: true'), false leaves it out
            if _flag(value, where, col):
                argv.append(f"--{col.replace('_', '-')}")
        else:
            argv += [f"--{col.replace('_', '-')}", str(value)]
    if truth and method == "udn" and spec is None:
        argv += ["--truth", truth]
    item = Item(id=name, method=method, argv=tuple(argv), source=where, truth=truth, spec=spec,
                spec_data=tuple(spec_data), inputs=tuple(sorted(inputs.items())))
    return _check(item)


def _whole(value: Any, col: str, where: str) -> int:
    """A whole-number cell for a job spec, read as ``lenslesscam recon udn`` reads the option.

    ``iters = 1.9`` or ``downsample = true`` are refused as on the command line (they became
    1).
    """
    action = _options("udn").get(col)
    text = str(value).lower() if isinstance(value, bool) else str(value)
    parse = getattr(action, "type", None) or int
    try:
        return int(parse(text))
    except (argparse.ArgumentTypeError, TypeError, ValueError) as exc:
        why = str(exc) if isinstance(exc, argparse.ArgumentTypeError) else (
            f"must be an integer, got {text!r}")
        raise ValueError(f"{where}: column {col!r} {why}") from None


def _spec_inputs(spec: dict[str, Any], base: Path, source: str) -> dict[str, str]:
    """The files a job spec's ``[data]`` names, made absolute as the spec loader makes them."""
    from recon.udn.spec import SCHEMA, normalise_spec

    out: dict[str, str] = {}
    for key, value in normalise_spec(spec, base, source=source)["data"].items():
        schema = SCHEMA["data"].get(key)
        if key in ("dark", "psf_dark"):
            if isinstance(value, str) and value != "auto":  # a dark-frame file, not a level
                out[key] = value
        elif schema is not None and schema.path and isinstance(value, list):
            out.update({f"{key}.{i}": str(v) for i, v in enumerate(value)})  # PSF planes
        elif schema is not None and schema.path and isinstance(value, str):
            out[key] = value
    return out


def _check(item: Item) -> Item:
    """Parse the item with the command's parser (and a udn item's spec) now, not in a task.

    Returns the item with every file its job spec names among its inputs (a udn item with a
    ``spec``: the spec's psf, dark, mask, ... are hashed as the columns' files are).
    """
    out = ["--out", "x.tif"] if item.method != "udn" else ["--out", "run"]
    try:
        if item.spec is None:
            parse_recon_args(item.method, [*item.argv, *out])
            return item
        from app.batch.task import build_udn_spec

        spec, base = build_udn_spec(item)
        named = _spec_inputs(spec, base, item.spec)
    except (ValueError, FileNotFoundError) as exc:
        raise ValueError(f"{item.source}: {exc}") from None
    inputs = {**dict(item.inputs), **named}
    return dataclasses.replace(item, inputs=tuple(sorted(inputs.items())))


def read_manifest(path: str | Path) -> list[Item]:
    """Read and check a manifest (see the module docstring); returns its items in order.

    Raises ValueError / FileNotFoundError naming the row and the problem.
    """
    path = Path(path)
    base = path.resolve().parent
    items: list[Item] = []
    explicit: list[bool] = []  # whether the item's name was given (not made from its file)
    named: dict[str, str] = {}  # an explicit name, as a result's file name -> where given
    for where, row, from_defaults in _read_rows(path):
        for col in ("measurement", "method"):
            if row.get(col) in (None, ""):
                raise ValueError(f"{where}: column {col!r} is missing or empty (a manifest "
                                 "needs at least measurement,psf,method)")
        pattern = str(row["measurement"])
        files, is_glob = _expand(base, pattern, where)
        for meas in files:
            stem = Path(meas).stem
            if row.get("name"):
                given = str(row["name"]) + (f"-{stem}" if is_glob else "")
                name = _SAFE.sub("_", given)
                if name in named:
                    same = "" if name == given else f" (as the file name {name!r})"
                    raise ValueError(f"{where}: name {given!r}{same} is given to another item "
                                     f"too ({named[name]}): names identify results")
                named[name] = where
            else:
                name = _SAFE.sub("_", f"{stem}-{row['method']}")
            items.append(_item_from(row, meas, base, where, name, from_defaults))
            explicit.append(bool(row.get("name")))
    if not items:
        raise ValueError(f"{path}: the manifest lists no items")
    # a name made from a file that is taken (by a given name, or an earlier item of the same
    # file and method) gets -2, -3, ... in manifest order, never one that is taken too
    taken = set(named)
    unique = []
    for it, given in zip(items, explicit, strict=True):
        if not given:
            n, name = 1, it.id
            while name in taken:
                n += 1
                name = f"{it.id}-{n}"
            taken.add(name)
            it = dataclasses.replace(it, id=name)
        _check_id_length(it, given)
        unique.append(it)
    return unique


def _check_id_length(item: Item, given: bool) -> None:
    """Refuse an item id too long for the file names made from it, naming the column.

    ``items/ID.json``, ``results/ID.tif``, ``runs/ID-HASH8`` and the temporary files of their
    atomic writes (``.ID.tif.RANDOM.tmp``) must stay within the file system's 255 bytes: a
    300-character name failed in the middle of the batch with "[Errno 36] File name too long".
    """
    n = len(item.id.encode("utf-8"))
    if n <= MAX_ID_BYTES:
        return
    if given:
        raise ValueError(f"{item.source}: column 'name' makes an item id of {n} bytes "
                         f"({item.id[:24]}...): at most {MAX_ID_BYTES}, as it names the item's "
                         "files; give a shorter name")
    raise ValueError(f"{item.source}: column 'measurement': the file name gives an item id of "
                     f"{n} bytes ({item.id[:24]}...): at most {MAX_ID_BYTES}, as it names the "
                     "item's files; give the item a shorter 'name'")


# --------------------------------------------------------------------------------------------
# Hashes (what makes a rerun skip an item)
# --------------------------------------------------------------------------------------------


def _hash_path(path: str) -> str | None:
    from recon.formats import file_hash

    p = Path(path)
    if p.is_file():
        return file_hash(p)
    if p.is_dir():  # a folder of PSF planes
        h = hashlib.sha256()
        for f in sorted(q for q in p.iterdir() if q.is_file()):
            h.update(f.name.encode())
            h.update(file_hash(f).encode())
        return "dir:" + h.hexdigest()
    return None


def input_hashes(item: Item) -> dict[str, str | None]:
    """SHA-256 of every input file of the item (None for a file that is absent)."""
    return {name: _hash_path(path) for name, path in item.inputs}


def item_hash(item: Item, hashes: dict[str, str | None] | None = None) -> str:
    """One hash of the item's method, options and input contents: equal hashes, equal results."""
    hashes = input_hashes(item) if hashes is None else hashes
    doc = {"method": item.method, "argv": list(item.argv), "spec_data": item.spec_data,
           "truth": item.truth, "inputs": hashes}
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()


class _CheckedCsv:
    """A ``csv.DictReader`` whose ``csv.Error`` is a one-line ValueError (manifest and line).

    ``csv.Error`` (a field over csv's size limit) is no ValueError: it was a traceback.
    """

    def __init__(self, reader: Any, path: Path) -> None:
        self._reader, self._path = reader, path

    def _error(self, exc: Exception) -> ValueError:
        return ValueError(f"{self._path}:{self._reader.line_num}: not readable as CSV ({exc})")

    @property
    def fieldnames(self) -> Any:
        try:
            return self._reader.fieldnames
        except csv.Error as exc:
            raise self._error(exc) from None

    def __iter__(self) -> Any:
        return self

    def __next__(self) -> Any:
        try:
            return next(self._reader)
        except csv.Error as exc:
            raise self._error(exc) from None
