"""The summary tables of a batch: ``summary.csv`` and ``summary.md`` (one row per item)."""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from app.batch.manifest import Item

__all__ = ["COLUMNS", "summary_rows", "write_summary"]

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
                  status: dict[str, str]) -> list[Path]:
    """Write ``summary.csv`` and ``summary.md`` in ``root`` (atomically); their paths."""
    from app.batch.state import now_utc
    from recon.atomic import atomic_write_bytes
    from recon.formats import FORMAT_VERSION

    rows = summary_rows(items, records, status)
    buf = io.StringIO()
    wr = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
    wr.writeheader()
    wr.writerows(rows)
    csv_path = atomic_write_bytes(root / "summary.csv", buf.getvalue().encode("utf-8"))
    counts: dict[str, int] = {}
    for r in rows:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
    md = [f"# Batch summary: {root.name}", "",
          f"(format {SUMMARY_FORMAT}, version {FORMAT_VERSION}, written {now_utc()}; the item "
          "records are in items/ID.json)", "",
          f"{len(rows)} items: " + ", ".join(f"{n} {k}" for k, n in sorted(counts.items())),
          "", "| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in rows:
        cells = [r[c].replace("|", "/").replace("\n", " ") for c in COLUMNS]
        md.append("| " + " | ".join(cells) + " |")
    md_path = atomic_write_bytes(root / "summary.md", ("\n".join(md) + "\n").encode("utf-8"))
    return [csv_path, md_path]
