"""``cornermap maps show``: a map's frame, its versions with their standing, and each drive with its recording span
and the versions holding it; for a map with an identity (``maps create``) or without (made by ``cornermap build``)."""
from __future__ import annotations

from datetime import datetime, timezone
from pathlib import Path

from pipeline import storage
from pipeline.names import inside
from pipeline.version_read import state_note, version_states


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
    from pipeline.safe_yaml import load_yaml, load_yaml_file

    try:
        if storage.uri_scheme(drive_yaml) is not None:  # a drive in a bucket: its drive file read from there
            from pipeline.drive_store import read_drive_file

            doc = load_yaml(read_drive_file(drive_yaml), drive_yaml) or {}
        else:
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


def _mark(version: int, state: str) -> str:
    from pipeline.version_read import version_name

    return version_name(version) + {"LATEST": "*", "refused": "(refused)", "candidate": "(candidate)"}.get(state, "")


def show_doc(mdir: Path, root: "str | Path | None" = None) -> dict:
    """What ``cornermap maps show`` says, as data (its ``--json``): the frame (``identity`` None for a map made by
    ``cornermap build``), each version with its standing, each drive; UnknownNameError for a folder with neither an
    identity nor a version. ``root``: the output root the datasets are read from when ``mdir`` is a local view of a
    map on an object store (default: the root holding ``mdir``)."""
    from mapservice.maps import latest_origin, read_identity
    from pipeline.errors import CornermapError, UnknownNameError
    from pipeline.version_read import list_versions, read_latest, read_manifest, version_name

    ident = read_identity(mdir)
    versions = list_versions(mdir)
    if ident is None and not versions:
        raise UnknownNameError(f"{mdir}: no map here (neither {storage.IDENTITY} nor a published version); hint: "
                               "--root is the folder holding maps/NAME")
    doc: dict = {"map": Path(mdir).name, "path": str(mdir), "identity": None, "enu_origin": None,
                 "latest": None, "versions": [], "drives": drive_rows(mdir, ident)}
    if ident is not None:
        doc["identity"] = {"tile_size_m": ident.tile_size_m, "max_radius_km": ident.max_radius_km,
                           "created_utc": ident.created_utc,
                           "check_drive": ident.check_drive.model_dump() if ident.check_drive else None}
        doc["enu_origin"] = ident.enu_origin.plain()
    elif storage.latest_file(Path(mdir)).exists():
        doc["enu_origin"] = latest_origin(mdir)
    if storage.latest_file(Path(mdir)).exists():
        latest = read_latest(mdir)
        doc["latest"] = version_name(latest) if latest is not None else None
    doc["drift"] = latest_drift(mdir, root)
    states = version_states(mdir)
    for v in versions:
        try:
            m = read_manifest(Path(mdir) / version_name(v))[0]
            created, n = str(m.get("created_utc", "?"))[:19], len(m.get("source_drives", []))
        except CornermapError:
            created, n = "unreadable manifest", None
        doc["versions"].append({"version": version_name(v), "created_utc": created, "drives": n,
                                "standing": states[v] or None, "note": state_note(mdir, v, states[v]) or None})
    return doc


def show_lines(mdir: Path, root: "str | Path | None" = None) -> list[str]:
    """The text of ``cornermap maps show`` (``show_doc`` in words)."""
    doc = show_doc(mdir, root)
    o, ident = doc["enu_origin"], doc["identity"]
    lines = []
    if ident is not None:
        lines.append(f"map {doc['map']}: origin {o['lat_deg']},{o['lon_deg']},{o['h_m']} (WGS84), tiles "
                     f"{ident['tile_size_m']} m, area {ident['max_radius_km']:g} km around the origin, created "
                     f"{ident['created_utc']}"
                     + (f", check drive {ident['check_drive']['path']}" if ident["check_drive"] else ""))
    else:
        from stages.common.geodesy import EnuOrigin

        lines.append(f"map {doc['map']}: no identity (made by `cornermap build`; `cornermap maps create` pins "
                     "its frame for rebuilds)"
                     + (f"; origin {EnuOrigin.validate(o).text()} (WGS84) of LATEST {doc['latest']}"
                        if o and doc["latest"] else ""))
    lines.append(f"{'version':9s} {'created (UTC)':20s} {'drives':>6s}  standing")
    for v in doc["versions"]:
        note = "LATEST" if v["standing"] == "LATEST" else (v["note"] or "")
        n = "?" if v["drives"] is None else str(v["drives"])
        lines.append(f"{v['version']:9s} {v['created_utc']:20s} {n:>6s}  {note}".rstrip())
    lines += localizability_lines(mdir)
    lines += drift_lines(doc["drift"])
    rows = doc["drives"]
    lines.append(f"{'drive':16s} {'first pose':20s} {'last pose':20s} {'added (UTC)':20s} versions")
    lines += [f"{r['name']:16s} {r['first']:20s} {r['last']:20s} {r['added']:20s} {r['versions']}" for r in rows]
    if not rows:
        lines.append("(no drives yet: cornermap rebuild --root ROOT --map NAME --inbox DIR)")
    return lines


def localizability_lines(mdir: Path, limit: int = 10) -> list[str]:
    """LATEST's localizability summary (its manifest's ``localizability``: the tiles stage's prediction of the
    localizers' uncertainty per cell of the roads): the median and p95 per method and the cells predicted weak or
    failing, worst first, with their reason. Nothing for a version without one."""
    from pipeline.errors import CornermapError
    from pipeline.version_read import read_latest, read_manifest, version_name

    try:
        latest = read_latest(mdir) if storage.latest_file(Path(mdir)).exists() else None
        loc = read_manifest(Path(mdir) / version_name(latest))[0].get("localizability") if latest else None
    except CornermapError:
        return []
    if not isinstance(loc, dict) or not isinstance(loc.get("methods"), dict):
        return []
    head = f"localizability of {version_name(latest)} ({loc.get('n_cells')} cells of {loc.get('cell_m'):g} m): "
    out = [head + "; ".join(f"{m} sigma_2d median {v.get('median_sigma_2d_m')} m, p95 {v.get('p95_sigma_2d_m')} m, "
                            f"{v.get('n_weak')} weak" for m, v in sorted(loc["methods"].items()))]
    weak = loc.get("weak_cells") or []
    for w in weak[:limit]:
        out.append(f"  {w.get('status', 'weak'):4s} {w['method']} at ENU ({w['east_m']:.1f}, {w['north_m']:.1f}) m: "
                   f"sigma_2d {w['sigma_2d_m']:.3f} m, {w['reason']}")
    if len(weak) > limit:
        out.append(f"  ... {len(weak) - limit} more in the manifest's localizability.weak_cells; every cell in "
                   "tiles/*/localizability.parquet")
    return out


def drive_rows(mdir: Path, ident) -> list[dict]:
    """name, first, last (recording span of the drive's poses in its time base), added, versions holding it. Without
    an identity (``ident`` None): the drives the versions hold, their time base unknown."""
    from pipeline.errors import CornermapError
    from pipeline.version_read import list_versions, read_manifest, version_name

    states = version_states(mdir)
    held: dict[str, list[str]] = {}
    span: dict[str, tuple[float, float]] = {}
    for v in list_versions(mdir):
        try:
            manifest = read_manifest(mdir / version_name(v))[0]
        except CornermapError:
            continue
        for d in manifest.get("source_drives", []):
            held.setdefault(d["drive"], []).append(_mark(v, states.get(v, "")))
            try:
                got = _first_last_s(inside(mdir / version_name(v), d["trajectory"]))
            except (OSError, ValueError, CornermapError):
                got = None
            if got is not None:
                span[d["drive"]] = got
    rows = []
    drives = [(d.name, d.path, d.added_utc[:19]) for d in ident.drives] if ident is not None else \
        [(name, None, "-") for name in sorted(held)]
    for name, path, added in drives:
        first, last = span.get(name, (None, None))
        base = _time_base(path) if path else "?"
        rows.append({"name": name, "first": _when(first, base), "last": _when(last, base), "added": added,
                     "versions": " ".join(held.get(name, [])) or "-"})
    return rows


def latest_drift(mdir: Path, root: "str | Path | None" = None) -> dict | None:
    """The drift statistic of LATEST's pose graph (``stages/posegraph/drift.py``; written by an incremental rebuild
    into its ``poses_optimized`` dataset's metadata), with ``version``; None for a joint or reoptimized solve, a
    version without it, or a dataset not under the map's root (``root``, default the one holding ``mdir``; an
    ``s3://`` root's manifest is read from the bucket)."""
    from pipeline.errors import CornermapError
    from pipeline.store import data_root
    from pipeline.version_read import read_latest, version_name
    from pipeline.version_read import read_manifest as read_version_manifest

    try:
        latest = read_latest(mdir) if storage.latest_file(Path(mdir)).exists() else None
        if latest is None:
            return None
        poses = (read_version_manifest(Path(mdir) / version_name(latest))[0].get("inputs") or {}).get("poses") or {}
        if poses.get("dataset") != "poses_optimized" or not poses.get("fingerprint"):
            return None
        m = data_root(root if root is not None else storage.root_of_map(Path(mdir))).manifest(
            "poses_optimized", poses["fingerprint"])
    except (CornermapError, OSError, ValueError):
        return None
    drift = (((m or {}).get("extra") or {}).get("incremental") or {}).get("drift")
    return {**drift, "version": version_name(latest)} if isinstance(drift, dict) else None


def drift_lines(drift: dict | None) -> list[str]:
    """``reoptimize advised: region R ...`` per region whose statistic exceeds its threshold, else one line saying
    none is (with the largest share of its threshold); nothing without a statistic."""
    if not drift:
        return []
    return _frame_lines(drift) + _region_lines(drift)


def _frame_lines(drift: dict) -> list[str]:
    """The window's frame test (``stages/posegraph/window.py``): is the held map's frame where it says it is?"""
    f = drift.get("frame")
    if not isinstance(f, dict) or not f.get("dof"):
        return []
    what = (f"the held map's frame moved ({f['shift_en_m'][0]:+.3f}, {f['shift_en_m'][1]:+.3f}) m, "
            f"{f['rotation_deg']:+.3f} deg in {drift['version']}'s window of {f['window_poses']} poses; "
            f"statistic {f['chi2']:.1f}")
    if f.get("advised"):
        return [f"reoptimize advised: {what} > threshold {f['threshold']:.1f} (the map is off by more than its frame "
                "covariance states; poses outside the window keep it); run `cornermap maps reoptimize`"]
    return [f"drift: frame consistent ({what} of threshold {f['threshold']:.1f})"]


def _region_lines(drift: dict) -> list[str]:
    rows = [r for r in drift.get("regions", []) if r.get("loops")]
    where = f"{drift['version']}'s incremental solve, chi2 of the new drives' loops onto the map per region"
    advised = [r for r in rows if r.get("advised")]
    if advised:
        return [f"reoptimize advised: region {r['region']} at ENU ({r['center_en_m'][0]:.0f}, "
                f"{r['center_en_m'][1]:.0f}) m, statistic {r['chi2']:.1f} > threshold {r['threshold']:.1f} "
                f"({r['loops']} loops; {where}); run `cornermap maps reoptimize`" for r in advised]
    if not rows:
        return [f"drift: no loop of the new drives reached the map ({drift['version']}); nothing to test"]
    worst = max(rows, key=lambda r: r["chi2"] / r["threshold"])
    return [f"drift: no region advised for reoptimize ({where}: largest {worst['chi2']:.1f} of threshold "
            f"{worst['threshold']:.1f}, region {worst['region']}, {worst['loops']} loops)"]
