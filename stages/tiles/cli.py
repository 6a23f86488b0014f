"""``cornermap tiles ls|diff|log|export|verify``: inspect, compare, export and check published map versions.

Heavy imports happen inside the commands so ``cornermap --help`` stays instant.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from pipeline import cli_options as opts

ROOT_OPT = opts.ROOT
MAP_OPT = opts.MAP_OR_ONLY
VERSION_OPT = opts.MAP_VERSION

EXAMPLES = ("Examples:\n\n"
            "  cornermap tiles ls --map tiny --root runs/tiny\n\n"
            "  cornermap tiles diff v0001 LATEST --map tiny --root runs/tiny\n\n"
            "  cornermap tiles log --map tiny --root runs/tiny\n\n"
            "  cornermap tiles export --format geojson --out runs/city.geojson --map city --root runs/maps\n\n"
            "  cornermap tiles export --format geotiff --out runs/rasters --overwrite --map city --root runs/maps\n\n"
            "  cornermap tiles verify --all --map tiny --root runs/tiny\n\n"
            "  cornermap tiles ls --map tiny --root runs/tiny --json\n\n"
            "  cornermap tiles query --at 37.4979,127.0276 --radius 150 --map tiny --root runs/tiny --json\n\n"
            "  cornermap tiles bundle --from v0001 --to v0002 --out runs/city-delta --map city --root runs/maps\n\n"
            "  cornermap tiles apply runs/city-delta --map city --root runs/vehicle\n\n"
            "  cornermap tiles push --map tiny --root runs/tiny --to s3://maps/city-root\n\n"
            "  cornermap tiles verify --map tiny --root s3://maps/city-root")


def map_dir_of(root: Path, name: Optional[str]) -> Path:
    """ROOT/maps/NAME; with no name, the only map under ROOT/maps (``pipeline.names.published_map_dir``)."""
    from pipeline.names import published_map_dir

    return published_map_dir(root, name, hint="pass --map NAME (and --root ROOT)")


def ls(root: Path = opts.ROOT_OR_URI, map_name: Optional[str] = MAP_OPT, as_json: bool = opts.JSON) -> None:
    """List the versions of a map (* marks LATEST) with tiles, corners, parent and creation time; a candidate the
    rebuild's regression gate refused, or one never gated, is marked so. The root may be s3://BUCKET/PREFIX.

    Example: [b]cornermap tiles ls --map tiny --root runs/tiny[/b]
    """
    from pipeline.store_maps import readable_root

    with readable_root(root, map_name, whole=()) as (local_root, shown):
        _ls(local_root, map_name, as_json, shown)


def _ls(root: Path, map_name: Optional[str], as_json: bool, shown) -> None:
    from pipeline.errors import MapFormatError
    from pipeline.version_read import state_note, version_states
    from pipeline.versioned import list_versions, read_latest, read_manifest, version_name

    d = map_dir_of(root, map_name)
    latest = read_latest(d)
    states = version_states(d)
    rows = []
    if not as_json:
        typer.echo(f"{shown(str(d))}  (LATEST = {version_name(latest) if latest is not None else 'none'})")
    for v in list_versions(d):
        mark = "*" if v == latest else " "
        try:
            m, sha = read_manifest(d / version_name(v))
        except MapFormatError as exc:
            rows.append({"version": version_name(v), "latest": v == latest, "error": str(exc)})
            if not as_json:
                typer.echo(f"{mark} {version_name(v)}  unreadable: {exc}")
            continue
        parent = m.get("parent_version")
        note = state_note(d, v, states.get(v, ""))
        rows.append({"version": version_name(v), "latest": v == latest, "standing": states.get(v) or None,
                     "note": note or None, "created_utc": m.get("created_utc"),
                     "n_tiles": m.get("n_tiles"), "n_corners": m.get("n_corners"),
                     "drives": [d_.get("drive") for d_ in m.get("source_drives", [])],
                     "parent_version": version_name(parent) if parent is not None else None,
                     "format_version": m.get("format_version"), "manifest_sha256": sha})
        if not as_json:
            typer.echo(f"{mark} {version_name(v)}  {m.get('created_utc', '?')}  tiles={m.get('n_tiles', '?'):<5} "
                       f"corners={m.get('n_corners', '?'):<7} drives={len(m.get('source_drives', []))} "
                       f"parent={version_name(parent) if parent is not None else '-'}  "
                       f"format={m.get('format_version')} sha256={sha[:12]}" + (f"  {note}" if note else ""))
    if as_json:
        opts.echo_json({"map": d.name, "path": shown(str(d)),
                        "latest": version_name(latest) if latest is not None else None, "versions": rows})


def diff(version_a: str = typer.Argument(..., help="Old version (vNNNN, N or LATEST)."),
         version_b: str = typer.Argument(..., help="New version."),
         root: Path = opts.ROOT_OR_URI, map_name: Optional[str] = MAP_OPT,
         significance: float = typer.Option(0.001, "--significance", help="A matched corner is moved when the "
                                            "chi-square test (2 dof) on its displacement with both covariances "
                                            "rejects 'unchanged' at this level; marking cells likewise."),
         move_threshold_m: float = typer.Option(0.0, "--move-threshold-m", help="... and it moved more than this "
                                                "(0: the test alone)."),
         match_radius_m: float = typer.Option(1.0, "--match-radius-m", help="Corners further apart never match."),
         as_json: bool = typer.Option(False, "--json", help="Print the per-tile diff as JSON.")) -> None:
    """Per tile: corners added, removed, moved (chi-square test on both covariances); marking cells changed beyond
    the rasters' noise (A -> B).

    Example: [b]cornermap tiles diff v0001 LATEST --map tiny --root runs/tiny[/b]
    """
    import math

    from mapformat.change_tests import chi2_threshold
    from mapformat.diff import diff_maps, marking_cells
    from mapformat.loader import open_map
    from pipeline.errors import OptionError

    for opt, value in (("--move-threshold-m", move_threshold_m), ("--match-radius-m", match_radius_m)):
        if not (math.isfinite(value) and 0.0 <= value <= 1000.0):
            raise OptionError(opt, [f"{value}: expected 0 to 1000 m"])
    if not (0.0 < significance < 1.0):
        raise OptionError("--significance", [f"{significance}: expected a probability in (0, 1)"])
    from pipeline.store_maps import map_location

    d = map_location(root, map_name)  # a folder, or a bucket's map (each version downloaded and verified)
    a, b = open_map(d, version_a), open_map(d, version_b)
    diffs = diff_maps(a, b, move_threshold_m=move_threshold_m, match_radius_m=match_radius_m,
                      significance=significance)
    cells, test = marking_cells(a, b, significance)
    corner_test = {"method": "chi2", "dof": 2, "significance": significance,
                   "threshold": round(chi2_threshold(significance), 3)}
    if as_json:
        typer.echo(json.dumps({"a": a.version, "b": b.version, "corner_test": corner_test,
                               "tiles": [t.as_dict() for t in diffs],
                               "marking_cells": cells, "marking_test": test}, indent=1))
        return
    typer.echo(f"diff v{a.version:04d} -> v{b.version:04d}: {len(diffs)} tile(s) changed (corners: chi-square, 2 "
               f"dof, significance {significance:g}, threshold {corner_test['threshold']})")
    for t in diffs:
        typer.echo(f"  tile ({t.i},{t.j}): +{t.corners_added} -{t.corners_removed} ~{t.corners_moved} corners, "
                   f"{t.marking_px_changed} marking px changed")
    totals = [sum(getattr(t, k) for t in diffs) for k in ("corners_added", "corners_removed", "corners_moved",
                                                         "marking_px_changed")]
    typer.echo("total: +{} -{} ~{} corners, {} marking px changed".format(*totals))
    typer.echo(f"marking cells changed ({test['cells_compared']} compared, noise rate {test['noise_rate']:g}): "
               + (", ".join(f"({c['east_m']:.0f}, {c['north_m']:.0f}) {c['px_changed']} px" for c in cells)
                  or "none"))


def log(root: Path = opts.ROOT_OR_URI, map_name: Optional[str] = MAP_OPT,
        as_json: bool = typer.Option(False, "--json", help="Print every version's changelog as JSON."),
        details: bool = typer.Option(False, "--details", help="Also list the ids of added, removed and moved "
                                     "corners and the changed tiles.")) -> None:
    """History of a map, oldest first: per version its drives, corners added / removed / moved (stable ids),
    marking pixels changed and whether the frame stayed the same (each version's changelog.json). The root may be
    s3://BUCKET/PREFIX.

    Example: [b]cornermap tiles log --map tiny --root runs/tiny[/b]
    """
    from pipeline.store_maps import readable_root

    changelog = lambda m: [str(m["changelog"])] if m.get("changelog") else []  # noqa: E731
    with readable_root(root, map_name, whole=(), pick=changelog) as (local_root, shown):
        _log(local_root, map_name, as_json, details, shown)


def _log(root: Path, map_name: Optional[str], as_json: bool, details: bool, shown) -> None:
    from mapformat.changelog import read_changelog, summary_line
    from pipeline.errors import ChecksumError, MapFormatError
    from pipeline.versioned import list_versions, read_latest, read_manifest, version_name

    d = map_dir_of(root, map_name)
    latest = read_latest(d)
    docs = []
    if not as_json:
        typer.echo(f"{shown(str(d))}  (LATEST = {version_name(latest) if latest is not None else 'none'})")
    for v in list_versions(d):
        mark = "*" if v == latest else " "
        try:
            m, _ = read_manifest(d / version_name(v))
            doc = read_changelog(d / version_name(v), m)
        except (MapFormatError, ChecksumError) as exc:
            if as_json:
                docs.append({"version": version_name(v), "error": str(exc)})
            else:
                typer.echo(f"{mark} {version_name(v)}  unreadable: {exc}")
            continue
        docs.append({"version": version_name(v), "created_utc": m.get("created_utc"), "changelog": doc})
        if as_json:
            continue
        typer.echo(f"{mark} {summary_line(version_name(v), m, doc)}")
        if details and doc:
            c = doc["corners"]
            for key in ("added", "removed"):
                if c[key]:
                    typer.echo(f"    {key}: " + ", ".join(f"#{e['id']} ({e['east_m']:.2f}, {e['north_m']:.2f})"
                                                        for e in c[key]))
            if c["moved"]:
                typer.echo("    moved: " + ", ".join(f"#{e['id']} {e['dist_m']:.2f} m" for e in c["moved"]))
            for t in doc["markings"]["tiles"]:
                typer.echo(f"    tile ({t['tile'][0]},{t['tile'][1]}): {t['px_changed']} marking px changed")
    if as_json:
        typer.echo(json.dumps(docs, indent=1))


def export(
    fmt: str = typer.Option(
        ..., "--format", "-f", help="im2016-text | geojson | markings-geojson | autoware | geotiff | tum | kitti"
    ),
    out: Path = typer.Option(..., "--out", "-o", help="Output file (a directory for autoware, geotiff, tum, kitti)."),
    root: Path = opts.ROOT_OR_URI,
    map_name: Optional[str] = MAP_OPT,
    version: str = VERSION_OPT,
    old_version: Optional[str] = opts.MOVED_VERSION,
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing non-empty --out folder as a whole "
                                   "(a folder export is refused there otherwise)."),
    quiet: bool = opts.QUIET,
    as_json: bool = opts.JSON,
) -> None:
    """Export a version: Im 2016 Table 1 text, GeoJSON (WGS84 lon/lat), Autoware map folder, GeoTIFFs (COG) with a
    VRT per layer, or the version's trajectories (TUM, KITTI) with their frame stated.

    Examples: [b]cornermap tiles export -f im2016-text -o runs/city.txt --map city --root runs/maps[/b];
    [b]cornermap tiles export -f markings-geojson -o runs/markings.geojson --map city --root runs/maps[/b]; an
    Autoware map folder (point cloud map tiles, projector info, Lanelet2 lanelets and markings): -f autoware -o DIR
    (reads the scans and poses the version was built from under --root); trajectories: -f tum -o DIR, -f kitti -o DIR.
    A folder is written beside --out and renamed into place when complete; an existing non-empty folder is refused
    (exit 1) unless --overwrite.
    """
    from mapformat.export import FORMATS, export_map
    from mapformat.loader import open_map
    from pipeline.progress import StageProgress

    if fmt not in FORMATS:
        raise typer.BadParameter(f"{fmt!r}; expected one of {', '.join(FORMATS)}", param_hint="--format")
    from pipeline.storage import refuse_uri, uri_scheme
    from pipeline.store_maps import readable_root

    refuse_uri(out, "--out")
    with readable_root(root, map_name, version=version) as (local_root, _):
        reader = open_map(map_dir_of(local_root, map_name), version)
        with StageProgress(enabled=not quiet and not as_json):
            # the datasets a version was built from (the Autoware point cloud) are read from the root itself
            files = export_map(reader, fmt, out, root=root if uri_scheme(root) else local_root, overwrite=overwrite)
    if as_json:
        typer.echo(json.dumps({"format": fmt, "out": str(out), "files": [str(f) for f in files]}, indent=1))
        return
    typer.echo(exported_line(out, [Path(f) for f in files]))


def exported_line(out: Path, files: list[Path], shown: int = 3) -> str:
    """One line for an export: the file itself, or the folder with its file count and the first few names (an
    Autoware folder holds one point-cloud file per tile; ``--json`` lists every file)."""
    if len(files) == 1:
        return f"wrote {files[0]}"
    names = [str(f.relative_to(out)) if f.is_relative_to(out) else str(f) for f in files[:shown]]
    more = f", ... ({len(files) - shown} more; --json lists them)" if len(files) > shown else ""
    return f"wrote {len(files)} files under {out}: {', '.join(names)}{more}"


def verify(root: Path = opts.ROOT_OR_URI, map_name: Optional[str] = MAP_OPT, version: str = VERSION_OPT,
           old_version: Optional[str] = opts.MOVED_VERSION,
           all_versions: bool = typer.Option(False, "--all", help="Verify every version, not only one."),
           as_json: bool = opts.JSON) -> None:
    """Recompute every file's sha256 and compare with the manifest; exit 1 on any mismatch. On an s3:// root the
    bytes checked are the bucket's (downloaded to a temporary folder).

    Example: [b]cornermap tiles verify --all --map tiny --root runs/tiny[/b]
    """
    from pipeline.errors import ChecksumError
    from pipeline.store_maps import readable_root

    with readable_root(root, map_name, whole="all" if all_versions else "latest", version=version) \
            as (local_root, shown):
        try:
            _verify(local_root, map_name, version, all_versions, as_json, shown)
        except ChecksumError as exc:
            raise ChecksumError(shown(str(exc))) from None


def _verify(root: Path, map_name: Optional[str], version: str, all_versions: bool, as_json: bool, shown) -> None:
    from mapformat.verify import verify_map
    from pipeline.errors import ChecksumError, UnknownNameError
    from pipeline.versioned import list_versions, resolve_version, trusted_manifest_digests, version_name

    d = map_dir_of(root, map_name)
    dirs = [d / version_name(v) for v in list_versions(d)] if all_versions else [resolve_version(d, version)]
    if not dirs:
        raise UnknownNameError(f"{d}: no published versions to verify")
    trusted = trusted_manifest_digests(d)
    bad, rows = [], []
    for vdir in dirs:
        expected = trusted.get(int(vdir.name[1:]))
        problems = verify_map(vdir, expected)
        rows.append({"version": vdir.name, "ok": not problems, "problems": [shown(p) for p in problems],
                     "manifest_digest_recorded": bool(expected)})
        if not as_json:
            note = "" if expected else " (no digest recorded outside the manifest: only its files were checked)"
            typer.echo(f"{vdir.name}: {'ok' if not problems else f'{len(problems)} problem(s)'}{note}")
            for p in problems:
                typer.echo(f"  - {shown(p)}")
        bad += problems
    if as_json:
        opts.echo_json({"map": d.name, "path": shown(str(d)), "ok": not bad, "versions": rows})
    if bad:
        raise ChecksumError(f"{d}: {len(bad)} integrity problem(s) (listed above); hint: republish the version")


def query(root: Path = opts.ROOT_OR_URI, map_name: Optional[str] = MAP_OPT, version: str = VERSION_OPT,
          at: str = typer.Option(..., "--at", help="LAT,LON in degrees, WGS84."),
          radius_m: float = typer.Option(150.0, "--radius", help="Metres around --at (at most 10 km)."),
          heading_deg: Optional[float] = typer.Option(None, "--heading-deg", help="The vehicle's heading, degrees "
                                                      "counter-clockwise from east (with --fov-deg)."),
          fov_deg: Optional[float] = typer.Option(None, "--fov-deg", help="Field of view about --heading-deg."),
          as_json: bool = typer.Option(False, "--json", help="Print the answer as JSON.")) -> None:
    """What the map holds where the vehicle is: corners (id, east/north, lat/lon, wall angles, covariance), the
    marking window and the localizability cells within --radius of a latitude / longitude.

    Example: [b]cornermap tiles query --at 37.49790,127.02760 --radius 150 --map tiny --root runs/tiny --json[/b]
    """
    from mapformat.loader import open_map
    from mapformat.query import as_json as answer_json
    from mapformat.query import check_area, query_latlon

    parts = at.split(",")
    try:
        lat, lon = (float(v) for v in parts)
    except ValueError:
        raise typer.BadParameter(f"{at!r}: expected LAT,LON in degrees, e.g. 37.4979,127.0276",
                                 param_hint="--at") from None
    if (heading_deg is None) != (fov_deg is None):
        raise typer.BadParameter("give --heading-deg and --fov-deg together", param_hint="--fov-deg")
    check_area(radius_m, fov_deg)
    from pipeline.store_maps import map_location

    reader = open_map(map_location(root, map_name), version)
    q = query_latlon(reader, lat, lon, radius_m, heading_deg=heading_deg, fov_deg=fov_deg)
    doc = answer_json(reader, q)
    if as_json:
        typer.echo(json.dumps(doc, indent=1))
        return
    view = f", heading {heading_deg:g} deg, field of view {fov_deg:g} deg" if fov_deg is not None else ""
    typer.echo(f"{doc['map']} v{reader.version:04d} at {lat:.8f},{lon:.8f} = ENU ({q.east_m:.3f}, {q.north_m:.3f}) m, "
               f"radius {radius_m:g} m{view}: {len(doc['corners'])} corner(s), "
               f"{len(doc['localizability'])} localizability row(s)")
    for c in doc["corners"]:
        typer.echo(f"  #{c['corner_id']:<6d} ENU ({c['east_m']:9.3f}, {c['north_m']:9.3f}) m  {c['lat_deg']:.9f},"
                   f"{c['lon_deg']:.9f}  walls {c['theta1_deg']:7.2f} {c['theta2_deg']:7.2f} deg  cov "
                   f"[{c['cov_ee_m2']:.2e} {c['cov_en_m2']:.2e} {c['cov_nn_m2']:.2e}] m^2")
    m = doc["marking_window"]
    typer.echo("marking window: none (no rasters)" if m is None else
               f"marking window: {m['width_px']} x {m['height_px']} px of {m['cell_m']} m from ENU "
               f"({m['origin_east_m']:.1f}, {m['origin_north_m']:.1f}) m, {m['painted_px']} painted")
    for c in doc["localizability"]:
        typer.echo(f"  cell ({c['cell_i']},{c['cell_j']}) {c['method']}: sigma_2d {c['sigma_2d_m']:.3f} m (along "
                   f"{c['sigma_along_m']:.3f}, across {c['sigma_cross_m']:.3f}) {c['status']}"
                   + (f": {c['reason']}" if c["reason"] else ""))


def bundle(root: Path = ROOT_OPT, map_name: Optional[str] = MAP_OPT,
           base: str = typer.Option(..., "--from", help="The version the vehicle holds (vNNNN or N)."),
           target: str = typer.Option(..., "--to", help="The version to deliver (vNNNN, N or LATEST)."),
           out: Path = typer.Option(..., "--out", "-o", help="A new folder for the bundle."),
           as_json: bool = typer.Option(False, "--json", help="Print the bundle manifest as JSON.")) -> None:
    """Write a delta bundle: the files of --to whose bytes --from does not have, the target's manifest and a bundle
    manifest naming every file of the target with its sha256 and both versions' manifest digests.

    Example: [b]cornermap tiles bundle --from v0001 --to v0002 --out runs/city-delta --map city --root runs/maps[/b]
    """
    from mapformat.bundle import make_bundle

    doc = make_bundle(map_dir_of(root, map_name), base, target, out)
    if as_json:
        typer.echo(json.dumps(doc, indent=1))
        return
    n = sum(e["source"] == "bundle" for e in doc["files"])
    b, t = doc["bytes"]["bundle"], doc["bytes"]["target"]
    typer.echo(f"wrote {out}: v{doc['base']['version']:04d} -> v{doc['target']['version']:04d}, {n + 1} of "
               f"{len(doc['files']) + 1} files, {b} of {t} bytes ({100.0 * b / max(t, 1):.1f} %)")


def apply(bundle_dir: Path = typer.Argument(..., help="The bundle folder (bundle.json, files/)."),
          root: Optional[Path] = typer.Option(None, "--root", envvar="CORNERMAP_ROOT", show_envvar=False,
                                              help="The vehicle's root (it holds maps/NAME)."),
          map_name: Optional[str] = typer.Option(None, "--map", "-m", help="Map name (ROOT/maps/NAME); default: "
                                                 "the only map there. A vehicle's copy kept outside a root may be "
                                                 "given as its folder (one holding LATEST), without --root."),
          as_json: bool = typer.Option(False, "--json", help="Print the outcome as JSON.")) -> None:
    """Apply a delta bundle to a copy of a map (ROOT/maps/NAME on the vehicle: LATEST and the version it names):
    the copy's LATEST must name the bundle's base; the target is built and checked file by file in a staging
    folder, renamed into place, then named by LATEST.

    Example: [b]cornermap tiles apply runs/city-delta --map city --root runs/vehicle[/b]
    """
    from mapformat.bundle import apply_bundle

    map_folder = _vehicle_map_folder(root, map_name)
    res = apply_bundle(bundle_dir, map_folder)
    if as_json:
        typer.echo(json.dumps(res, indent=1))
    elif res["already"]:
        typer.echo(f"{map_folder}: already holds v{res['target']:04d}; nothing to do")
    else:
        typer.echo(f"{map_folder}: v{res['base']:04d} -> v{res['target']:04d} ({res['written']} files from the "
                   f"bundle, {res['from_base']} from v{res['base']:04d}, every sha256 checked); LATEST = "
                   f"v{res['target']:04d}")


def _vehicle_map_folder(root: Optional[Path], map_name: Optional[str]) -> Path:
    """ROOT/maps/NAME, or a copy's own folder when --map names one (a path holding LATEST) and --root is not given."""
    from pipeline.errors import OptionError
    from pipeline.storage import latest_file

    if map_name is not None and ("/" in map_name or "\\" in map_name):
        folder = Path(map_name)
        if root is not None:
            raise OptionError("--map", [f"{map_name!r} is a folder; with --root, --map is a name (ROOT/maps/NAME)"])
        if not latest_file(folder).is_file():
            raise OptionError("--map", [f"{map_name!r} holds no LATEST: not a map folder; expected a name with "
                                        "--root ROOT (ROOT/maps/NAME) or a map's folder"])
        return folder
    return map_dir_of(root if root is not None else Path("."), map_name)


def register(app: typer.Typer, stage_app: typer.Typer | None = None) -> None:
    """Add ls/diff/log/export/verify to the ``tiles`` group (created on ``app`` when not given)."""
    target = stage_app
    if target is None:
        target = typer.Typer(no_args_is_help=True, help="Published map versions: ls, diff, log, export, verify.")
        app.add_typer(target, name="tiles")
    target.info.help = (target.info.help or "Published map versions.") + "\n\n" + EXAMPLES
    target.command("ls")(ls)
    target.command("diff")(diff)
    target.command("log")(log)
    target.command("export")(export)
    target.command("verify")(verify)
    target.command("rollback")(rollback)
    target.command("query")(query)
    target.command("bundle")(bundle)
    target.command("apply")(apply)
    target.command("push")(push)


def push(root: Path = ROOT_OPT, map_name: str = opts.MAP,
         to: str = typer.Option(..., "--to", help="The root to publish to: s3://BUCKET/PREFIX (or a folder)."),
         quiet: bool = opts.QUIET) -> None:
    """Publish a map's versions to another root, e.g. the bucket vehicles download from: each version not yet there
    (its files, then its manifest, created last and only if absent), the identity, then LATEST. Idempotent.

    Example: [b]cornermap tiles push --root runs/maps --map city --to s3://maps/city-root[/b]
    """
    from pipeline.storage import SCHEMES, Store, normalise_uri, refuse_uri, uri_scheme
    from pipeline.store_maps import push_map
    from pipeline.versioned import version_name

    if uri_scheme(to) is not None and uri_scheme(to) not in SCHEMES:
        refuse_uri(to, "--to", "a folder or an s3://BUCKET/PREFIX URI")
    store = Store.open(normalise_uri(to))
    pushed = push_map(map_dir_of(root, map_name).parent.parent, map_name, store,
                      say=None if quiet else typer.echo)
    typer.echo(f"{store.uri}: map {map_name!r}: {len(pushed)} version(s) committed"
               + (f" ({', '.join(version_name(v) for v in pushed)})" if pushed else " (already up to date)"))


def rollback(to: str = typer.Option(..., "--to", help="The version LATEST should name (vNNNN or N)."),
             root: Path = opts.ROOT_OR_URI, map_name: Optional[str] = MAP_OPT) -> None:
    """Point LATEST back at an older, verified version (a new LATEST write; no version is deleted). The root may be
    s3://BUCKET/PREFIX (LATEST is one PUT, under the map's lease).

    Example: [b]cornermap tiles rollback --to v0001 --map city --root runs/maps[/b]
    """
    from pipeline.storage import Store, uri_scheme
    from pipeline.versioned import rollback_latest, version_name

    if uri_scheme(root) is not None:
        from pipeline.store_maps import rollback as rollback_remote

        before, now = rollback_remote(Store.open(root), map_name, to)
    else:
        before, now = rollback_latest(map_dir_of(root, map_name), to)
    typer.echo(f"LATEST: {version_name(before) if before is not None else 'none'} -> {version_name(now)}")
