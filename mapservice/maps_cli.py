"""``cornermap maps create|show``, ``cornermap rebuild`` and ``cornermap gc``: a map kept up to date on a schedule.

Exit codes of ``rebuild`` (for monitoring): 0 published, 0 nothing to do, 3 the regression gate refused the
candidate (LATEST unchanged), 1 error, 2 usage, 75 another rebuild of the map holds its lock, 130 / 143
interrupted / terminated. Heavy imports inside.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from pipeline import cli_options as opts
from stages.common.tiling import DEFAULT_TILE_SIZE_M

maps_app = typer.Typer(no_args_is_help=True, help="A map's identity: pinned frame, tile size, drive set.\n\n"
                       "Examples:\n\n  cornermap maps create --root runs/maps --map kept --origin 37.4979,127.0276,57"
                       "\n\n  cornermap maps show --root runs/maps --map kept")

ROOT_REQ = opts.ROOT
MAP_REQ = opts.MAP


@maps_app.command("create")
def create_cmd(root: Path = opts.ROOT_OR_URI, map_name: str = MAP_REQ,
               origin: str = typer.Option(..., "--origin", help="The map's ENU origin LAT,LON,H (degrees, degrees, "
                                          "metres WGS84), fixed for every version."),
               tile_size_m: float = typer.Option(DEFAULT_TILE_SIZE_M, "--tile-size-m",
                                                 help="Tile edge in metres, fixed."),
               max_radius_km: float = typer.Option(10.0, "--max-radius-km", help="The map's area: drives with a GNSS "
                                                   "fix farther from the origin are refused (exit 3). 10 km: the ENU "
                                                   "up axis leans 0.09 deg there and the ground lies 7.8 m below its "
                                                   "plane (docs/maintenance.md); at most 100."),
               check_drive: Optional[Path] = typer.Option(None, "--check-drive", help="drive.yaml the rebuild's "
                                                          "regression gate localizes (default: the newest drive)."),
               check_reference: Optional[Path] = typer.Option(None, "--check-reference", help="Truth TUM of "
                                                              "--check-drive (default: its own pose graph).")) -> None:
    """Write a map's identity (ROOT/maps/NAME/map.json): every build and rebuild of NAME uses this frame. The root
    may be s3://BUCKET/PREFIX.

    Example: [b]cornermap maps create --root runs/maps --map kept --origin 37.4979,127.0276,57[/b]
    """
    from mapservice.build import parse_origin
    from mapservice.maps import MAX_RADIUS_LIMIT_KM, CheckDrive, create_map
    from pipeline.errors import ConfigError, OptionError

    if not (0 < tile_size_m <= 10000):
        raise OptionError("--tile-size-m", [f"expected 0 < S <= 10000 m; got {tile_size_m}"])
    if not (0 < max_radius_km <= MAX_RADIUS_LIMIT_KM):
        raise OptionError("--max-radius-km", [f"expected 0 < R <= {MAX_RADIUS_LIMIT_KM:g} km; got {max_radius_km}"])
    check = None
    if check_drive is not None:
        for opt, p in (("--check-drive", check_drive), ("--check-reference", check_reference)):
            if p is not None and not p.is_file():
                raise ConfigError(opt, [f"no such file {p}"])
        check = CheckDrive(path=str(check_drive.resolve()),
                           reference=str(check_reference.resolve()) if check_reference else None)
    elif check_reference is not None:
        raise OptionError("--check-reference", ["applies to --check-drive only"])
    from mapservice.maps import MapHome
    from pipeline.storage import identity_file

    ident = create_map(root, map_name, parse_origin(origin), tile_size_m, check, max_radius_km)
    home = MapHome(root, map_name)
    o = ident.enu_origin
    typer.echo(f"created map {map_name!r}: origin {o.lat_deg},{o.lon_deg},{o.h_m}, tiles {ident.tile_size_m} m, "
               f"area {ident.max_radius_km:g} km -> {home.store.url(identity_file(home.mdir))}")


@maps_app.command("show")
def show_cmd(root: Path = opts.ROOT_OR_URI, map_name: str = MAP_REQ, as_json: bool = opts.JSON) -> None:
    """Print a map's frame, its versions (LATEST, refused by the gate, candidate) and drives: when each was recorded
    (first/last pose), when added, the versions holding it. Maps made by `cornermap build` too. The root may be
    s3://BUCKET/PREFIX.

    Example: [b]cornermap maps show --root runs/maps --map kept[/b]
    """
    from mapservice.maps import map_dir
    from mapservice.maps_show import show_doc, show_lines
    from pipeline.store_maps import readable_root

    trajectories = lambda m: [str(d["trajectory"]) for d in m.get("source_drives", [])]  # noqa: E731
    with readable_root(root, map_name, whole=(), pick=trajectories) as (local_root, shown):
        mdir = map_dir(local_root, map_name)
        if as_json:
            doc = show_doc(mdir, root)
            opts.echo_json({**doc, "path": shown(str(doc.get("path", mdir)))})
            return
        for line in show_lines(mdir, root):
            typer.echo(shown(line))


def rebuild_cmd(root: Path = opts.ROOT_OR_URI, map_name: str = MAP_REQ,
                inbox: Path = opts.INBOX_OR_URI,
                min_free_gib: float = typer.Option(2.0, "--min-free-gib", help="Free space required to start."),
                quiet_period_min: float = typer.Option(10.0, "--quiet-period-min", help="A drive folder is taken "
                                                       "when nothing under it changed for this long (minutes), or at "
                                                       "once when it holds a READY file written after the copy; "
                                                       "until then: one line 'waiting: ...'."),
                gate_tol_m: float = typer.Option(0.05, "--gate-tol-m", help="Gate: a localization figure may grow "
                                                 "by max(this, --gate-tol-rel x previous) metres."),
                gate_tol_rel: float = typer.Option(0.2, "--gate-tol-rel", help="Gate: relative tolerance."),
                no_gate: bool = typer.Option(False, "--no-gate", help="Publish without the regression gate."),
                full: bool = typer.Option(False, "--full", help="Solve every drive's poses jointly again (default: "
                                          "incremental, the new drives solved against LATEST's poses held "
                                          "fixed; docs/maintenance.md)."),
                scheduler: Optional[str] = opts.SCHEDULER, workers: Optional[int] = opts.WORKERS,
                dask_host: str = opts.DASK_HOST, params: Optional[Path] = opts.PARAMS,
                workflow: str = typer.Option("map_rebuild", "--workflow", help="The map workflow."),
                quiet: bool = opts.QUIET, as_json: bool = opts.JSON) -> None:
    """Build the next version of map NAME from its drives plus the new ones in INBOX, gate it, publish it.

    Delivery: a drive is a folder INBOX/NAME with its drive.yaml, taken once complete: a READY file in it written
    after the copy, or nothing under it changed for --quiet-period-min (default 10). A drive already in the map
    (same content) or delivered twice is left alone; a bad one moves to INBOX/quarantine/ with a reason.

    Exit codes: 0 published or nothing to do, 3 gate refused or a drive outside the map's area (LATEST unchanged),
    1 error, 2 usage, 75 another writer of the map or root holds its lock, 130/143 interrupted/terminated (LATEST
    unchanged unless the candidate was already published).

    ROOT and INBOX may be s3://BUCKET/PREFIX (docs/storage.md): drives are then prefixes INBOX/NAME/ with a
    drive.yaml, complete with a READY object (or quiet for --quiet-period-min), read from a local copy in the
    scratch folder; the free-space check applies to that scratch folder.

    Example: [b]cornermap rebuild --root runs/maps --map kept --inbox runs/sim[/b] (drive folders in runs/sim)
    """
    import math

    from mapservice.rebuild import RebuildParams, rebuild
    from pipeline.errors import OptionError
    from pipeline.progress import StageProgress

    for opt, v in (("--min-free-gib", min_free_gib), ("--gate-tol-m", gate_tol_m), ("--gate-tol-rel", gate_tol_rel),
                   ("--quiet-period-min", quiet_period_min)):
        if not (math.isfinite(v) and v >= 0):
            raise OptionError(opt, [f"expected a finite number >= 0; got {v}"])
    params = RebuildParams(min_free_gib=min_free_gib, gate=not no_gate, gate_tol_m=gate_tol_m,
                           gate_tol_rel=gate_tol_rel, workflow=workflow, scheduler=scheduler,
                           quiet_period_s=quiet_period_min * 60.0, params_file=params, workers=workers,
                           dask_host=dask_host, full=full)
    with StageProgress(enabled=not quiet):
        # each line as it comes (a cron log keeps what was quarantined even when the build then fails)
        result = rebuild(root, map_name, inbox, params, say=None if as_json else typer.echo)
    if as_json:
        opts.echo_json({"map": map_name, "status": result.status, "exit_code": result.exit_code,
                        "version": f"v{result.version:04d}" if result.version is not None else None,
                        "quarantined": result.quarantined, "lines": result.lines, "stages": result.summary})
    elif result.summary:  # the build ran: per stage its partitions (reused), wall and CPU seconds
        from pipeline.progress import summary_lines

        for line in summary_lines(result.summary, root):
            typer.echo(line)
    if result.exit_code:
        raise typer.Exit(result.exit_code)


def _hours(value: float) -> float:
    import math

    if not (math.isfinite(value) and value >= 0):
        raise typer.BadParameter(f"expected a number of hours >= 0; got {value}")
    return value


def gc_cmd(root: Path = opts.ROOT_OR_URI,
           apply: bool = typer.Option(False, "--apply", help="Delete (default: a dry run that only prints)."),
           min_age_h: float = typer.Option(24.0, "--min-age-h", callback=_hours, help="Uncommitted dataset "
                                           "folders, scratch (ROOT/tmp) entries and staged drives (ROOT/drives) "
                                           "younger than this (runs in progress) are kept; >= 0."),
           as_json: bool = typer.Option(False, "--json", help="Print the plan (or what was removed) as one JSON "
                                        "document.")) -> None:
    """Remove intermediates and staged drives no kept map version and no current drive set references (dry run by
    default).

    Example: [b]cornermap gc --root runs/maps[/b] (a dry run; add --apply to delete)
    """
    import json

    from mapservice.gc import apply_gc, plan_gc
    from pipeline.errors import ConfigError
    from pipeline.storage import is_root_dir, uri_scheme

    verb = "remove" if apply else "would remove"
    mib = lambda b: f"{b / 2**20:.1f} MiB"  # noqa: E731
    if uri_scheme(root) is not None:  # an object-store root: datasets, staged drives, map versions, leases
        from mapservice.gc import apply_gc_store, plan_gc_store
        from pipeline.storage import Store
        from pipeline.store_maps import gc_uncommitted

        store = Store.open(root)
        plan = plan_gc_store(store, min_age_h)
        if apply and (plan.remove or plan.drives_remove):
            plan = apply_gc_store(store, plan, min_age_h)
        found = gc_uncommitted(store, min_age_h, apply)
        if as_json:
            doc = plan.as_json(store.root, url=store.url)
            doc.pop("scratch")
            doc.update(root=store.uri, applied=apply, other=[{"uri": uri, "why": why} for uri, why in found])
            typer.echo(json.dumps(doc, indent=1))
            return
        for loc in plan.remove:
            typer.echo(f"{verb} {store.url(loc)}")
        for loc in plan.drives_remove:
            typer.echo(f"{verb} {store.url(loc)} (a staged drive nothing kept names)")
        for loc in plan.drives_young:
            typer.echo(f"keep (staged drive, younger than {min_age_h} h) {store.url(loc)}")
        for uri, why in found:
            typer.echo(f"{verb} {uri} ({why})")
        freed, kept = ("freed" if apply else "to free"), len(plan.keep) + len(plan.young_uncommitted)
        typer.echo(f"{len(plan.remove)} dataset folder(s), {mib(plan.remove_bytes)} {freed}; {kept} kept; "
                   f"{len(plan.drives_remove)} staged drive(s), {mib(plan.drives_bytes)} {freed}; {len(found)} other "
                   f"object prefix(es) {'removed' if apply else 'to remove'}")
        return
    if not is_root_dir(root):  # a typo: "nothing to free", exit 0
        raise ConfigError("--root", [f"{root} holds no datasets/, maps/ or tmp/ folder: not an output root"])
    plan = plan_gc(root, min_age_h)
    if apply:  # under the root's exclusive lock (exit 75 while a run writes): what a plan made there still lists
        plan = apply_gc(root, plan, min_age_h)
    if as_json:
        doc = plan.as_json(Path(root))
        doc.update(root=str(root), applied=apply)
        typer.echo(json.dumps(doc, indent=1))
        return
    for d in plan.remove:
        typer.echo(f"{verb} {d.relative_to(root)}")
    for d in plan.young_uncommitted:
        typer.echo(f"keep (uncommitted, younger than {min_age_h} h) {d.relative_to(root)}")
    for entry in plan.stale_scratch:
        typer.echo(f"{verb} {entry.relative_to(root)} (scratch of a killed run)")
    for d in plan.drives_remove:
        typer.echo(f"{verb} {d.relative_to(root)} (a staged drive nothing kept names)")
    for d in plan.drives_young:
        typer.echo(f"keep (staged drive, younger than {min_age_h} h) {d.relative_to(root)}")
    scratch = (f"; {len(plan.stale_scratch)} scratch folder(s) of killed runs, {mib(plan.scratch_bytes)}"
               if plan.stale_scratch else "")
    drives = (f"; {len(plan.drives_remove)} staged drive(s), {mib(plan.drives_bytes)}" if plan.drives_remove else "")
    typer.echo(f"{len(plan.remove)} dataset folder(s), {mib(plan.remove_bytes)} "
               f"{'freed' if apply else 'to free'}; {len(plan.keep)} kept ({mib(plan.keep_bytes)}){scratch}{drives}")


def register(app: typer.Typer) -> None:
    from mapservice.reoptimize_cli import reoptimize_cmd  # issue 59 item 2: maps reoptimize

    maps_app.command("reoptimize")(reoptimize_cmd)
    app.add_typer(maps_app, name="maps")
    app.command("rebuild")(rebuild_cmd)
    app.command("gc")(gc_cmd)
