"""Adapter of the markings stage: Arrow tables in, per-tile rasters (PNG + sidecar) and one metadata row out.

Source of the cloud: the survey cloud (``survey_enu``) when the workflow has one with rows; otherwise a
mobile-mapping cloud accumulated from the drives' scans (``scans_raw``) with ``poses_optimized`` and the
extrinsics in ``drive_info``. Either way the tile's grid is built piece by piece (one survey partition or one
scan chunk at a time), so memory is bounded by the tile raster plus one piece.
"""
from __future__ import annotations

import logging
from typing import Any, Iterator

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from pipeline.declare import PartitionKey
from pipeline.errors import ConfigError
from schemas import SCHEMAS
from stages.common.drive_tables import select_drives
from stages.common.geodesy import EnuOrigin
from stages.common.marking_raster.elevation_grid import GridAccumulator
from stages.common.marking_raster.rasterize import halo_px_for, rasterize_grid
from stages.common.records import Extrinsics, decode_scans_raw, pose_matrices
from stages.common.survey_parts import distinct_survey_partitions
from stages.common.tiling import resolve_tile_size_m, tile_bounds, tile_key_of, tile_shape_px, tiles_touching
from stages.markings.accumulate import scans_to_enu
from stages.markings.params import MarkingParams
from stages.markings.raster_io import TileRasters, write_tile_rasters

log = logging.getLogger(__name__)
SCANS_PER_PIECE = 16  # scans read and placed at once (a 120k-point HDL-64E scan: ~16 MB per piece member)
_POSE_COLUMNS = ["drive", "scan_id", "stamp_ns", "x_m", "y_m", "z_m", "qx", "qy", "qz", "qw"]


def _tile_size_m(ctx) -> float:
    return resolve_tile_size_m(ctx.settings.get("tile_size_m"))


def survey_available(inputs) -> bool:
    """True when the survey input exists and at least one of its partitions has rows."""
    if not inputs.has("survey"):
        return False
    return any(inputs.read("survey", partition=key, columns=["east_m"]).num_rows > 0
               for key in distinct_survey_partitions(inputs))


def cloud_source(ctx) -> str:
    """'survey' or 'drives', from ``params.source`` (auto: the survey when it has points)."""
    wanted = ctx.params.source
    if wanted == "survey" and not survey_available(ctx.inputs):
        raise ConfigError("markings stage inputs", ["source 'survey' asked for, but the workflow's survey cloud is "
                                                     "missing or empty"])
    if wanted == "auto":
        return "survey" if survey_available(ctx.inputs) else "drives"
    return wanted


def plan_tiles(ctx) -> list[PartitionKey]:
    """Tiles covering the survey cloud's points, or the drives' poses buffered by ``pose_buffer_m``."""
    params: MarkingParams = ctx.params
    size_m = _tile_size_m(ctx)
    keys: set[tuple[int, int]] = set()
    source = cloud_source(ctx)
    if source == "survey":
        for part in distinct_survey_partitions(ctx.inputs):
            table = ctx.inputs.read("survey", partition=part, columns=["east_m", "north_m"])
            i, j = tile_key_of(table["east_m"].to_numpy(), table["north_m"].to_numpy(), size_m)
            packed = np.unique((i << 32) | (j & 0xFFFFFFFF))  # one 1-D sort instead of a row-wise unique
            keys.update(zip((packed >> 32).tolist(), ((packed & 0xFFFFFFFF).astype(np.int32)).tolist()))
    elif ctx.inputs.has("poses") and ctx.inputs.has("scans"):
        poses = _map_drive_poses(ctx, ["drive", "x_m", "y_m"])
        keys.update(tiles_touching(poses["x_m"].to_numpy(), poses["y_m"].to_numpy(), params.pose_buffer_m,
                                   size_m))
    else:
        raise ConfigError("markings stage inputs", [
            "neither a survey cloud with rows (survey_enu) nor drive scans with poses (scans_raw + "
            "poses_optimized) are available; hint: name a survey cloud in the catalog or run posegraph first"])
    return [PartitionKey(tile_i=i, tile_j=j) for i, j in sorted(keys)]


def _survey_pieces(ctx, e0: float, n0: float, e1: float, n1: float) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    window = ((pc.field("east_m") >= e0) & (pc.field("east_m") < e1)
              & (pc.field("north_m") >= n0) & (pc.field("north_m") < n1))
    for part in distinct_survey_partitions(ctx.inputs):
        table = ctx.inputs.read("survey", partition=part, columns=["east_m", "north_m", "up_m", "intensity"],
                                filters=window)
        if table.num_rows:
            pts = np.column_stack([table[c].to_numpy() for c in ("east_m", "north_m", "up_m")])
            yield pts, table["intensity"].to_numpy().astype(float)


def _extrinsics(ctx) -> dict[str, np.ndarray]:
    return Extrinsics.from_table(ctx.inputs.read("drive_info", columns=["drive", "T_vehicle_lidar"])).T_vehicle_lidar


def _drive_pieces(ctx, e0: float, n0: float, e1: float, n1: float) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    params: MarkingParams = ctx.params
    reach = params.max_range_m
    poses = _map_drive_poses(ctx, _POSE_COLUMNS)
    x, y = poses["x_m"].to_numpy(), poses["y_m"].to_numpy()
    near = (x >= e0 - reach) & (x < e1 + reach) & (y >= n0 - reach) & (y < n1 + reach)
    poses = poses.filter(pa.array(near))
    if poses.num_rows == 0:
        return
    extrinsics = _extrinsics(ctx) if ctx.inputs.has("drive_info") else {}
    scan_parts = ctx.inputs.partitions("scans")
    for drive in sorted(set(poses["drive"].to_pylist())):
        dp = poses.filter(pc.equal(poses["drive"], drive))
        ids = dp["scan_id"].to_numpy()
        stamps = dp["stamp_ns"].to_numpy()
        T_map_vehicle = pose_matrices(dp)
        T_vehicle_lidar = extrinsics.get(drive, np.eye(4))
        if drive not in extrinsics:
            log.warning("no drive_info for drive %s: using identity T_vehicle_lidar", drive)
        parts = [p for p in scan_parts if p.drive in (None, drive)]
        for start in range(0, len(ids), SCANS_PER_PIECE):  # a few scans at a time: memory bounded by the piece
            batch = ids[start:start + SCANS_PER_PIECE].tolist()
            for part in parts:
                table = ctx.inputs.read_in("scans", "scan_id", batch, partition=part,
                                           columns=["drive", "scan_id", "x_m", "y_m", "z_m", "intensity",
                                                    "time_offset_s"])
                table = table.filter(pc.equal(table["drive"], drive))
                if table.num_rows == 0:
                    continue
                rows = decode_scans_raw(table, by_scan=False)
                # each point at its own time in the sweep, between its scan's optimized pose and the next's
                enu, keep = scans_to_enu(rows.xyz_lidar_m.astype(float), rows.scan_id, ids, T_map_vehicle,
                                         T_vehicle_lidar, min_range_m=params.min_range_m,
                                         max_range_m=params.max_range_m,
                                         time_offset_s=rows.time_offset_s.astype(float), pose_stamps_ns=stamps)
                yield enu, rows.intensity.astype(float)[keep]


def _map_drive_poses(ctx, columns: list[str]) -> pa.Table:
    """Optimized poses of the workflow's map drives only (evaluation drives never go into the map)."""
    poses = ctx.inputs.read("poses", columns=list(dict.fromkeys(["drive", *columns])))
    return select_drives(poses, list(ctx.settings.get("map_drives") or [])).select(columns)


def compute(ctx) -> dict[str, Any]:
    params: MarkingParams = ctx.params
    key = ctx.partition
    if key.tile_i is None or key.tile_j is None:
        raise ConfigError("markings stage", [f"expected a per-tile partition, got {key}"])
    size_m, cell_m = _tile_size_m(ctx), params.cell_m
    rows, cols = tile_shape_px(size_m, cell_m)
    e0, n0, e1, n1 = tile_bounds(key.tile_i, key.tile_j, size_m)
    halo_px = halo_px_for(cell_m, params.threshold_block_m, params.ground_window_m)
    halo_m = halo_px * cell_m
    acc = GridAccumulator(e0 - halo_m, n0 - halo_m, cell_m, (rows + 2 * halo_px, cols + 2 * halo_px),
                          surface_band_m=params.surface_band_m)
    source = cloud_source(ctx)
    pieces = (_survey_pieces if source == "survey" else _drive_pieces)(ctx, e0 - halo_m, n0 - halo_m,
                                                                       e1 + halo_m, n1 + halo_m)
    for points, intensity in pieces:
        acc.add(points, intensity)
    layer = rasterize_grid(acc.finish(params.min_points_per_cell), halo_px, **params.rasterize_kwargs())
    grid = layer.grid
    n_points = int(grid.count.sum())
    origin = ctx.settings.get("enu_origin")
    origin = EnuOrigin.validate(origin).plain() if origin else None  # the workflow's, as the engine carries it
    meta = {
        "tile_i": key.tile_i,
        "tile_j": key.tile_j,
        "tile_size_m": size_m,
        "source": source,
        "n_points": n_points,
        "n_above_surface": acc.n_above_surface,
        "enu_origin": origin,
        "intensity_norm_low": layer.intensity_low,
        "intensity_norm_high": layer.intensity_high,
        "threshold_offset_levels": layer.offset_levels,
        "params": params.model_dump(),
    }
    rasters = TileRasters(marking_mask=layer.marking, traversable_mask=layer.traversable,
                          intensity=grid.mean_intensity, min_up_m=grid.min_up_m, mean_up_m=grid.mean_up_m,
                          count=grid.count, origin_east_m=e0, origin_north_m=n0, cell_m=cell_m, meta=meta)
    write_tile_rasters(ctx.artifact_dir("rasters"), rasters)
    log.info("markings tile (%d, %d): %d points (%d above the lowest surface dropped), %d traversable, %d marking "
             "cells (%s)", key.tile_i, key.tile_j, n_points, acc.n_above_surface, int(layer.traversable.sum()),
             int(layer.marking.sum()), source)
    row = {"tile_i": key.tile_i, "tile_j": key.tile_j, "origin_east_m": e0, "origin_north_m": n0,
           "cell_m": cell_m, "width_px": cols, "height_px": rows, "n_marking_px": int(layer.marking.sum()),
           "n_traversable_px": int(layer.traversable.sum()), "n_points": n_points, "source": source}
    return {"raster": pa.Table.from_pylist([row], schema=SCHEMAS["marking_raster"]), "rasters": None}
