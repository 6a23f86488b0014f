"""Adapter of the corner map stage: Arrow tables in, Arrow tables out (the algorithms are in the sibling modules)."""
from __future__ import annotations

import logging
from typing import Any

import numpy as np
import pyarrow as pa

from pipeline.errors import DataQualityError
from schemas import SCHEMAS
from stages.common.drive_tables import select_drives
from stages.common.records import Extrinsics, pose_matrices
from stages.cornermap.aggregate import aggregate_clusters, lag_one_correlation
from stages.cornermap.clustering import cluster_observations
from stages.cornermap.filtering import FilterThresholds, reject_reasons
from stages.cornermap.merge import merge_duplicates
from stages.cornermap.params import CornerMapParams
from stages.cornermap.partition import cluster_partitioned
from stages.cornermap.transform import covariance_from_components, transform_to_enu

log = logging.getLogger(__name__)

def match_poses(corners: pa.Table, poses: pa.Table) -> tuple[np.ndarray, np.ndarray]:
    """Row of ``poses`` holding each corner's (drive, scan_id) -> (pose_row, has_pose), vectorised."""
    c_drive = corners["drive"].to_numpy(zero_copy_only=False)
    p_drive = poses["drive"].to_numpy(zero_copy_only=False)
    names, codes = np.unique(np.concatenate([c_drive, p_drive]), return_inverse=True)
    shift = np.int64(1) << np.int64(40)
    c_key = codes[:len(c_drive)].astype(np.int64) * shift + corners["scan_id"].to_numpy()
    p_key = codes[len(c_drive):].astype(np.int64) * shift + poses["scan_id"].to_numpy()
    order = np.argsort(p_key, kind="stable")
    sorted_keys = p_key[order]
    if len(sorted_keys) > 1 and np.any(dup := sorted_keys[1:] == sorted_keys[:-1]):
        first = order[1:][dup][0]
        raise DataQualityError(f"cornermap: poses_optimized has {int(dup.sum())} duplicate (drive, scan_id) rows, "
                               f"e.g. drive {p_drive[first]!r} scan {poses['scan_id'][int(first)].as_py()}; "
                               "expected one pose per scan; hint: rerun posegraph")
    pos = np.clip(np.searchsorted(sorted_keys, c_key), 0, max(len(sorted_keys) - 1, 0))
    has = (sorted_keys[pos] == c_key) if len(sorted_keys) else np.zeros(len(c_key), bool)
    return order[pos] if len(sorted_keys) else pos, has


def _finite_rows(t: pa.Table) -> np.ndarray:
    cols = ["x_m", "y_m", "theta1_rad", "theta2_rad", "cov_xx_m2", "cov_xy_m2", "cov_yy_m2"]
    return np.all([np.isfinite(t[c].to_numpy()) for c in cols], axis=0)


def _extrinsics(drive_info: pa.Table, drive_names: list[str]) -> np.ndarray:
    """(D,4,4) T_vehicle_lidar per drive name."""
    rows = Extrinsics.from_table(drive_info.select(["drive", "T_vehicle_lidar"])).T_vehicle_lidar
    missing = [d for d in drive_names if d not in rows]
    if missing:
        raise DataQualityError(f"cornermap: drives {missing} have corners but no drive_info row (T_vehicle_lidar); "
                               f"drive_info has {sorted(rows)}; hint: run ingest for those drives")
    return np.stack([rows[d] for d in drive_names])


def _pose_matrices(poses: pa.Table, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    T = pose_matrices(poses, rows)
    cov_all = np.asarray(poses["cov_xy_yaw"].combine_chunks().flatten().to_numpy(), dtype=float)
    return T, cov_all.reshape(-1, 3, 3)[rows]


def _empty(name: str) -> pa.Table:
    return SCHEMAS[name].empty_table()


def compute(ctx) -> dict[str, Any]:
    p: CornerMapParams = ctx.params
    drives = list(ctx.settings.get("map_drives") or [])
    all_corners, all_poses = ctx.inputs.read("corners"), ctx.inputs.read("poses")
    corners = select_drives(all_corners, drives)
    poses = select_drives(all_poses, drives)
    pose_row, has_pose = match_poses(corners, poses)
    finite = _finite_rows(corners)
    keep = has_pose & finite
    n_no_pose, n_nonfinite = int(np.sum(~has_pose)), int(np.sum(has_pose & ~finite))
    joined = corners.filter(pa.array(keep))
    pose_row = pose_row[keep]
    if n_no_pose or n_nonfinite:
        log.warning("cornermap: dropped %d observations without an optimized pose and %d with non-finite values",
                    n_no_pose, n_nonfinite)
    extra = {"cornermap": {"n_observations": joined.num_rows, "n_dropped_no_pose": n_no_pose,
                           "n_dropped_nonfinite": n_nonfinite, "drives": drives}}
    if joined.num_rows == 0:
        log.warning("cornermap: no corner observations with poses; writing an empty map")
        return {"corner_map": _empty("corner_map"), "rejected": _empty("corner_map_rejected"), "_extra": extra}

    drive_names, drive_code = np.unique(joined["drive"].to_numpy(zero_copy_only=False), return_inverse=True)
    drive_names = [str(d) for d in drive_names]
    T_vehicle_lidar = _extrinsics(ctx.inputs.read("drive_info"), drive_names)[drive_code]
    T_map_vehicle, cov_pose = _pose_matrices(poses, pose_row)
    col = lambda c: joined[c].to_numpy()  # noqa: E731
    obs = transform_to_enu(
        np.column_stack([col("x_m"), col("y_m")]), np.column_stack([col("theta1_rad"), col("theta2_rad")]),
        covariance_from_components(col("cov_xx_m2"), col("cov_xy_m2"), col("cov_yy_m2")),
        T_map_vehicle, T_vehicle_lidar, cov_pose)

    def cluster(en, theta):
        return cluster_observations(en, theta, link_radius_m=p.link_radius_m, angle_tol_rad=np.radians(p.angle_tol_deg),
                                    max_neighbors=p.max_neighbors, split_spread_m=p.split_spread_m)

    labels, report = cluster_partitioned(obs.en_m, obs.theta_enu_rad, cell_size_m=p.cell_size_m, halo_m=p.halo_m,
                                         link_radius_m=p.link_radius_m, workers=p.workers, cluster=cluster)
    thresholds = FilterThresholds(min_obs=p.min_obs, min_drives=p.min_drives, max_spread_m=p.max_spread_m,
                                  max_cov_trace_m2=p.max_cov_trace_m2,
                                  max_angle_spread_rad=np.radians(p.max_angle_spread_deg))

    rho = None
    if p.extraction_error_per_drive and p.pass_autocorrelation:
        rho, n_pairs = lag_one_correlation(labels, drive_code, col("stamp_ns"), obs.en_m)
        extra["cornermap"]["pass_lag_one_correlation"] = {"rho": rho, "pairs": n_pairs}

    def summarise(lab):
        return aggregate_clusters(lab, obs, drive_code, drive_names, col("stamp_ns"), col("interior_angle_rad"),
                                  col("convex"), scatter_per_drive=p.extraction_error_per_drive, pass_rho=rho,
                                  pose_shared_per_pass=p.pose_shared_per_pass,
                                  pass_shared_fraction=p.pass_shared_fraction)

    summary = summarise(labels)
    duplicate, n_merged = np.zeros(len(summary.n_obs), bool), 0
    if p.merge_radius_m > 0:
        labels, duplicate, n_merged = merge_duplicates(
            labels, summary.en_m, summary.theta_rad, summary.n_obs,
            lambda lab: np.array([r == "" for r in reject_reasons(summarise(lab), thresholds)], bool),
            merge_radius_m=p.merge_radius_m, angle_tol_rad=np.radians(p.angle_tol_deg), max_neighbors=p.max_neighbors)
        summary = summarise(labels)
    reasons = reject_reasons(summary, thresholds)
    for i in np.flatnonzero(duplicate):
        reasons[i] = "; ".join(filter(None, [reasons[i], f"duplicate: a stronger corner with the same walls lies "
                                                         f"within {p.merge_radius_m:.2f} m"]))
    kept = np.array([r == "" for r in reasons], bool)
    extra["cornermap"].update({"n_merged_groups": n_merged, "n_duplicates_rejected": int(duplicate.sum()),
                               "n_cells": report.n_cells, "n_wide_clusters": report.n_wide_clusters,
                               "n_partition_conflicts": report.n_conflicts, "n_clusters": len(kept),
                               "n_kept": int(kept.sum()), "n_rejected": int((~kept).sum())})
    log.info("cornermap: %d observations -> %d clusters (%d duplicate groups merged, %d duplicates rejected) -> "
             "%d corners kept", len(labels), len(kept), n_merged, int(duplicate.sum()), kept.sum())
    table = corner_map_table(summary, kept)
    en_map = np.column_stack([table["east_m"].to_numpy(), table["north_m"].to_numpy()])
    extra["cornermap"]["layer_vs_poses"] = check_layer_vs_poses(ctx, all_corners, all_poses, en_map, p)
    return {"corner_map": table, "rejected": rejected_table(summary, kept, reasons), "_extra": extra}


def check_layer_vs_poses(ctx, corners: pa.Table, poses: pa.Table, en_map: np.ndarray, p: CornerMapParams) -> dict:
    """``frame_check.layer_vs_poses`` over every drive with corners and optimized poses (the evaluation drives
    too: a localizer is scored against their poses); a drive whose median offset exceeds ``frame_check_warn_m``
    is logged as a warning."""
    from stages.cornermap.frame_check import layer_vs_poses

    pose_row, has_pose = match_poses(corners, poses)
    keep = has_pose & _finite_rows(corners)
    if not keep.any() or not len(en_map):
        return {}
    joined, pose_row = corners.filter(pa.array(keep)), pose_row[keep]
    names, code = np.unique(joined["drive"].to_numpy(zero_copy_only=False), return_inverse=True)
    names = [str(d) for d in names]
    T_map_vehicle, cov_pose = _pose_matrices(poses, pose_row)
    col = lambda c: joined[c].to_numpy()  # noqa: E731
    obs = transform_to_enu(np.column_stack([col("x_m"), col("y_m")]),
                           np.column_stack([col("theta1_rad"), col("theta2_rad")]),
                           covariance_from_components(col("cov_xx_m2"), col("cov_xy_m2"), col("cov_yy_m2")),
                           T_map_vehicle, _extrinsics(ctx.inputs.read("drive_info"), names)[code], cov_pose)
    out = layer_vs_poses(en_map, obs.en_m, code, names, max_match_m=p.frame_check_match_m)
    for name, row in out.items():
        off = row.get("median_offset_en_m")
        if off is None:
            continue
        level = logging.WARNING if np.hypot(*off) > p.frame_check_warn_m else logging.INFO
        log.log(level, "cornermap: corner layer vs %s's optimized poses: median offset (%.3f, %.3f) m, rms %.3f m, "
                "rigid fit %.3f m / %.3f deg over %d observations", name, off[0], off[1], row["rms_m"],
                row["fit_shift_m"], row["fit_rotation_deg"], row["n_matched"])
    return out


def corner_map_table(s, kept: np.ndarray) -> pa.Table:
    """Kept clusters -> corner_map, corner_id 1..K in order of (east, north)."""
    idx = np.flatnonzero(kept)
    idx = idx[np.lexsort((s.en_m[idx, 1], s.en_m[idx, 0]))]
    cov = s.cov_map_m2[idx]
    cols = {
        "corner_id": np.arange(1, len(idx) + 1, dtype=np.int64),
        "east_m": s.en_m[idx, 0], "north_m": s.en_m[idx, 1],
        "theta1_rad": s.theta_rad[idx, 0], "theta2_rad": s.theta_rad[idx, 1],
        "cov_ee_m2": cov[:, 0, 0], "cov_en_m2": cov[:, 0, 1], "cov_nn_m2": cov[:, 1, 1],
        "n_obs": s.n_obs[idx], "n_drives": s.n_drives[idx].astype(np.int32),
        "drives": [s.drives[i] for i in idx],
        "first_seen_ns": s.first_seen_ns[idx], "last_seen_ns": s.last_seen_ns[idx],
        "interior_angle_rad": s.interior_angle_rad[idx], "convex": s.convex[idx],
    }
    return pa.Table.from_pydict(cols, schema=SCHEMAS["corner_map"])


def rejected_table(s, kept: np.ndarray, reasons: list[str]) -> pa.Table:
    idx = np.flatnonzero(~kept)
    cols = {
        "east_m": s.en_m[idx, 0], "north_m": s.en_m[idx, 1], "n_obs": s.n_obs[idx],
        "cov_trace_m2": np.trace(s.cov_map_m2[idx], axis1=1, axis2=2) if len(idx) else np.empty(0),
        "reason": [reasons[i] for i in idx],
    }
    return pa.Table.from_pydict(cols, schema=SCHEMAS["corner_map_rejected"])

