"""Odometry over a sequence of scans: initial guesses, deskewing, registration, vehicle-frame edges.

Arrays in, arrays out. ``T_vehicle_lidar`` maps lidar points into the vehicle frame; an edge is
``T_prev_curr`` of the vehicle frame with its 6x6 information (gtsam order, body frame of the edge).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import open3d as o3d

from stages.common.geometry import se3_inverse
from stages.common.ground_plane import GroundPlane, align_ground_planes, fit_ground_plane, ground_mask
from stages.common.registration import (
    RegistrationResult,
    adjoint_se3,
    crop_range,
    deskew_points,
    floor_information,
    point_to_plane_hessian,
    prepare_cloud,
    register_clouds,
)


@dataclass(frozen=True)
class Scan:
    scan_id: int
    stamp_ns: int
    points_lidar_m: np.ndarray  # (N,3)
    time_offset_s: np.ndarray | None  # (N,) or None when the scan carries no per-point time


@dataclass(frozen=True)
class Edge:
    scan_id: int  # the later scan; the earlier is scan_id - span
    stamp_ns: int
    T_prev_curr: np.ndarray  # vehicle frame
    fitness: float
    inlier_rmse_m: float
    information: np.ndarray  # 6x6 gtsam order
    converged: bool
    span: int = 1  # 1: consecutive scans; N > 1: a span edge over N scans (``span_scans``)

    @property
    def scan_id_from(self) -> int:
        return self.scan_id - self.span


def lidar_to_vehicle_edge(T_lprev_lcurr: np.ndarray, information_lidar: np.ndarray,
                          T_vehicle_lidar: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Move a lidar-frame relative pose and its body-frame information into the vehicle frame."""
    T_lidar_vehicle = se3_inverse(T_vehicle_lidar)
    T_v = T_vehicle_lidar @ T_lprev_lcurr @ T_lidar_vehicle
    Ad = adjoint_se3(T_lidar_vehicle)  # xi_lidar = Ad(T_lidar_vehicle) xi_vehicle
    return T_v, Ad.T @ information_lidar @ Ad


def initial_guess(prev_pose_map: np.ndarray | None, curr_pose_map: np.ndarray | None,
                  last_edge: np.ndarray | None, dt_ratio: float) -> np.ndarray:
    """Vehicle increment guess: the GNSS/INS increment when both poses exist, else constant velocity."""
    if prev_pose_map is not None and curr_pose_map is not None:
        return se3_inverse(prev_pose_map) @ curr_pose_map
    if last_edge is None:
        return np.eye(4)
    return scale_motion(last_edge, dt_ratio)


def scale_motion(T: np.ndarray, ratio: float) -> np.ndarray:
    """Constant-velocity extrapolation of a small motion to ``ratio`` times its duration."""
    from scipy.spatial.transform import Rotation

    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(ratio * Rotation.from_matrix(T[:3, :3]).as_rotvec()).as_matrix()
    out[:3, 3] = ratio * T[:3, 3]
    return out


def rotation_angle_rad(T: np.ndarray) -> float:
    """Angle of the rotation part of a 4x4 transform."""
    return float(np.arccos(np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))


def gate_edge(T_v: np.ndarray, T_gnss_v: np.ndarray | None, fitness: float, registered: bool, *,
              min_fitness: float, max_deviation_m: float, max_deviation_rad: float, planar: bool = False) -> bool:
    """Accept an ICP edge: registration converged, enough overlap, and (when a reference increment exists)
    within ``max_deviation_m`` / ``max_deviation_rad`` of it. 10 Hz GNSS/INS increments are good to ~0.1 m and
    ~0.05 deg on the simulator, so an edge far from them is a registration failure (degenerate scene).
    ``planar``: the reference is a wheel-odometry increment, which knows nothing of height, roll and pitch;
    only the horizontal translation and the heading are compared."""
    if not registered or fitness < min_fitness:
        return False
    if T_gnss_v is None:
        return True
    D = se3_inverse(T_gnss_v) @ T_v
    if planar:
        return bool(np.linalg.norm(D[:2, 3]) <= max_deviation_m
                    and abs(np.arctan2(D[1, 0], D[0, 0])) <= max_deviation_rad)
    return bool(np.linalg.norm(D[:3, 3]) <= max_deviation_m and rotation_angle_rad(D) <= max_deviation_rad)


@dataclass
class _Prepared:
    """One scan ready for registration: structure cloud (registration), road plane and ground points (height,
    roll, pitch and their information)."""

    points_m: np.ndarray
    time_offset_s: np.ndarray | None
    structure: o3d.geometry.PointCloud
    plane: GroundPlane | None
    ground_points_m: np.ndarray | None
    voxel_m: float
    knn: int

    @cached_property
    def ground(self) -> o3d.geometry.PointCloud | None:
        """Ground cloud with normals, built on first use (only the final edges' information needs it; scans
        deskewed after a first pass are prepared again)."""
        if self.ground_points_m is None:
            return None
        return prepare_cloud(self.ground_points_m, self.voxel_m, self.knn, with_covariances=False)


def _prepare(points_m: np.ndarray, time_offset_s: np.ndarray | None, T_vehicle_lidar: np.ndarray, *,
             voxel_m: float, knn: int, with_cov: bool, ground_split: bool, ground_tolerance_m: float) -> _Prepared:
    plane = fit_ground_plane(points_m, T_vehicle_lidar) if ground_split else None
    if plane is None:
        return _Prepared(points_m, time_offset_s, prepare_cloud(points_m, voxel_m, knn, with_covariances=with_cov),
                         None, None, voxel_m, knn)
    on_ground = ground_mask(points_m, plane, ground_tolerance_m)
    return _Prepared(points_m, time_offset_s,
                     prepare_cloud(points_m[~on_ground], voxel_m, knn, with_covariances=with_cov), plane,
                     points_m[on_ground], voxel_m, knn)


def estimate_edges(scans: list[Scan], T_vehicle_lidar: np.ndarray, gnss_poses: dict[int, np.ndarray], *,
                   method: str, voxel_m: float, knn: int, max_corr_m: float, max_iterations: int,
                   relative_tolerance: float, min_range_m: float, max_range_m: float, deskew: bool,
                   min_fitness: float, max_deviation_m: float, max_deviation_rad: float, point_sigma_m: float,
                   min_sigma_m: float, min_sigma_rad: float, rot_sigma_per_rad: float = 0.0,
                   ground_split: bool = True, ground_tolerance_m: float = 0.25,
                   guide_increments: dict[int, np.ndarray] | None = None,
                   max_deviation_guide_m: float = 0.05, max_deviation_guide_rad: float = 0.0035,
                   span_scans: tuple[int, ...] | list[int] = ()) -> list[Edge]:
    """Register each scan onto its predecessor (``scans`` sorted by id; pairs need consecutive ids).

    ``gnss_poses`` maps scan_id -> T_map_vehicle for scans with a valid GNSS/INS solution (initial guesses and
    the deviation gate). Scans whose ``time_offset_s`` is None are taken as already motion-compensated (e.g.
    with wheel odometry by the stage). With ``ground_split`` the road plane is fitted per scan, the structure
    above it is registered (GICP) and the ground planes then fix height, roll and pitch; the information sums
    the point-to-plane Hessians of structure and ground. With ``deskew`` and per-point times, a first pass
    estimates every edge, each scan is then deskewed with the motion over *its own* sweep (the edge to the next
    scan; the last scan uses the edge before it) and registered again. (Deskewing both scans of a pair with the
    pair's motion, as an earlier version did, cancels nothing in turns; measured in docs/posegraph.md.)
    ``rot_sigma_per_rad`` adds a rotation std proportional to the edge's rotation angle.
    ``guide_increments`` (scan_id -> vehicle increment from the previous scan, e.g. wheel odometry) replace the
    GNSS/INS increments as initial guess and gate reference where given: a multipath jump makes a GNSS
    increment tens of centimetres wrong, which rejected correct ICP edges (measured on the simulator). Edges
    with a guide are gated at ``max_deviation_guide_m`` / ``_rad`` (the guide is far better than GNSS/INS).
    ``span_scans`` (e.g. (10, 30, 90)): after the consecutive edges, each scan at a position i that is a multiple
    of N in ``scans`` is also registered onto the scan N positions before it, starting from the chain of the N
    accepted consecutive edges between them and gated against that chain (``max_deviation_m`` / ``_rad``). These
    span edges (``Edge.span`` = N, after the consecutive ones in the returned list) carry the same information
    model; each spans N scans with one registration error instead of N, which cuts the random walk and the
    per-edge bias of chained scan-to-scan ICP (gangnam: docs/posegraph.md, tenth pass).
    """
    T_lidar_vehicle = se3_inverse(T_vehicle_lidar)
    to_lidar = lambda T_v: T_lidar_vehicle @ T_v @ T_vehicle_lidar  # noqa: E731
    with_cov = method == "gicp"
    prep_kw = dict(voxel_m=voxel_m, knn=knn, with_cov=with_cov, ground_split=ground_split,
                   ground_tolerance_m=ground_tolerance_m)
    prepared = []
    for scan in scans:
        ok = crop_range(scan.points_lidar_m, min_range_m, max_range_m)
        t_s = scan.time_offset_s[ok] if scan.time_offset_s is not None else None
        prepared.append(_prepare(scan.points_lidar_m[ok], t_s, T_vehicle_lidar, **prep_kw))
    pairs = [k for k in range(1, len(scans)) if scans[k].scan_id == scans[k - 1].scan_id + 1]
    dt_s = {k: (scans[k].stamp_ns - scans[k - 1].stamp_ns) * 1e-9 for k in pairs}
    T_gnss_v = {k: se3_inverse(gnss_poses[scans[k - 1].scan_id]) @ gnss_poses[scans[k].scan_id]
                for k in pairs if scans[k - 1].scan_id in gnss_poses and scans[k].scan_id in gnss_poses}
    guided = {k for k in pairs if guide_increments and scans[k].scan_id in guide_increments}
    for k in guided:
        T_gnss_v[k] = guide_increments[scans[k].scan_id]
    reg = dict(method=method, max_corr_m=max_corr_m, max_iterations=max_iterations, point_sigma_m=point_sigma_m,
               min_sigma_m=min_sigma_m, min_sigma_rad=min_sigma_rad, relative_tolerance=relative_tolerance)

    def register_all(guesses: dict[int, np.ndarray] | None) -> dict[int, RegistrationResult]:
        out: dict[int, RegistrationResult] = {}
        last_v, last_dt = None, None
        for k in pairs:
            if guesses is not None:
                guess_l = guesses[k]
            else:
                ratio = dt_s[k] / last_dt if (dt_s[k] > 0 and last_dt) else 1.0
                guess_v = T_gnss_v.get(k)
                guess_l = to_lidar(guess_v if guess_v is not None else initial_guess(None, None, last_v, ratio))
            res = register_clouds(prepared[k].structure, prepared[k - 1].structure, guess_l, **reg)
            out[k] = res
            if res.converged and guesses is None:
                last_v, last_dt = T_vehicle_lidar @ res.T_target_source @ T_lidar_vehicle, dt_s[k]
        return out

    def with_road(src: _Prepared, tgt: _Prepared, res: RegistrationResult) -> np.ndarray:
        """The registration with height, roll and pitch from the two scans' road planes."""
        if res.converged and src.plane is not None and tgt.plane is not None:
            return align_ground_planes(res.T_target_source, src.plane, tgt.plane)
        return res.T_target_source

    def vehicle_edge(src: _Prepared, tgt: _Prepared, res: RegistrationResult) -> tuple[np.ndarray, np.ndarray]:
        """Vehicle-frame increment (road planes applied) and its information: the structure's point-to-plane
        Hessian, plus the ground's where the road planes were used; floored; a rotation term in turns."""
        H = res.hessian  # the structure's, computed by register_clouds with the same max_corr_m / point_sigma_m
        T_l = with_road(src, tgt, res)
        if T_l is not res.T_target_source and src.ground is not None and tgt.ground is not None:
            H = H + point_to_plane_hessian(src.ground, tgt.ground, T_l, max_corr_m, point_sigma_m)
        T_v, info_v = lidar_to_vehicle_edge(T_l, floor_information(H, min_sigma_m, min_sigma_rad), T_vehicle_lidar)
        if rot_sigma_per_rad > 0:  # turns: residual rotation error grows with the edge's rotation
            info_v = floor_information(info_v, 1e-9, rot_sigma_per_rad * rotation_angle_rad(T_v) + 1e-12)
        return T_v, info_v

    results = register_all(None)
    timed = [p.time_offset_s is not None for p in prepared]
    if deskew and any(timed):
        # the sweep motion must include the road planes' height/roll/pitch: structure-only ICP leaves them
        # weak, and a wrong roll rate tilts the deskewed scan (measured: 0.09 deg roll error per edge)
        motion = {k: with_road(prepared[k], prepared[k - 1], r) for k, r in results.items()}
        for i, p in enumerate(prepared):
            if not timed[i]:
                continue
            own = next((k for k in (i + 1, i) if k in results and results[k].converged and dt_s[k] > 0), None)
            if own is None:
                continue
            pts = deskew_points(p.points_m, p.time_offset_s, motion[own], dt_s[own])
            prepared[i] = _prepare(pts, None, T_vehicle_lidar, **prep_kw)
        results = register_all(motion)

    edges: list[Edge] = []
    for k in pairs:
        res = results[k]
        T_v, info_v = vehicle_edge(prepared[k], prepared[k - 1], res)
        accepted = gate_edge(T_v, T_gnss_v.get(k), res.fitness, res.converged, min_fitness=min_fitness,
                             max_deviation_m=max_deviation_guide_m if k in guided else max_deviation_m,
                             max_deviation_rad=max_deviation_guide_rad if k in guided else max_deviation_rad,
                             planar=k in guided)
        edges.append(Edge(scans[k].scan_id, scans[k].stamp_ns, T_v, res.fitness, res.inlier_rmse_m, info_v,
                          accepted))
    by_position = dict(zip(pairs, edges))
    for span in sorted(set(int(n) for n in span_scans if int(n) > 1)):
        for i in range(span, len(scans), span):
            chain = [by_position.get(k) for k in range(i - span + 1, i + 1)]
            if any(e is None or not e.converged for e in chain):
                continue  # a gap or a rejected edge inside: no reference to start from or gate against
            T_chain_v = np.eye(4)
            for e in chain:
                T_chain_v = T_chain_v @ e.T_prev_curr
            src, tgt = prepared[i], prepared[i - span]
            res = register_clouds(src.structure, tgt.structure, to_lidar(T_chain_v), **reg)
            T_v, info_v = vehicle_edge(src, tgt, res)
            accepted = gate_edge(T_v, T_chain_v, res.fitness, res.converged, min_fitness=min_fitness,
                                 max_deviation_m=max_deviation_m, max_deviation_rad=max_deviation_rad)
            edges.append(Edge(scans[i].scan_id, scans[i].stamp_ns, T_v, res.fitness, res.inlier_rmse_m, info_v,
                              accepted, span))
    return edges
