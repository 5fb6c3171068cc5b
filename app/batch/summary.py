"""The summary tables of a batch: ``summary.csv`` and ``summary.md`` (one row per item).

``summary.csv`` starts with ``# key: value`` lines (:mod:`recon.csvmeta`): ``format``
(:data:`SUMMARY_FORMAT`), ``format_version``, provenance, the batch folder, its manifest and the
counts; then the table (:data:`COLUMNS`). pandas reads it with ``comment="#"``;
:func:`read_summary` is its one reader (a file from before the header reads as version 0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from app.batch.manifest import Item

__all__ = ["COLUMNS", "SUMMARY_FORMAT", "SummaryFile", "read_summary", "summary_rows",
           "write_summary"]

SUMMARY_FORMAT = "lenslesscam.batch_summary"
#: Columns of the tables, in order.
COLUMNS = ("id", "method", "status", "attempt", "time_s", "iterations", "stop_reason",
           "final_loss", "residual", "psnr", "ssim", "output", "error")


def _num(v: Any, fmt: str = ".4g") -> str:
    if v is None or v == "":
        return ""
    if isinstance(v, float):
        return format(v, fmt) if math.isfinite(v) else str(v)
    return str(v)


def summary_rows(items: list[Item], records: dict[str, dict[str, Any]],
                 status: dict[str, str]) -> list[dict[str, str]]:
    """One row per item (manifest order): status of this run, time, loss, metrics."""
    rows = []
    for it in items:
        rec = records.get(it.id, {})
        st = status.get(it.id, rec.get("status", "pending"))
        metrics = rec.get("metrics") or {}
        rows.append({
            "id": it.id, "method": it.method,
            "status": "done (earlier run)" if st == "skipped" else st,
            "attempt": _num(rec.get("attempt")), "time_s": _num(rec.get("time_s"), ".3f"),
            "iterations": _num(rec.get("iterations")),
            "stop_reason": _num(rec.get("stop_reason")),
            "final_loss": _num(rec.get("loss")), "residual": _num(rec.get("residual")),
            "psnr": _num(metrics.get("psnr"), ".2f"), "ssim": _num(metrics.get("ssim"), ".3f"),
            "output": _num(rec.get("output")),
            "error": str(rec.get("error") or rec.get("detail") or "")
            if st in ("failed", "cancelled") else "",
        })
    return rows


def write_summary(root: Path, items: list[Item], records: dict[str, dict[str, Any]],
                  status: dict[str, str], manifest: str | None = None,
                  started_utc: str | None = None) -> list[Path]:
    """Write ``summary.csv`` and ``summary.md`` in ``root`` (atomically); their paths.

    ``manifest`` and ``started_utc`` (the driver's) go into the csv's header.
    """
    from recon.atomic import atomic_write_bytes
    from recon.csvmeta import format_table
    from recon.formats import FORMAT_VERSION, provenance

    rows = summary_rows(items, records, status)
    counts: dict[str, int] = {}
    for r in rows:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
    prov = provenance()
    meta = [("created_utc", prov["created_utc"]), ("host", prov["host"]),
            ("versions", prov["versions"]), ("batch", str(root)),
            ("manifest", manifest), ("started_utc", started_utc),
            ("items", len(rows)), ("counts", dict(sorted(counts.items())))]
    text = format_table(SUMMARY_FORMAT, FORMAT_VERSION,
                        [(k, v) for k, v in meta if v is not None], COLUMNS, rows)
    csv_path = atomic_write_bytes(root / "summary.csv", text.encode("utf-8"))
    md = [f"# Batch summary: {root.name}", "",
          f"(format {SUMMARY_FORMAT}, version {FORMAT_VERSION}, written {prov['created_utc']}; "
          "the item records are in items/ID.json)", "",
          f"{len(rows)} items: " + ", ".join(f"{n} {k}" for k, n in sorted(counts.items())),
          "", "| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in rows:
        cells = [r[c].replace("|", "/").replace("\n", " ") for c in COLUMNS]
        md.append("| " + " | ".join(cells) + " |")
    md_path = atomic_write_bytes(root / "summary.md", ("\n".join(md) + "\n").encode("utf-8"))
    return [csv_path, md_path]


@dataclass
class SummaryFile:
    """A batch's ``summary.csv`` as read."""

    path: Path
    format_version: int  # 0: a file from before the header (no metadata)
    meta: dict[str, Any]  # the header's values (batch, manifest, counts, provenance)
    rows: list[dict[str, str]]  # one per item, keyed by COLUMNS (and any later columns)


def read_summary(path: str | Path) -> SummaryFile:
    """Read a batch's ``summary.csv``, with or without its header.

    The one reader of the file kind: a newer format version or another file is refused
    (:class:`recon.formats.FormatError`, naming the file).
    """
    from recon.csvmeta import read_table
    from recon.formats import FORMAT_VERSION

    table = read_table(path, SUMMARY_FORMAT, FORMAT_VERSION, "batch summary.csv")
    missing = [c for c in COLUMNS if c not in table.fieldnames]
    if missing:
        raise ValueError(f"{path}: not a batch summary.csv (no column {', '.join(missing)})")
    return SummaryFile(Path(path), table.format_version, table.meta,
                       [row for _, row in table.rows])
