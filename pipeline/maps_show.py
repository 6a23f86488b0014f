"""Rows of ``cornermap maps show``: each drive of a map with its recording span and the versions holding it."""
from __future__ import annotations

from datetime import datetime, timezone
from pathlib import Path

from pipeline.names import inside


def _first_last_s(path: Path) -> tuple[float, float] | None:
    """First and last stamp (s) of a TUM trajectory file (comment lines skipped)."""
    first = last = None
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            if line.strip() and not line.startswith("#"):
                t = float(line.split()[0])
                first = t if first is None else first
                last = t
    return None if first is None else (first, last)


def _utc(t_s: float | None) -> str:
    if t_s is None:
        return "-"
    return datetime.fromtimestamp(t_s, timezone.utc).strftime("%Y-%m-%d %H:%M:%S")


def drive_rows(mdir: Path, ident) -> list[dict]:
    """name, first, last (recording span of the drive's poses, UTC), added, versions (the ones that hold it)."""
    from pipeline.errors import CornermapError
    from pipeline.version_read import list_versions, read_latest, read_manifest, version_name

    latest = read_latest(mdir) if (mdir / "LATEST").exists() else None
    held: dict[str, list[str]] = {}
    span: dict[str, tuple[float, float]] = {}
    for v in list_versions(mdir):
        try:
            manifest = read_manifest(mdir / version_name(v))[0]
        except CornermapError:
            continue
        for d in manifest.get("source_drives", []):
            held.setdefault(d["drive"], []).append(version_name(v) + ("*" if v == latest else ""))
            try:
                got = _first_last_s(inside(mdir / version_name(v), d["trajectory"]))
            except (OSError, ValueError, CornermapError):
                got = None
            if got is not None:
                span[d["drive"]] = got
    rows = []
    for d in ident.drives:
        first, last = span.get(d.name, (None, None))
        rows.append({"name": d.name, "first": _utc(first), "last": _utc(last), "added": d.added_utc[:19],
                     "versions": " ".join(held.get(d.name, [])) or "-"})
    return rows
