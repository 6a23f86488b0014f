"""Engines and trajectory metrics of the odometry bench: our odometry stage's algorithm chunk by chunk, kiss-icp,
and the comparisons (per-step differences, errors against truth, time alignment of kiss-icp's poses)."""
from __future__ import annotations

import itertools
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from bench.odometry_sources import ScanFile


@dataclass(frozen=True)
class Run:
    """One engine's trajectory: ``poses[k]`` is T_first_vehicle (vehicle frame of its first pose) at the start
    of scan ``k + pose_shift``."""

    engine: str
    threads: int
    poses: np.ndarray  # (N,4,4)
    seconds: float  # registration only
    n_registered: int
    n_flagged: int  # edges our gate did not accept (chained anyway: ICP-only)
    pose_shift: int


def kiss_available() -> bool:
    try:
        import kiss_icp.kiss_icp  # noqa: F401
    except ImportError:
        return False
    return True


# ---------------------------------------------------------------- engines
def chain(increments: Iterable[np.ndarray]) -> np.ndarray:
    poses = [np.eye(4)]
    for T in increments:
        poses.append(poses[-1] @ T)
    return np.array(poses)


def odometry_ours(chunks: Iterable[list], T_vehicle_lidar: np.ndarray, track=None, threads: int = 0,
                  engine: str = "ours", **overrides) -> Run:
    """Our odometry stage's algorithm, chunk by chunk as the stage runs it, without GNSS/INS (ICP-only);
    wheel deskew and wheel guides where ``track`` is given and the params say deskew='odometry'. ``overrides``: our
    params' keys, dotted for a section's (``**{"prepare.voxel_m": 0.5}``)."""
    from pipeline.declare import nested
    from stages.odometry.compute import deskew_with_wheel_odometry, wheel_guides
    from stages.odometry.core import estimate_edges
    from stages.odometry.params import OdometryParams

    p = cfg = OdometryParams.model_validate(nested(overrides))
    edges, seconds, prev = [], 0.0, None
    for chunk in chunks:
        scans = ([prev] if prev is not None else []) + chunk
        t0 = time.perf_counter()
        guides = wheel_guides(scans, track)
        if p.deskew == "odometry":
            scans, _ = deskew_with_wheel_odometry(scans, track, T_vehicle_lidar)
        edges += estimate_edges(scans, T_vehicle_lidar, {}, cfg, guide_increments=guides or None)
        seconds += time.perf_counter() - t0  # span edges (p.span_scans) are part of the stage's cost
        prev = chunk[-1]
    edges = [e for e in edges if e.span == 1]  # the dead-reckoning chain
    ids = [e.scan_id for e in edges]
    if ids and ids != list(range(ids[0], ids[0] + len(ids))):
        raise ValueError(f"{engine}: edges are not consecutive (scan ids {ids[:5]}...); hint: a scan is missing")
    return Run(engine, threads, chain(e.T_prev_curr for e in edges), seconds, len(edges),
               sum(not e.accepted for e in edges), 0)


def kiss_config(threads: int, deskew: bool):
    from kiss_icp.config import load_config

    cfg = load_config(None)  # kiss-icp's defaults, voxel size resolved from max_range as its pipeline does
    cfg.data.deskew = deskew
    cfg.registration.max_num_threads = threads
    return cfg


def odometry_kiss(scans: Iterable, T_vehicle_lidar: np.ndarray, threads: int = 1) -> Run:
    """kiss-icp (its defaults) over the scans; per-point time when the first scan has it (deskew on)."""
    from kiss_icp.kiss_icp import KissICP

    from stages.common.geometry import se3_inverse

    it = iter(scans)
    first = next(it)
    deskew = first.time_offset_s is not None
    odom = KissICP(kiss_config(threads, deskew))
    poses, seconds = [], 0.0
    for s in itertools.chain([first], it):
        t = s.time_offset_s if deskew and s.time_offset_s is not None else np.zeros(len(s.points_lidar_m))
        pts = np.ascontiguousarray(s.points_lidar_m, dtype=np.float64)
        t0 = time.perf_counter()
        odom.register_frame(pts, np.ascontiguousarray(t, dtype=np.float64))
        seconds += time.perf_counter() - t0
        poses.append(odom.last_pose.copy())
    P = T_vehicle_lidar @ np.array(poses) @ se3_inverse(T_vehicle_lidar)
    P = se3_inverse(P[0]) @ P
    return Run("kiss-icp", threads, P, seconds, len(poses), 0, 1 if deskew else 0)


# ---------------------------------------------------------------- metrics
def inverse_poses(T: np.ndarray) -> np.ndarray:
    """Batch inverse of (N,4,4) rigid transforms."""
    out = np.tile(np.eye(4), (len(T), 1, 1))
    Rt = np.transpose(T[:, :3, :3], (0, 2, 1))
    out[:, :3, :3] = Rt
    out[:, :3, 3] = -np.einsum("nij,nj->ni", Rt, T[:, :3, 3])
    return out


def yaw_rad(T: np.ndarray) -> np.ndarray:
    return np.arctan2(T[..., 1, 0], T[..., 0, 0])


def rotation_deg(T: np.ndarray) -> np.ndarray:
    c = (np.trace(T[..., :3, :3], axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.rad2deg(np.arccos(np.clip(c, -1.0, 1.0)))


def steps(P: np.ndarray) -> np.ndarray:
    return inverse_poses(P[:-1]) @ P[1:]


def on_common_scans(runs: list[Run], n_scans: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """Scan indices every run has a pose for (at that scan's start) and each run's poses there, rebased on the
    first common scan."""
    idx = [np.arange(len(r.poses)) + r.pose_shift for r in runs]
    common = np.arange(n_scans)
    for i in idx:
        common = np.intersect1d(common, i)
    out = []
    for r, i in zip(runs, idx):
        P = r.poses[np.searchsorted(i, common)]
        out.append(inverse_poses(P[:1])[0] @ P)
    return common, out


def compare_trajectories(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    """Per-step difference (translation mm, rotation deg) and the position difference after chaining; both
    trajectories on the same scans and rebased on the same first scan."""
    D = inverse_poses(steps(a)) @ steps(b)
    dt_mm = 1000 * np.linalg.norm(D[:, :3, 3], axis=1)
    dr_deg = rotation_deg(D)
    dyaw_deg = np.rad2deg(yaw_rad(D))
    dpos_mm = 1000 * np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=1)
    return {"steps": len(D), "dt_rms_mm": float(np.sqrt(np.mean(dt_mm ** 2))), "dt_max_mm": float(dt_mm.max()),
            "dr_rms_deg": float(np.sqrt(np.mean(dr_deg ** 2))), "dr_max_deg": float(dr_deg.max()),
            "dyaw_rms_deg": float(np.sqrt(np.mean(dyaw_deg ** 2))),
            "dpos_max_mm": float(dpos_mm.max()), "dpos_end_mm": float(dpos_mm[-1])}


def errors_vs_truth(est: np.ndarray, truth: np.ndarray, segment_m: float = 100.0) -> dict[str, float]:
    """ICP-only errors of a trajectory against truth on the same scans (both (N,4,4); est in any frame, started
    at the truth's first pose): per-edge xy / yaw RMS, end position error and its share of the (horizontal)
    distance, the RMS relative error over ``segment_m`` of path in %, and the heading error at the end."""
    est_w = truth[0] @ inverse_poses(est[:1])[0] @ est
    E = inverse_poses(steps(truth)) @ steps(est_w)
    cum = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(truth[:, :2, 3], axis=0), axis=1))]
    end_m = float(np.linalg.norm(est_w[-1, :2, 3] - truth[-1, :2, 3]))
    rpe = []
    for i in range(len(truth)):
        j = int(np.searchsorted(cum, cum[i] + segment_m))
        if j >= len(truth):
            break
        rel_t = inverse_poses(truth[[i]])[0] @ truth[j]
        rel_e = inverse_poses(est_w[[i]])[0] @ est_w[j]
        rpe.append(100 * np.linalg.norm((np.linalg.inv(rel_t) @ rel_e)[:2, 3]) / (cum[j] - cum[i]))
    heading = np.rad2deg(np.angle(np.exp(1j * (yaw_rad(est_w[-1]) - yaw_rad(truth[-1])))))
    return {"edges": len(E), "distance_m": float(cum[-1]),
            "edge_xy_rms_mm": float(1000 * np.sqrt(np.mean(np.sum(E[:, :2, 3] ** 2, axis=1)))),
            "edge_yaw_rms_deg": float(np.rad2deg(np.sqrt(np.mean(yaw_rad(E) ** 2)))),
            "end_xy_m": end_m, "drift_pct": 100 * end_m / cum[-1] if cum[-1] > 0 else float("nan"),
            "rpe_rms_pct": float(np.sqrt(np.mean(np.square(rpe)))) if rpe else float("nan"),
            "end_heading_deg": float(heading)}


def sim_odometry(sim: Path, drive: str, n_scans: int, **overrides) -> tuple[Run, dict[str, float], float]:
    """``odometry_ours`` over the first ``n_scans`` of a simulated drive (its wheel track, 100-scan chunks, the stage's
    params with ``overrides``): the run, its ``errors_vs_truth`` (the truth at the scan starts) and its wall seconds."""
    import time

    from bench.odometry_sources import chunked, sim_extrinsic, sim_files, sim_track

    files = sim_files(sim, drive, n_scans)
    t0 = time.perf_counter()
    run = odometry_ours(chunked(files, 100), sim_extrinsic(sim), sim_track(sim, drive), **overrides)
    total_s = time.perf_counter() - t0
    truth = truth_at_scans(sim / "truth" / f"{drive}_poses_tum.txt", files)
    return run, errors_vs_truth(run.poses, truth[:len(run.poses)]), total_s


def truth_at_scans(path: Path, files: list[ScanFile]) -> np.ndarray:
    """Truth pose at each scan's start (nearest truth sample; refused when more than 5 ms away)."""
    from stages.common.records import Trajectory

    truth = Trajectory.from_tum(path)
    t, T = truth.stamp_s, truth.T
    s = np.array([f.stamp_ns for f in files]) * 1e-9
    i = np.clip(np.searchsorted(t, s), 1, len(t) - 1)
    i = np.where(np.abs(t[i - 1] - s) < np.abs(t[i] - s), i - 1, i)
    worst = float(np.max(np.abs(t[i] - s)))
    if worst > 0.005:
        raise ValueError(f"{path}: no truth sample within 5 ms of every scan start (worst {worst:.3f} s); "
                         "hint: truth and stamps.csv must share the GPS time base")
    return T[i]
