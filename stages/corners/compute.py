"""Table adapter of the corners stage: scans_raw rows of one scan chunk -> corners_per_scan rows."""
from __future__ import annotations

import logging

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from pipeline.declare import StageContext
from schemas.registry import schema_of
from stages.common.records import Extrinsics, decode_scans_raw
from stages.common.wheel_odometry import OdometryTrack, track_from_table
from stages.corners.core import extract_corners, select_scan_layers
from stages.corners.determine import Corners
from stages.corners.params import CornerParams

log = logging.getLogger(__name__)

SCAN_COLUMNS = ["scan_id", "stamp_ns", "x_m", "y_m", "z_m", "ring", "time_offset_s"]
GEOMETRY_COLUMNS = ["x_m", "y_m", "z_m", "ring"]


def corners_table(drive: str, chunk: int, scan_ids: list[int], stamps_ns: list[int], corners: list[Corners]
                  ) -> pa.Table:
    """Assemble corners_per_scan rows (sensor frame) for the scans of one chunk."""
    counts = np.array([len(c) for c in corners], dtype=np.int64)
    n = int(counts.sum())

    def cat(attr: str, dtype, shape=()) -> np.ndarray:
        parts = [getattr(c, attr) for c in corners]
        return np.concatenate(parts).astype(dtype) if parts else np.zeros((0, *shape), dtype)

    cov = cat("cov_m2", np.float64, (2, 2))
    columns = {
        "drive": pa.array([drive] * n, pa.string()),
        "chunk": pa.array(np.full(n, chunk, np.int32)),
        "scan_id": pa.array(np.repeat(np.asarray(scan_ids, np.int64), counts)),
        "stamp_ns": pa.array(np.repeat(np.asarray(stamps_ns, np.int64), counts)),
        "corner_idx": pa.array(np.concatenate([np.arange(k, dtype=np.int32) for k in counts])
                               if counts.size else np.zeros(0, np.int32)),
        "x_m": pa.array(cat("x_m", np.float64)), "y_m": pa.array(cat("y_m", np.float64)),
        "theta1_rad": pa.array(cat("theta1_rad", np.float64)), "theta2_rad": pa.array(cat("theta2_rad", np.float64)),
        "cov_xx_m2": pa.array(cov[:, 0, 0]), "cov_xy_m2": pa.array(cov[:, 0, 1]),
        "cov_yy_m2": pa.array(cov[:, 1, 1]),
        "n_layers": pa.array(cat("n_layers", np.int16)), "range_m": pa.array(cat("range_m", np.float64)),
        "interior_angle_rad": pa.array(cat("interior_angle_rad", np.float64)),
        "convex": pa.array(cat("convex", bool)),
    }
    schema = schema_of("corners_per_scan")
    if "time_offset_s" in schema.names:  # forward compatible: the corner's own time within the scan
        columns["time_offset_s"] = pa.array(cat("time_offset_s", np.float64)).cast(schema.field("time_offset_s").type)
    return pa.Table.from_pydict(columns, schema=schema)


def _extrinsic(ctx: StageContext) -> np.ndarray | None:
    if not ctx.inputs.has("drive_info"):
        return None
    info = ctx.inputs.read("drive_info", partition=ctx.partition, columns=["drive", "T_vehicle_lidar"])
    return Extrinsics.from_table(info).of(ctx.partition.drive) if info.num_rows else None


def _odometry_track(ctx: StageContext, params: CornerParams) -> OdometryTrack | None:
    if not (params.layers.deskew and ctx.inputs.has("odometry")):
        return None
    odo = ctx.inputs.read("odometry", partition=ctx.partition, columns=["stamp_ns", "speed_mps", "yaw_rate_radps"])
    return track_from_table(odo)


def read_layer_points(ctx: StageContext, params: CornerParams) -> tuple[pa.Table, np.ndarray]:
    """The chunk's rows of its upper layers only, and those layers' ring ids.

    Corners use nothing of the other layers, so they are not read: the layers are chosen from the chunk's geometry
    (a ring's elevation is a constant of the sensor), then only their rows are read, the ring filter pushed down to
    the Parquet scan. A 100-scan chunk of 45k-point scans held ~375 bytes per point when every row and column was
    read (docs/performance.md)."""
    geometry = ctx.inputs.read("scans", partition=ctx.partition, columns=GEOMETRY_COLUMNS)
    if not geometry.num_rows:
        return ctx.inputs.read("scans", partition=ctx.partition, columns=SCAN_COLUMNS), np.zeros(0, np.intp)
    rows = decode_scans_raw(geometry, by_scan=False)
    layers = select_scan_layers(rows.xyz_lidar_m, rows.ring, params)
    del geometry, rows
    ring_type = schema_of("scans_raw").field("ring").type
    wanted = pc.field("ring").isin(pa.array(np.asarray(layers).tolist(), ring_type))
    return ctx.inputs.read("scans", partition=ctx.partition, columns=SCAN_COLUMNS, filters=wanted), layers


def compute(ctx: StageContext) -> dict[str, pa.Table]:
    params: CornerParams = ctx.params  # type: ignore[assignment]
    table, layers = read_layer_points(ctx, params)
    drive = ctx.partition.drive or ""
    chunk = ctx.partition.chunk if ctx.partition.chunk is not None else 0
    rows = decode_scans_raw(table)
    del table
    ids, bounds = rows.scan_rows()
    xyz, ring, stamp = rows.xyz_lidar_m, rows.ring, rows.stamp_ns
    t_s = rows.time_offset_s.astype(np.float64)
    track = _odometry_track(ctx, params)
    T_vehicle_lidar = _extrinsic(ctx) if track is not None else None
    scan_ids, stamps, corners, n_deskewed = [], [], [], 0
    for sid, a, b in zip(ids, bounds[:-1], bounds[1:]):
        scan_ids.append(int(sid))
        stamps.append(int(stamp[a]))
        pts = None if track is None else track.deskew_scan(xyz[a:b], t_s[a:b], stamps[-1], T_vehicle_lidar)
        if pts is not None:
            # corners are now in the lidar frame at the scan start: their time offset is 0
            corners.append(extract_corners(pts, ring[a:b], params, layers=layers, time_offset_s=np.zeros(b - a)))
            n_deskewed += 1
        else:
            corners.append(extract_corners(xyz[a:b], ring[a:b], params, layers=layers, time_offset_s=t_s[a:b]))
    if track is not None and n_deskewed < len(scan_ids):
        log.warning("corners %s: odometry (stamp_ns %d..%d) does not cover %d of %d scans (first scan stamp_ns %d);"
                    " those scans are not deskewed; hint: check that scans_raw and odometry_raw share a time base",
                    ctx.partition.label, track.stamp_ns[0], track.stamp_ns[-1], len(scan_ids) - n_deskewed,
                    len(scan_ids), stamps[0])
    out = corners_table(drive, chunk, scan_ids, stamps, corners)
    log.info("corners %s: %d scans (%d deskewed), %d corners", ctx.partition.label, len(scan_ids), n_deskewed,
             out.num_rows)
    return {"corners": out}
