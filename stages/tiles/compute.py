"""Adapter of the tiles stage: read inputs, run the quality gates, publish version N+1 of the map."""
from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np
import pyarrow as pa

from mapformat import layout
from mapformat.changelog import write_changelog
from mapformat.corner_ids import IdGates
from mapformat.localizability import split_by_tile, summary
from pipeline import storage
from pipeline.declare import PartitionKey, StageContext
from pipeline.errors import ConfigError, DataQualityError, DatasetIOError
from pipeline.names import check_name
from pipeline.registry import get_stage
from pipeline.store_maps import publish_map_version
from stages.common.geodesy import EnuOrigin
from stages.common.tiling import resolve_tile_size_m
from stages.tiles import core
from stages.tiles.history import carry_history
from stages.tiles.writer import DriveTrajectory, RasterTile, write_map_files

log = logging.getLogger(__name__)

_INPUT_ARGS = ("corner_map", "raster", "rasters", "poses", "drive_info")
_RASTER_META = ("origin_east_m", "origin_north_m", "cell_m", "width_px", "height_px", "n_marking_px",
                "n_traversable_px", "n_points", "source")


def compute(ctx: StageContext) -> dict[str, Any]:
    from schemas import schema_of  # the registry holds every schema of schemas/ (map_tiles: schemas/tiles.py)

    params = ctx.params
    size_m = resolve_tile_size_m(params.tile_size_m, ctx.settings.get("tile_size_m"))
    corners = ctx.inputs.read("corner_map")
    poses = ctx.inputs.read("poses").sort_by([("drive", "ascending"), ("stamp_ns", "ascending")])
    drive_info = ctx.inputs.read("drive_info")
    raster_rows = ctx.inputs.read("raster") if ctx.inputs.has("raster") else None

    problems = _schema_problems(corners, schema_of("corner_map")) if params.check_schema else []
    rasters = _collect_rasters(ctx, raster_rows, size_m, problems)
    trajectories = _trajectories(poses, drive_info)
    measured: dict[str, float] = {}
    if params.gates_enabled:
        if params.check_schema and not problems:
            problems += core.check_corner_values(*(corners[c].to_numpy() for c in (
                "corner_id", "east_m", "north_m", "theta1_rad", "theta2_rad", "cov_ee_m2", "cov_en_m2", "cov_nn_m2")))
        paths = [t.pose_xyz_qxyzw[:, :2] for t in trajectories]
        corner_tiles = set(core.group_by_tile(corners["east_m"].to_numpy(), corners["north_m"].to_numpy(), size_m))
        measured, failures = core.evaluate_gates(
            corners.num_rows, core.distinct_path_length_m(paths, params.path_step_m, params.distinct_path_radius_m),
            corner_tiles,
            core.path_tiles(paths, size_m, params.path_step_m), params.min_corners_per_km,
            params.max_empty_path_tile_share)
        problems += failures
    if problems and not params.gates_enabled:
        log.warning("tiles: gates disabled; publishing despite %d problem(s): %s", len(problems), problems)
    elif problems:
        raise DataQualityError(f"tiles: {len(problems)} quality gate failure(s); nothing published, LATEST "
                               "unchanged:\n" + "\n".join(f"  - {p}" for p in problems))

    name = str(ctx.settings["map_name"])
    decl = get_stage(ctx.stage)  # the declaration the engine runs this stage under
    inputs = {arg: {"dataset": decl.inputs[arg], "fingerprint": ctx.inputs.metadata(arg).get("fingerprint")}
              for arg in _INPUT_ARGS if arg in ("corner_map", "poses", "drive_info") or ctx.inputs.has(arg)}
    resolved = {**params.model_dump(mode="json"), "tile_size_m": size_m}
    fields = {"format": layout.FORMAT_NAME, "format_version": layout.FORMAT_VERSION, "map_name": name,
              "enu_origin": _enu_origin(ctx, drive_info).as_dict(), "tile_size_m": size_m,
              "n_corners": corners.num_rows, "corner_columns": list(layout.CORNER_COLUMNS),
              "stage": decl.name, "code_version": decl.code_version, "params": resolved, "inputs": inputs,
              "quality": measured,
              # how the corners' errors correlate with distance: the pose graph's figure (posegraph
              # error_correlation.py) for localizers that hold several corners at once; None: not stated
              "corner_error_correlation": ctx.inputs.metadata("poses").get("pose_error_correlation"),
              # the map frame's error against ENU (posegraph map_frame.py); the corner covariances are relative to it
              "map_frame": ctx.inputs.metadata("poses").get("map_frame")}

    cells = _localizability(params, size_m, corners, trajectories, rasters, fields["corner_error_correlation"])
    by_tile = split_by_tile(cells, params.localizability_cell_m, size_m) if cells is not None else None
    if cells is not None:
        fields["localizability"] = summary(cells, params.localizability_cell_m)
    check_name(name, "map", "tiles: settings.map_name")
    origin = EnuOrigin.from_dict(fields["enu_origin"])

    def write(staging: Path) -> dict[str, Any]:  # runs under the map's publish lock: LATEST cannot move
        # the map's folder (its parent version): ROOT/maps/NAME, or its local copy when the root is an object store
        _, doc = carry_history(staging.parent, corners, origin, size_m, staging,
                               lambda table, kept: write_map_files(staging, table, size_m, rasters, trajectories,
                                                                   by_tile, kept),
                               gates=IdGates(params.id_max_dist_m, params.id_max_angle_deg),
                               move_threshold_m=params.changelog_move_threshold_m,
                               new_paths=[t.pose_xyz_qxyzw[:, :2] for t in trajectories],
                               significance=params.changelog_significance,
                               min_obs=params.changelog_min_obs, plan=plan if params.tile_local else None)
        out = dict(fields)
        if doc["plan"] is not None:
            out["tile_local"] = doc["plan"].record
            if doc["plan"].kept and cells is not None:  # the layer as published: the kept tiles' cells are the parent's
                out["localizability"] = summary(_published_cells(staging, doc["files"]["tiles"]),
                                                params.localizability_cell_m)
        return {**out, "n_tiles": len(doc["files"]["tiles"]), **doc["files"],
                "next_corner_id": doc["changelog"]["corners"]["next_corner_id"],
                "changelog": write_changelog(staging, doc["changelog"])}

    def plan(prev, ided: pa.Table):
        from stages.tiles.keep import plan_tiles
        from stages.tiles.tilelocal import Tolerances

        same = prev.manifest.get("params") == resolved and prev.manifest.get("code_version") == decl.code_version
        tol = Tolerances(params.tile_local_corner_tol_m, params.tile_local_cov_tol_rel, params.tile_local_pose_tol_m,
                         params.tile_local_reach_m)
        return plan_tiles(prev, ided, trajectories, rasters, by_tile, size_m, tol, same)

    def unchanged(latest: dict[str, Any]) -> bool:
        fps = [v["fingerprint"] for v in inputs.values()]
        return (all(fps) and latest.get("inputs") == inputs and latest.get("params") == resolved
                and latest.get("code_version") == decl.code_version)

    pub = publish_map_version(ctx.settings["root"], name, write, keep_last=params.keep_last, reuse=unchanged,
                          move_latest=not ctx.settings.get("hold_latest", False))
    rel = storage.version_dir(storage.map_dir(PurePosixPath(), name), pub.version).as_posix()  # maps/NAME/vNNNN
    table = pa.table({
        "map_name": pa.array([name], pa.string()), "version": pa.array([pub.version], pa.int32()),
        "path": pa.array([rel], pa.string()),  # relative to the root: a moved root still works
        "n_tiles": pa.array([int(pub.manifest["n_tiles"])], pa.int32()),
        "n_corners": pa.array([int(pub.manifest["n_corners"])], pa.int64()),
        "manifest_sha256": pa.array([pub.manifest_sha256], pa.string())}, schema=schema_of("map_tiles"))
    held = ctx.settings.get("hold_latest", False)
    what = "wrote candidate (LATEST not moved)" if held else "published"
    local = pub.manifest.get("tile_local") or {}
    kept = f", {local['n_kept']} kept from v{local['parent_version']:04d}" if local.get("n_kept") else ""
    outcome = [f"{what} map {name!r} version {pub.name}: {{root}}/{rel} "
               f"({pub.manifest['n_corners']} corners, {pub.manifest['n_tiles']} tiles{kept})"]
    return {"published": table, "_extra": {"outcome": outcome}}


def _localizability(params, size_m: float, corners: pa.Table, trajectories: list[DriveTrajectory],
                    rasters: list[RasterTile], correlation: dict | None) -> pa.Table | None:
    """The localizability layer's cells (None when the param turns it off)."""
    if not params.localizability:
        return None
    per = size_m / params.localizability_cell_m
    if abs(per - round(per)) > 1e-9:
        raise ConfigError("tiles stage", [f"localizability_cell_m {params.localizability_cell_m} does not divide "
                                          f"the tile edge {size_m} m"])
    from stages.common.localizability import LocalizabilityConfig
    from stages.tiles.localizability import localizability_table

    cfg = LocalizabilityConfig(cell_m=params.localizability_cell_m,
                               detection_rate=params.localizability_detection_rate,
                               weak_sigma_m=params.localizability_weak_sigma_m,
                               fail_sigma_m=params.localizability_fail_sigma_m)
    corr = (correlation["share"], correlation["length_m"]) if correlation else None
    return localizability_table(corners, trajectories, rasters, corr, cfg)


def _published_cells(staging: Path, tiles: list[dict[str, Any]]) -> pa.Table:
    """Every cell of the localizability layer as written into ``staging`` (kept tiles hold the parent's)."""
    import pyarrow.parquet as pq

    from mapformat.localizability import LOCALIZABILITY_FILE, SCHEMA

    parts = [pq.read_table(staging / t["dir"] / LOCALIZABILITY_FILE).select(SCHEMA.names).cast(SCHEMA)
             for t in tiles if LOCALIZABILITY_FILE in (t.get("files") or {})]
    return pa.concat_tables(parts) if parts else SCHEMA.empty_table()


def _schema_problems(table: pa.Table, expected: pa.Schema) -> list[str]:
    problems = []
    for fld in expected:
        if fld.name not in table.column_names:
            problems.append(f"corner_map: column {fld.name!r} missing (expected {fld.type})")
        elif not table.schema.field(fld.name).type.equals(fld.type):
            problems.append(f"corner_map: column {fld.name!r} is {table.schema.field(fld.name).type}, "
                            f"expected {fld.type}")
    return problems


def _collect_rasters(ctx: StageContext, rows: pa.Table | None, size_m: float, problems: list[str]) -> list[RasterTile]:
    """Raster rows + their artifact files (every file of the tile is copied)."""
    if rows is None or rows.num_rows == 0:
        return []
    arg = "rasters" if ctx.inputs.has("rasters") else "raster"
    out = []
    for row in rows.to_pylist():
        i, j = int(row["tile_i"]), int(row["tile_j"])
        if abs(row["origin_east_m"] - i * size_m) > 1e-6 or abs(row["origin_north_m"] - j * size_m) > 1e-6:
            problems.append(f"marking_raster tile ({i},{j}): origin ({row['origin_east_m']}, {row['origin_north_m']})"
                            f" m is not the tile's lower-left corner ({i * size_m}, {j * size_m}) for tile_size_m "
                            f"{size_m}; hint: the markings and tiles stages must use the same tile_size_m")
        try:
            src_dir = ctx.inputs.artifact_dir(arg, PartitionKey(tile_i=i, tile_j=j))
        except DatasetIOError as exc:
            problems.append(f"marking_raster tile ({i},{j}): no artifact files ({exc})")
            continue
        files = {}
        for src in sorted(Path(src_dir).iterdir()) if Path(src_dir).is_dir() else []:
            name = layout.published_name_of(src.name, i, j)
            if src.is_file() and name is not None:
                files[name] = src
        if not set(layout.MARKING_MASK_FILES) & set(files):
            problems.append(f"marking_raster tile ({i},{j}): no marking mask ({' or '.join(layout.MARKING_MASK_FILES)})"
                            f" in {src_dir}")
        out.append(RasterTile(i, j, {k: row[k] for k in _RASTER_META if k in row}, files))
    return out


def _trajectories(poses: pa.Table, drive_info: pa.Table) -> list[DriveTrajectory]:
    cols = ["x_m", "y_m", "z_m", "qx", "qy", "qz", "qw"]
    drives = np.asarray(poses["drive"].to_pylist(), dtype=object)
    arr = np.column_stack([poses[c].to_numpy() for c in cols]) if poses.num_rows else np.zeros((0, 7))
    stamps = poses["stamp_ns"].to_numpy()
    info = {r["drive"]: r for r in drive_info.to_pylist()}
    out = []
    for drive in sorted(set(drives.tolist())):
        sel = drives == drive
        h = hashlib.sha256(json.dumps(info.get(drive), sort_keys=True, default=str).encode())
        h.update(np.ascontiguousarray(stamps[sel]).tobytes())
        h.update(np.ascontiguousarray(arr[sel]).tobytes())
        out.append(DriveTrajectory(drive, stamps[sel], arr[sel], h.hexdigest()[:16]))
    return out


def _enu_origin(ctx: StageContext, drive_info: pa.Table) -> EnuOrigin:
    for source in (ctx.inputs.metadata("drive_info").get("enu_origin"), ctx.settings.get("enu_origin")):
        if source:
            return EnuOrigin.from_dict(source)
    if drive_info.num_rows:
        r = drive_info.slice(0, 1).to_pylist()[0]
        if r.get("origin_lat_deg") is not None:
            return EnuOrigin(r["origin_lat_deg"], r["origin_lon_deg"], r["origin_h_m"])
    raise ConfigError("tiles stage", ["no ENU origin: drive_info metadata has no 'enu_origin', the workflow "
                                      "sets none and drive_info has no rows; a published map must be geo-referenced"])
