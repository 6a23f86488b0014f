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


GPS_EPOCH = datetime(1980, 1, 6, tzinfo=timezone.utc)


def _time_base(drive_yaml: str) -> str:
    """The drive's time base (``gnss.time.base`` of its drive file: gps by default, docs/drive-file.md)."""
    from pipeline.safe_yaml import load_yaml_file

    try:
        doc = load_yaml_file(Path(drive_yaml)) or {}
    except Exception:  # noqa: BLE001 - a drive file gone or unreadable: the dates are shown as unknown
        return "?"
    gnss = doc.get("gnss") if isinstance(doc, dict) else None
    return str(((gnss or {}).get("time") or {}).get("base", "gps")) if gnss else "?"


def _when(t_s: float | None, base: str) -> str:
    """A stamp as a calendar time: GPS time (no leap seconds) labelled GPS, unix time labelled UTC."""
    if t_s is None or base not in ("gps", "unix"):
        return "-"
    from datetime import timedelta

    t = GPS_EPOCH + timedelta(seconds=t_s) if base == "gps" else datetime.fromtimestamp(t_s, timezone.utc)
    return t.strftime("%Y-%m-%d %H:%M") + (" GPS" if base == "gps" else " UTC")


def drive_rows(mdir: Path, ident) -> list[dict]:
    """name, first, last (recording span of the drive's poses in its time base), added, versions holding it."""
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
        base = _time_base(d.path)
        rows.append({"name": d.name, "first": _when(first, base), "last": _when(last, base), "added": d.added_utc[:19],
                     "versions": " ".join(held.get(d.name, [])) or "-"})
    return rows
