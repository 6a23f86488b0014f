"""Synthetic corner observations with known truth (a grid city) for the bench, tests and the docs figure.

Observations are made from the true poses and tagged with "optimized" poses that drift from truth by a slowly
varying offset (a few centimetres), as the pose graph's output would; 3 % of observations are false corners.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from schemas import SCHEMAS

T_VEHICLE_LIDAR = np.array([[1, 0, 0, 0.9], [0, 1, 0, 0.0], [0, 0, 1, 1.9], [0, 0, 0, 1.0]], float)


def grid_city(n_cols: int, n_rows: int, block_w_m: float = 115.0, block_h_m: float = 88.0,
              street_m: float = 24.0, seed: int = 0) -> tuple[list[np.ndarray], np.ndarray]:
    """Rectangular buildings (CCW footprints) on a block grid and the street centre-line nodes (rows+1, cols+1, 2)."""
    rng = np.random.default_rng(seed)
    pitch = np.array([block_w_m + street_m, block_h_m + street_m])
    nodes = np.stack(np.meshgrid(np.arange(n_cols + 1) * pitch[0], np.arange(n_rows + 1) * pitch[1]), -1)
    buildings = []
    for j in range(n_rows):
        for i in range(n_cols):
            lo = nodes[j, i] + street_m / 2 + 2.0
            hi = nodes[j + 1, i + 1] - street_m / 2 - 2.0
            x = lo[0]
            while x < hi[0] - 8.0:
                w = min(rng.uniform(12.0, 35.0), hi[0] - x)
                y0 = lo[1] + rng.uniform(0.0, 4.0)
                y1 = hi[1] - rng.uniform(0.0, 4.0)
                buildings.append(np.array([[x, y0], [x + w, y0], [x + w, y1], [x, y1]]))
                x += w + rng.uniform(2.0, 6.0)
    return buildings, nodes


def footprint_corners(buildings: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Every footprint vertex -> (K,2) east/north and (K,2) directions along the two walls away from it."""
    en, theta = [], []
    for fp in buildings:
        prev, nxt = np.roll(fp, 1, axis=0), np.roll(fp, -1, axis=0)
        en.append(fp)
        theta.append(np.column_stack([np.arctan2(*(nxt - fp).T[::-1]), np.arctan2(*(prev - fp).T[::-1])]))
    return np.vstack(en), np.vstack(theta)


def serpentine_route(nodes: np.ndarray, step_m: float) -> np.ndarray:
    """Drive every east-west street, then every north-south street; (M,3) east, north, yaw at step_m spacing."""
    waypoints = []
    for j in range(nodes.shape[0]):
        row = nodes[j] if j % 2 == 0 else nodes[j][::-1]
        waypoints += [row[0], row[-1]]
    for i in range(nodes.shape[1])[::-1]:
        col = nodes[:, i] if i % 2 == 0 else nodes[::-1, i]
        waypoints += [col[0], col[-1]]
    wp = np.array(waypoints)
    seg = np.diff(wp, axis=0)
    length = np.linalg.norm(seg, axis=1)
    s = np.arange(0.0, length.sum(), step_m)
    k = np.searchsorted(np.cumsum(length), s, side="right").clip(0, len(seg) - 1)
    s0 = np.concatenate([[0.0], np.cumsum(length)])[k]
    frac = ((s - s0) / np.maximum(length[k], 1e-9))[:, None]
    pos = wp[k] + frac * seg[k]
    yaw = np.arctan2(seg[k, 1], seg[k, 0])
    lane = 4.0 * np.column_stack([np.sin(yaw), -np.cos(yaw)])  # keep right
    return np.column_stack([pos + lane, yaw])


def observe_drive(drive: str, route: np.ndarray, corners_en: np.ndarray, corners_theta: np.ndarray, seed: int,
                  max_range_m: float = 40.0, drift_m: float = 0.05, false_share: float = 0.03):
    """(corners_per_scan, poses_optimized) of one drive; corners visible when both walls face the lidar.

    corner_idx holds the index of the true corner observed (-1 for a false corner), for scoring.
    """
    rng = np.random.default_rng(seed)
    n = len(route)
    c, s = np.cos(route[:, 2]), np.sin(route[:, 2])
    lidar_en = route[:, :2] + 0.9 * np.column_stack([c, s])
    pairs = cKDTree(corners_en).query_ball_point(lidar_en, max_range_m)
    scan = np.repeat(np.arange(n), [len(p) for p in pairs])
    k = np.concatenate([np.asarray(p, np.int64) for p in pairs])
    ray = lidar_en[scan] - corners_en[k]
    u1 = np.column_stack([np.cos(corners_theta[k, 0]), np.sin(corners_theta[k, 0])])
    u2 = np.column_stack([np.cos(corners_theta[k, 1]), np.sin(corners_theta[k, 1])])
    rn = ray / np.linalg.norm(ray, axis=1, keepdims=True)
    cross = lambda a, b: a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]  # noqa: E731
    grazing = np.sin(np.radians(10.0))
    # each wall is seen from its outer side (away from the other wall), not at grazing incidence
    seen1 = cross(u1, rn) * np.sign(cross(u1, u2)) < -grazing
    seen2 = cross(u2, rn) * np.sign(cross(u2, u1)) < -grazing
    visible = seen1 & seen2 & (rng.random(len(k)) < 0.8)
    scan, k, ray = scan[visible], k[visible], ray[visible]
    range_m = np.linalg.norm(ray, axis=1)
    sigma = 0.02 + 0.002 * range_m
    yaw = route[scan, 2]
    rel = corners_en[k] - lidar_en[scan]
    x = np.cos(yaw) * rel[:, 0] + np.sin(yaw) * rel[:, 1] + rng.normal(0, 1, len(k)) * sigma
    y = -np.sin(yaw) * rel[:, 0] + np.cos(yaw) * rel[:, 1] + rng.normal(0, 1, len(k)) * sigma
    th = corners_theta[k] - yaw[:, None] + rng.normal(0, np.radians(1.0), (len(k), 2))
    n_false = int(false_share * len(k))
    fs = rng.integers(0, n, n_false)
    x = np.concatenate([x, rng.uniform(-30, 30, n_false)])
    y = np.concatenate([y, rng.uniform(-15, 15, n_false)])
    th = np.vstack([th, rng.uniform(-np.pi, np.pi, (n_false, 2))])
    scan = np.concatenate([scan, fs])
    truth_idx = np.concatenate([k, np.full(n_false, -1)]).astype(np.int32)
    sigma = np.concatenate([sigma, np.full(n_false, 0.05)])
    stamps = (np.arange(n) * 100_000_000).astype(np.int64)
    corners = pa.Table.from_pydict({
        "drive": [drive] * len(scan), "chunk": (scan // 200).astype(np.int32), "scan_id": scan.astype(np.int64),
        "stamp_ns": stamps[scan], "corner_idx": truth_idx, "x_m": x, "y_m": y,
        "theta1_rad": th[:, 0], "theta2_rad": th[:, 1], "cov_xx_m2": sigma**2, "cov_xy_m2": np.zeros(len(scan)),
        "cov_yy_m2": sigma**2, "n_layers": np.full(len(scan), 6, np.int16), "range_m": np.hypot(x, y),
        "interior_angle_rad": np.full(len(scan), np.pi / 2), "convex": np.ones(len(scan), bool),
        "time_offset_s": np.full(len(scan), np.nan)},
        schema=SCHEMAS["corners_per_scan"])
    # optimized poses: truth + a smooth drift (random walk low-passed), in the vehicle reference point
    drift = np.cumsum(rng.normal(0, 1, (n, 2)), axis=0)
    drift -= drift.mean(0)
    drift *= drift_m / max(drift.std(), 1e-9)
    q = Rotation.from_euler("z", route[:, 2:3]).as_quat()
    cov = np.tile(np.diag([drift_m**2, drift_m**2, 1e-6]).ravel(), (n, 1))
    poses = pa.Table.from_pydict({
        "drive": [drive] * n, "scan_id": np.arange(n, dtype=np.int64), "stamp_ns": stamps,
        "x_m": route[:, 0] + drift[:, 0], "y_m": route[:, 1] + drift[:, 1], "z_m": np.zeros(n),
        "qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2], "qw": q[:, 3],
        "cov_xy_yaw": pa.FixedSizeListArray.from_arrays(pa.array(cov.ravel()), 9)},
        schema=SCHEMAS["poses_optimized"])
    return corners, poses


def drive_info_table(drives: list[str]) -> pa.Table:
    return pa.Table.from_pylist(
        [
            {
                "drive": d,
                "sensor": "synthetic",
                "T_vehicle_lidar": T_VEHICLE_LIDAR.ravel().tolist(),
                "origin_lat_deg": 37.4979,
                "origin_lon_deg": 127.0276,
                "origin_h_m": 57.0,
                "n_scans": 0,
                "n_quarantined": 0,
                "drive_file": "",
            }
            for d in drives
        ],
        schema=SCHEMAS["drive_info"],
    )
