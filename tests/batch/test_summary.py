"""The batch's summary.csv: a ``# key: value`` header (format, version, metadata), its reader."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from app.batch.manifest import Item
from app.batch.summary import COLUMNS, read_summary, summary_rows, write_summary
from recon.formats import FORMAT_VERSION, FormatError

ITEMS = [Item("m00-fista", "fista", ("--iters", "20"), "m.csv:2"),
         Item("m01-udn", "udn", (), "m.csv:3"),
         Item("m02-admm", "admm", (), "m.csv:4")]
RECORDS = {
    "m00-fista": {"status": "done", "attempt": 1, "time_s": 1.25, "iterations": 20,
                  "stop_reason": "max_iter", "loss": 0.5, "residual": 0.02,
                  "metrics": {"psnr": 21.5, "ssim": 0.7}, "output": "results/m00-fista.tif"},
    "m02-admm": {"status": "failed", "attempt": 1, "error": "item #3: PSF 24x28, measurement "
                 "12x14, they must match"},
}
STATUS = {"m00-fista": "done", "m01-udn": "cancelled", "m02-admm": "failed"}


def test_summary_csv_has_a_header_and_reads_back(tmp_path: Path) -> None:
    csv_path, md_path = write_summary(tmp_path, ITEMS, RECORDS, STATUS, "/data/m.csv",
                                      "2026-01-01T00:00:00+00:00")
    lines = csv_path.read_text(encoding="utf-8").splitlines()
    assert lines[:2] == ["# format: lenslesscam.batch_summary",
                         f"# format_version: {FORMAT_VERSION}"]
    table = [ln for ln in lines if not ln.startswith("#")]
    assert table[0] == ",".join(COLUMNS) and len(table) == 4
    # the error has a '#': its row is quoted, so pandas (comment="#") keeps it whole
    assert table[3].startswith('"m02-admm","admm","failed"')
    s = read_summary(csv_path)
    assert s.format_version == FORMAT_VERSION
    assert s.rows == summary_rows(ITEMS, RECORDS, STATUS)
    assert s.meta["manifest"] == "/data/m.csv" and s.meta["batch"] == str(tmp_path)
    assert s.meta["items"] == 3 and s.meta["counts"] == {"cancelled": 1, "done": 1, "failed": 1}
    assert s.meta["started_utc"] == "2026-01-01T00:00:00+00:00" and "created_utc" in s.meta
    assert f"version {FORMAT_VERSION}" in md_path.read_text()


def test_old_summary_csv_without_header_is_still_read(tmp_path: Path) -> None:
    rows = summary_rows(ITEMS, RECORDS, STATUS)
    with open(tmp_path / "summary.csv", "w", encoding="utf-8", newline="") as fh:
        wr = csv.DictWriter(fh, fieldnames=COLUMNS, lineterminator="\n")  # the old writer
        wr.writeheader()
        wr.writerows(rows)
    s = read_summary(tmp_path / "summary.csv")
    assert s.format_version == 0 and s.meta == {} and s.rows == rows


def test_newer_or_foreign_summary_csv_is_refused_in_one_line(tmp_path: Path) -> None:
    path = write_summary(tmp_path, ITEMS, RECORDS, STATUS)[0]
    text = path.read_text(encoding="utf-8")
    path.write_text(text.replace(f"# format_version: {FORMAT_VERSION}\n",
                                 f"# format_version: {FORMAT_VERSION + 1}\n"), encoding="utf-8")
    with pytest.raises(FormatError) as err:
        read_summary(path)
    assert str(err.value) == (f"{path}: batch summary.csv format version {FORMAT_VERSION + 1} "
                              f"is newer than this lenslesscam reads ({FORMAT_VERSION}); "
                              "update lenslesscam to read it")
    path.write_text(text.replace("lenslesscam.batch_summary", "lenslesscam.trade"),
                    encoding="utf-8")
    with pytest.raises(FormatError, match=r"not a batch summary\.csv \(its format is "
                                          r"'lenslesscam\.trade'"):
        read_summary(path)
    (tmp_path / "x.csv").write_text("a,b\n1,2\n", encoding="utf-8")
    with pytest.raises(ValueError, match=r"x\.csv: not a batch summary\.csv \(no column id, "):
        read_summary(tmp_path / "x.csv")
