"""Arrow tables <-> pose-graph arrays (DriveInput, pose rows, loop rows). No algorithms here."""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from pipeline.errors import FormatError
from schemas.registry import schema_of
from stages.common.records import INCREMENT_COLUMNS, Extrinsics, PriorPoses, pose_columns, pose_matrices
from stages.common.wheel_odometry import track_from_table, wheel_increments
from stages.posegraph.factors.drive import DriveInput, SpanEdges
from stages.posegraph.factors.wheel import calibrate_wheel, calibrated_wheel_increments


def _information(edges: pa.Table) -> np.ndarray:
    """(N,6,6) information matrices of odometry_edges / odometry_span_edges rows."""
    return np.asarray(edges["information"].combine_chunks().flatten().to_numpy(), float).reshape(-1, 6, 6)


def drive_input(drive: str, gnss: pa.Table, edges: pa.Table, drive_info: pa.Table,
                odometry: pa.Table | None = None, span_edges: pa.Table | None = None,
                prior: pa.Table | None = None) -> DriveInput:
    """One drive's rows of poses_gnss (one per scan), odometry_edges, drive_info and (optional) odometry_raw
    (wheel speed and yaw rate: increments where ICP failed), odometry_span_edges (accepted ones kept) and
    poses_prior (a prior trajectory, a start pose: the frame of a drive without GNSS)."""
    g = gnss.filter(pc.equal(gnss["drive"], drive)).sort_by("scan_id")
    if g.num_rows == 0:
        raise FormatError(f"poses_gnss: no rows for drive {drive!r}; hint: is it in the workflow's drives?")
    T_vl = Extrinsics.from_table(drive_info).of(drive)
    ids = g["scan_id"].to_numpy()
    n = len(ids)
    e = edges.filter(pc.equal(edges["drive"], drive))
    e_ids = e["scan_id"].to_numpy()
    pos = np.searchsorted(ids, e_ids)
    inside = (pos < n) & (pos > 0)
    inside[inside] &= (ids[pos[inside]] == e_ids[inside]) & (ids[pos[inside] - 1] == e_ids[inside] - 1)
    edge_T = np.tile(np.eye(4), (n, 1, 1))
    edge_info = np.tile(np.eye(6), (n, 1, 1))
    edge_ok = np.zeros(n, bool)
    if e.num_rows:
        Te = pose_matrices(e, position=INCREMENT_COLUMNS)
        info = _information(e)
        conv = e["accepted"].to_numpy(zero_copy_only=False)
        edge_T[pos[inside]] = Te[inside]
        edge_info[pos[inside]] = info[inside]
        edge_ok[pos[inside]] = conv[inside]
    std = np.column_stack([g[c].to_numpy() for c in ("std_east_m", "std_north_m", "std_up_m")])
    d = DriveInput(drive, ids, g["stamp_ns"].to_numpy(), pose_matrices(g), std,
                   g["std_yaw_rad"].to_numpy(), g["valid"].to_numpy(zero_copy_only=False), edge_T, edge_info,
                   edge_ok, T_vl, *_wheel_arrays(drive, ids, g["stamp_ns"].to_numpy(), odometry))
    d.spans = _span_edges(drive, ids, span_edges)
    if "roll_pitch_known" in g.column_names:
        d.gnss_roll_pitch_known = g["roll_pitch_known"].to_numpy(zero_copy_only=False).astype(bool)
    if prior is not None and not d.gnss_valid.any():
        from stages.posegraph.factors.prior import prior_in_map

        d.prior = PriorPoses.from_table(prior, drive)
        placed = prior_in_map(d.prior, ids)
        if placed is not None:
            d.prior_T, d.prior_known = placed
    if d.wheel_T is not None:
        d.wheel_calibration = calibrate_wheel(d)
        d.wheel_T = calibrated_wheel_increments(d, d.wheel_calibration)
    return d


def _span_edges(drive: str, ids: np.ndarray, span_edges: pa.Table | None) -> SpanEdges | None:
    """The drive's accepted span edges whose two scans both have a poses_gnss row (positions into ``ids``)."""
    if span_edges is None:
        return None
    e = span_edges.filter(pc.and_(pc.equal(span_edges["drive"], drive), span_edges["accepted"]))
    a, b = e["scan_id_from"].to_numpy(), e["scan_id"].to_numpy()
    pa_, pb = np.searchsorted(ids, a), np.searchsorted(ids, b)
    ok = (pa_ < len(ids)) & (pb < len(ids))
    ok[ok] &= (ids[pa_[ok]] == a[ok]) & (ids[pb[ok]] == b[ok])
    if not ok.any():
        return SpanEdges(np.zeros(0, int), np.zeros(0, int), np.zeros((0, 4, 4)), np.zeros((0, 6, 6)))
    T = pose_matrices(e, position=INCREMENT_COLUMNS)
    return SpanEdges(pa_[ok], pb[ok], T[ok], _information(e)[ok])


def _wheel_arrays(drive: str, ids: np.ndarray, stamps_ns: np.ndarray, odometry: pa.Table | None
                  ) -> tuple[np.ndarray | None, np.ndarray | None]:
    if odometry is None:
        return None, None
    rows = odometry.filter(pc.equal(odometry["drive"], drive)) if "drive" in odometry.column_names else odometry
    track = track_from_table(rows)
    if track is None:
        return None, None
    inc = wheel_increments(track, ids, stamps_ns)
    wheel_T = np.tile(np.eye(4), (len(ids), 1, 1))
    wheel_ok = np.zeros(len(ids), bool)
    pos = np.searchsorted(ids, np.fromiter(inc, dtype=np.int64, count=len(inc)))
    for k, T in zip(pos, inc.values()):
        wheel_T[k] = T
        wheel_ok[k] = True
    return wheel_T, wheel_ok


def poses_table(name: str, drive: DriveInput, T: np.ndarray, cov_xy_yaw: np.ndarray | None = None) -> pa.Table:
    cols = {"drive": pa.array([drive.name] * drive.n, pa.string()), "scan_id": pa.array(drive.scan_ids, pa.int64()),
            "stamp_ns": pa.array(drive.stamps_ns, pa.int64()), **pose_columns(T)}
    if cov_xy_yaw is not None:
        cols["cov_xy_yaw"] = pa.FixedSizeListArray.from_arrays(
            pa.array(np.asarray(cov_xy_yaw, float).reshape(-1), pa.float64()), 9)
    return pa.table(cols, schema=schema_of(name))


def loops_table(rows: list[dict]) -> pa.Table:
    schema = schema_of("loop_closures")
    return pa.Table.from_pylist(rows, schema=schema) if rows else schema.empty_table()
