"""UDN settings suggested for one measurement by a saved plan or trade (Qt-free).

A plan (``recon.plan.Plan.to_json``) or a trade folder (``trade.csv``) is offered for a
measurement when it records the hashes of that measurement and its PSF (:func:`input_hashes`):
a plan file carries them under ``"inputs"`` (``Plan.from_json`` ignores the extra key), a
trade folder in ``inputs.json`` beside ``trade.csv``. One made on another measurement with the
same PSF (another frame of the same camera: a live camera's frames all differ, so its plans
were never offered again) is offered after those, marked as such
(:attr:`Suggestion.same_measurement` False); one of another PSF never. Plans and
trades are read by their one reader each (``Plan.from_json``, ``recon.trade.read_trade_csv``).

What each gives the UDN job (keys of :attr:`Suggestion.settings`):

- plan: ``downsample`` (its resolution analysis holds for any method); a ``udn`` plan also its
  ``iterations`` as ``max_iter`` (when > 0) and its budget as ``time_limit_s``.
- trade: the UDN row of the best quality (true PSNR where every UDN row has it, else the
  held-out proxy): ``channels``, ``precision``, ``downsample``, ``iterations`` as ``max_iter``.

Beyond these, :attr:`Suggestion.spec` holds the whole UDN settings the row recorded
(``udn_settings``, :func:`recon.trade.udn_settings`; a ``udn`` plan's :attr:`recon.plan.Plan.udn`)
as sections of a UDN job spec (:func:`udn_spec_sections`), so the job runs the network and
settings that were measured, not the defaults; a recorded setting no spec key takes is named
in :attr:`Suggestion.not_carried`. A trade.csv from before the settings were recorded gives
none, and its detail says so.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = [
    "INPUTS_FILE",
    "TRADE_INPUTS_FORMAT",
    "Suggestion",
    "find_suggestions",
    "from_plan",
    "from_trade_rows",
    "input_hashes",
    "input_hashes_of_files",
    "inputs_match",
    "udn_spec_sections",
    "write_plan_suggestion",
    "write_trade_inputs",
]

#: Beside a ``trade.csv``: the hashes of the measurement and PSF the trade was measured on.
INPUTS_FILE = "inputs.json"
#: the format name of a trade folder's inputs.json
TRADE_INPUTS_FORMAT = "lenslesscam.trade_inputs"


def input_hashes(meas: Any, psf: Any) -> dict[str, str]:
    """Hashes of a raw measurement and its PSF (as float32, so uint16 and float agree)."""
    import numpy as np

    from recon.formats import array_hash

    return {"measurement": array_hash(np.asarray(meas, dtype=np.float32)),
            "psf": array_hash(np.asarray(psf, dtype=np.float32))}


def input_hashes_of_files(meas_path: str | os.PathLike[str],
                          psf_path: str | os.PathLike[str]) -> dict[str, str]:
    """:func:`input_hashes` of a measurement file and a PSF file, read as the app holds them.

    The measurement as its raw counts (a snapshot's ``frame.pixels``: no dark, no scaling;
    the first channel of a colour file), the PSF through :func:`recon.readers.load_psf_any`,
    the reader the app loads PSFs with; so ``plan --out`` and ``trade`` of a snapshot are
    offered in the app's job dialog for that snapshot.
    """
    from recon.inputwarnings import collect_input_warnings
    from recon.readers import load_measurement, load_psf_any

    # read again only to be hashed: what the files hold was said (or not) by the command's
    # own read with the user's settings ("no dark level" was printed here despite --dark);
    # kept quiet in this thread only (a catch of warnings is process-wide)
    with collect_input_warnings(emit=False):
        meas = load_measurement(meas_path, normalise=None)[0]
        psf = load_psf_any(psf_path)
    return input_hashes(meas, psf)


def _match(recorded: Any, hashes: Mapping[str, str]) -> bool | None:
    """Whether ``recorded`` is this measurement (True), another one of this PSF (False).

    None: another PSF, or nothing recorded.
    """
    if inputs_match(recorded, hashes):
        return True
    if isinstance(recorded, Mapping) and hashes.get("psf") and recorded.get(
            "psf") == hashes.get("psf"):
        return False
    return None


def inputs_match(recorded: Any, hashes: Mapping[str, str]) -> bool:
    """True when ``recorded`` names the same measurement and PSF as ``hashes``."""
    if not isinstance(recorded, Mapping):
        return False
    return all(recorded.get(k) == hashes.get(k) and hashes.get(k)
               for k in ("measurement", "psf"))


def udn_spec_sections(udn: Mapping[str, Any] | None
                      ) -> tuple[dict[str, dict[str, Any]], tuple[str, ...]]:
    """Recorded UDN settings as UDN job-spec sections, and the ones no spec key takes.

    ``udn``: ``{"network": NetworkConfig fields, "config": UDNConfig fields}``
    (:func:`recon.trade.udn_settings`, :attr:`recon.plan.Plan.udn`). A network setting goes to
    the spec's ``network`` section, a run setting to whichever of ``optimizer``, ``stopping``,
    ``device`` and ``output`` (``average_every``) has its key (:data:`recon.udn.spec.SCHEMA`);
    a ``gain`` of None is the spec's ``'auto'``. ``max_iter`` and ``time_limit_s`` are left
    out (the suggestion's own ``max_iter`` / ``time_limit_s`` are the run's limits). The
    names (``part.key``) of settings no spec key takes (a trade of another release) are
    returned, not dropped silently.
    """
    from recon.udn.spec import SCHEMA

    sections: dict[str, dict[str, Any]] = {}
    missing: list[str] = []
    for part, where in (("network", ("network",)),
                        ("config", ("optimizer", "stopping", "device", "output"))):
        given = (udn or {}).get(part)
        for key, value in (given.items() if isinstance(given, Mapping) else ()):
            if part == "config" and key in ("max_iter", "time_limit_s"):
                continue
            section = next((sec for sec in where if key in SCHEMA[sec]), None)
            if section is None:
                missing.append(f"{part}.{key}")
                continue
            if part == "config" and key == "gain" and value is None:
                value = "auto"
            sections.setdefault(section, {})[key] = value
    return sections, tuple(missing)


@dataclass(frozen=True)
class Suggestion:
    """UDN job settings from one plan or trade file, and where they came from.

    ``settings``: the values the dialog's list shows (flat keys); ``spec``: UDN job-spec
    sections with every recorded UDN setting (:func:`udn_spec_sections`; empty when none was
    recorded); ``not_carried``: recorded settings no spec key takes.
    """

    source: str  # "plan" | "trade"
    path: Path
    created: str  # ISO date-time (the file's record, else its modification time)
    settings: dict[str, Any] = field(default_factory=dict)
    detail: str = ""
    spec: dict[str, dict[str, Any]] = field(default_factory=dict)
    not_carried: tuple[str, ...] = ()
    #: made on this measurement (False: on another one with the same PSF)
    same_measurement: bool = True

    @property
    def origin(self) -> str:
        """``from plan <file>, <date>`` / ``from trade <folder>, <date>``."""
        name = self.path.name if self.source == "plan" else str(self.path.parent.name)
        return f"from {self.source} {name}, {self.created[:16].replace('T', ' ')}"

    @property
    def label(self) -> str:
        """One line for a list: kind, date, the values, the file."""
        vals = ", ".join(f"{k}={v}" for k, v in self.settings.items())
        n = sum(len(keys) for keys in self.spec.values())
        if n:
            vals += f", +{n} recorded UDN settings"
        when = self.created[:16].replace("T", " ")
        name = self.path.name if self.source == "plan" else self.path.parent.name
        other = "" if self.same_measurement else " - another frame, same PSF"
        return f"{self.source} {when}{other}: {vals} ({name})"


def _mtime(path: Path) -> str:
    t = _dt.datetime.fromtimestamp(path.stat().st_mtime, _dt.UTC)
    return t.isoformat(timespec="seconds")


def from_plan(plan: Any, path: Path, created: str) -> Suggestion:
    """The UDN settings a :class:`recon.plan.Plan` implies."""
    s: dict[str, Any] = {"downsample": int(plan.downsample)}
    spec: dict[str, dict[str, Any]] = {}
    missing: tuple[str, ...] = ()
    detail = f"{plan.model} plan, method {plan.method}"
    if plan.method == "udn":
        if plan.iterations > 0:
            s["max_iter"] = int(plan.iterations)
        if plan.budget_s is not None:
            s["time_limit_s"] = float(plan.budget_s)
        spec, missing = udn_spec_sections(plan.udn)
        detail += _carried_text(spec, missing, plan.udn is not None,
                                "the plan names no UDN settings (the UDN's defaults)")
    return Suggestion("plan", Path(path), created, s, detail, spec, missing)


def _carried_text(spec: Mapping[str, Mapping[str, Any]], missing: tuple[str, ...],
                  recorded: bool, none: str) -> str:
    """The detail's words on the recorded UDN settings a suggestion carries."""
    if not recorded:
        return f"; {none}"
    n = sum(len(keys) for keys in spec.values())
    text = f"; its {n} recorded UDN settings go to the job's spec"
    if missing:
        text += (f"; not carried (settings this release's UDN job spec does not have): "
                 f"{', '.join(missing)}")
    return text


def from_trade_rows(rows: Iterable[Any], path: Path, created: str) -> Suggestion | None:
    """The best UDN setting of a trade's rows (None when the trade has no UDN row)."""
    udn = [r for r in rows if r.method == "udn"]
    if not udn:
        return None
    key = "psnr" if all(r.psnr is not None for r in udn) else "heldout_psnr"
    best = max(udn, key=lambda r: float(getattr(r, key)))
    s = {"channels": int(best.channels), "precision": str(best.precision),
         "downsample": int(best.downsample), "max_iter": int(best.iterations)}
    recorded = getattr(best, "udn_settings", None)
    spec, missing = udn_spec_sections(recorded)
    detail = (f"{best.setting}: {getattr(best, key):.2f} dB "
              f"{'PSNR' if key == 'psnr' else 'held-out'} in {best.wall_s:.2f} s")
    detail += _carried_text(spec, missing, recorded is not None,
                            "its row records no UDN settings (a trade.csv written before they "
                            "were recorded): only channels, precision, downsampling and "
                            "iterations are suggested, the rest are the job's defaults")
    return Suggestion("trade", Path(path), created, s, detail, spec, missing)


def _read_plan_file(path: Path, hashes: Mapping[str, str],
                    shape: tuple[int, int] | None = None) -> Suggestion | None:
    from recon.plan import Plan

    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    same = _match(d.get("inputs"), hashes) if isinstance(d, dict) else None
    if same is None:
        return None
    size = d.get("measurement_window") or d.get("sensor")
    if not same and shape is not None and isinstance(size, list) and tuple(size) != tuple(shape):
        return None  # another frame of another size (a camera ROI): recon auto refuses it too
    try:
        plan = Plan.from_json(d)
    except (ValueError, TypeError):
        return None
    created = str(d.get("created_utc") or _mtime(path))
    return _marked(from_plan(plan, path, created), same)


def _marked(s: Suggestion | None, same: bool) -> Suggestion | None:
    if s is None or same:
        return s
    return dataclasses.replace(s, same_measurement=False,
                               detail="made on another measurement with this PSF; " + s.detail)


def _read_trade_folder(csv_path: Path, hashes: Mapping[str, str]) -> Suggestion | None:
    from recon.trade import read_trade_csv

    try:
        rec = json.loads((csv_path.parent / INPUTS_FILE).read_text())
    except (OSError, ValueError):
        return None
    same = _match(rec, hashes) if isinstance(rec, dict) else None
    if same is None:
        return None
    from recon.formats import FORMAT_VERSION, whole_version

    version = whole_version(rec.get("format_version", 1))  # none: version 1
    if rec.get("format", TRADE_INPUTS_FORMAT) != TRADE_INPUTS_FORMAT or not (
            version is not None and version <= FORMAT_VERSION):
        return None  # another file, or a newer version than this release reads
    try:
        rows = read_trade_csv(csv_path)
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return _marked(from_trade_rows(rows, csv_path, str(rec.get("created_utc")
                                                       or _mtime(csv_path))), same)


def find_suggestions(folders: Iterable[str | os.PathLike[str]],
                     hashes: Mapping[str, str],
                     shape: tuple[int, int] | None = None) -> list[Suggestion]:
    """Plans (``*.json``) and trades (``*/trade.csv``) in ``folders`` made for ``hashes``.

    Those of this measurement first, then those of another one with the same PSF (and, for a
    plan, made for a measurement of ``shape`` when it is given), each newest first; files of
    another PSF, unreadable files and trades without a UDN row are left out.
    """
    found: list[Suggestion] = []
    for folder in folders:
        root = Path(folder)
        if not root.is_dir():
            continue
        for p in sorted(root.glob("*.json")):
            s = _read_plan_file(p, hashes, shape)
            if s is not None:
                found.append(s)
        for p in sorted([*root.glob("trade.csv"), *root.glob("*/trade.csv")]):
            s = _read_trade_folder(p, hashes)
            if s is not None:
                found.append(s)
    return sorted(found, key=lambda s: (s.same_measurement, s.created), reverse=True)


def write_plan_suggestion(folder: str | os.PathLike[str], plan: Any,
                          hashes: Mapping[str, str]) -> Path:
    """Save ``plan`` with the inputs' hashes in ``folder`` (``plan-<measurement>-<time>.json``)."""
    from recon.atomic import atomic_write_json

    Path(folder).mkdir(parents=True, exist_ok=True)
    now = _dt.datetime.now(_dt.UTC)
    d = plan.to_json()
    d["inputs"] = dict(hashes)
    d["created_utc"] = now.isoformat(timespec="seconds")
    stem = f"plan-{hashes['measurement'][:8]}-{now.strftime('%Y%m%d-%H%M%S')}"
    path, n = Path(folder) / f"{stem}.json", 1
    while path.exists():
        n += 1
        path = Path(folder) / f"{stem}-{n}.json"
    return atomic_write_json(path, d)


def write_trade_inputs(folder: str | os.PathLike[str], hashes: Mapping[str, str]) -> Path:
    """Record beside a trade's ``trade.csv`` which measurement and PSF it was measured on."""
    from recon.atomic import atomic_write_json

    Path(folder).mkdir(parents=True, exist_ok=True)
    now = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    from recon.formats import FORMAT_VERSION

    return atomic_write_json(Path(folder) / INPUTS_FILE, {
        "format": TRADE_INPUTS_FORMAT, "format_version": FORMAT_VERSION, **hashes,
        "created_utc": now})
