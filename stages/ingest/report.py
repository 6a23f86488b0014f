"""Rows of the ingest report: what was dropped, quarantined or flagged, by file and record."""
from __future__ import annotations

from dataclasses import dataclass, field

KINDS = ("quarantined_file", "dropped_points", "timestamp", "gnss_gap", "ring_coverage", "gnss_row", "gnss_default",
         "gnss_coverage", "deskew", "scan_gap", "prior")


@dataclass
class IngestReport:
    rows: list[dict] = field(default_factory=list)

    def add(self, kind: str, file: str, record: int | None, count: int, reason: str) -> None:
        if kind not in KINDS:
            raise ValueError(f"report kind {kind!r}, expected one of {', '.join(KINDS)}")
        self.rows.append({"kind": kind, "file": file, "record": record, "count": int(count), "reason": reason})

    def count(self, kind: str) -> int:
        return sum(1 for r in self.rows if r["kind"] == kind)

    def to_table(self, drive: str):
        import pyarrow as pa

        from schemas import SCHEMAS

        columns = {name: [r[name] for r in self.rows] for name in ("kind", "file", "record", "count", "reason")}
        return pa.table({"drive": [drive] * len(self.rows), **columns}, schema=SCHEMAS["ingest_report"])
