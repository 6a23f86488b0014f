"""Odometry over a sequence of scans, in named steps: prepare (``prepare.py``), pair, register, deskew over the
own sweep and register again, vehicle-frame edges with the gate, span edges.

Arrays in, arrays out. ``T_vehicle_lidar`` maps lidar points into the vehicle frame; an edge is
``T_prev_curr`` of the vehicle frame with its 6x6 information (gtsam order, body frame of the edge).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.common.deskew import deskew_with_transform, interpolate_transform
from stages.common.geometry import se3_inverse
from stages.common.ground_plane import on_road_planes
from stages.common.registration import (
    RegistrationResult,
    adjoint_se3,
    floor_information,
    plane_hessian,
    register_clouds,
)
from stages.odometry.config import GateConfig, PrepareConfig
from stages.odometry.params import OdometryParams
from stages.odometry.prepare import PreparedScan, prepare_scan, prepare_scans


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
    accepted: bool  # the gate's decision (gate_edge): registered, enough overlap, near the reference increment
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
    m = interpolate_transform(T, np.array([ratio]))
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = m.R[0], m.t_m[0]
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


@dataclass(frozen=True)
class PriorPoses:
    """A drive's prior trajectory for the odometry: scan_id -> T_frame_vehicle (any frame: only increments are
    used) and the std the drive file states for it (the largest per axis)."""

    T: dict[int, np.ndarray]
    sigma_m: float
    sigma_rad: float


@dataclass(frozen=True)
class _Pairs:
    """Consecutive scan pairs by position ``k`` (scan k-1 -> k): their duration, reference increments (the wheel
    guide, else the prior trajectory's, else the GNSS/INS's), which of them are guided, the gate's limits of the
    reference (m, rad) and which pairs are keyframe pairs (``keyframes.py``)."""

    k: list[int]
    dt_s: dict[int, float]
    reference_v: dict[int, np.ndarray]
    guided: set[int]
    limits: dict[int, tuple[float, float]] = None
    keyframe: frozenset[int] = frozenset()


def pair_scans(scans: list[Scan], gnss_poses: dict[int, np.ndarray],
               guide_increments: dict[int, np.ndarray] | None, prior: PriorPoses | None = None,
               cfg: OdometryParams | None = None) -> _Pairs:
    """Step 2: the consecutive pairs (ids k-1, k), their reference increments and the gate's limits."""
    pairs = [k for k in range(1, len(scans)) if scans[k].scan_id == scans[k - 1].scan_id + 1]
    dt_s = {k: (scans[k].stamp_ns - scans[k - 1].stamp_ns) * 1e-9 for k in pairs}
    g = cfg.gate if cfg is not None else None
    base = (g.max_deviation_m, g.max_deviation_rad) if g else (np.inf, np.inf)
    reference, limits = {}, {}
    for k in pairs:
        a, b = scans[k - 1].scan_id, scans[k].scan_id
        if a in gnss_poses and b in gnss_poses:
            reference[k], limits[k] = se3_inverse(gnss_poses[a]) @ gnss_poses[b], base
    if prior is not None and cfg is not None:  # a prior's increments: its std twice, at prior_gate_sigmas
        n = cfg.keyframe.prior_gate_sigmas * np.sqrt(2.0)
        for k in pairs:
            a, b = scans[k - 1].scan_id, scans[k].scan_id
            if a in prior.T and b in prior.T:
                reference[k] = se3_inverse(prior.T[a]) @ prior.T[b]
                limits[k] = (n * prior.sigma_m, n * prior.sigma_rad)
    guided = {k for k in pairs if guide_increments and scans[k].scan_id in guide_increments}
    for k in guided:
        reference[k] = guide_increments[scans[k].scan_id]
        limits[k] = (g.max_deviation_guide_m, g.max_deviation_guide_rad) if g else base
    keyframe = frozenset(k for k in pairs if cfg is not None and dt_s[k] > cfg.keyframe.min_dt_s and k not in guided)
    return _Pairs(pairs, dt_s, reference, guided, limits, keyframe)


def register_pairs(prepared: list[PreparedScan], pairs: _Pairs, T_vehicle_lidar: np.ndarray, cfg: OdometryParams,
                   guesses_l: dict[int, np.ndarray] | None = None) -> dict[int, RegistrationResult]:
    """Step 3: register every pair's structure clouds. Initial guess: ``guesses_l`` (lidar frame) when given,
    else the reference increment, else constant velocity from the last converged pair.

    A guided pair (wheel increment) starts from its guide corrected by the previous pair's registration
    (``guide_correction``: the guide's error, from wheel scale, gyro bias and deskew, changes slowly from scan to
    scan) and stops at ``cfg.icp.guided_relative_tolerance``. Open3D's criterion stops while the estimate still
    creeps towards the optimum, so a loose one leaves part of the start's error in the edge: from the raw guide,
    3e-3 tripled the ICP-only heading drift over 1,000-1,500 scans (gangnam seed 2 0.047 -> 0.128 deg, demo seed 3
    -0.133 -> -0.428 deg); from the corrected guide, 3e-3 left it as at 1e-4 (0.051, -0.136 deg) with 1.65-1.76 GICP
    iterations instead of 2.84-3.08 (``bench/bench_odometry_guess.py``; docs/posegraph.md, "The guided start")."""
    from stages.odometry.keyframes import global_guess_l, register_keyframe_pair

    T_lidar_vehicle = se3_inverse(T_vehicle_lidar)
    out: dict[int, RegistrationResult] = {}
    last_v, last_dt = None, None
    corrected: tuple[int, np.ndarray] | None = None  # (pair, its registration relative to its guide) of the last pair
    for k in pairs.k:
        guided = guesses_l is None and k in pairs.guided
        if k in pairs.keyframe:  # metres apart: no constant velocity; coarse-to-fine GICP
            if guesses_l is not None:
                guess_l = guesses_l[k]
            elif k in pairs.reference_v:
                guess_l = T_lidar_vehicle @ pairs.reference_v[k] @ T_vehicle_lidar
            else:
                guess_l = global_guess_l(prepared[k], prepared[k - 1], T_vehicle_lidar, cfg, seed=k)
            out[k] = register_keyframe_pair(prepared[k], prepared[k - 1], guess_l, T_vehicle_lidar, cfg)
            corrected = None
            continue
        if guesses_l is not None:
            guess_l = guesses_l[k]
        else:
            ratio = pairs.dt_s[k] / last_dt if (pairs.dt_s[k] > 0 and last_dt) else 1.0
            guess_v = pairs.reference_v.get(k)
            if guided and corrected is not None and corrected[0] == k - 1:
                guess_v = guess_v @ corrected[1]
            guess_v = guess_v if guess_v is not None else initial_guess(None, None, last_v, ratio)
            guess_l = T_lidar_vehicle @ guess_v @ T_vehicle_lidar
        res = register_clouds(prepared[k].structure, prepared[k - 1].structure, guess_l,
                              **cfg.registration_kwargs(guided=guided))
        out[k] = res
        registered_v = T_vehicle_lidar @ res.T_target_source @ T_lidar_vehicle
        if res.converged and guesses_l is None:
            last_v, last_dt = registered_v, pairs.dt_s[k]
        c = guide_correction(pairs.reference_v[k], registered_v, res.fitness, cfg.gate) \
            if guided and res.converged else None
        corrected = None if c is None else (k, c)
    return out


def guide_correction(guide_v: np.ndarray, registered_v: np.ndarray, fitness: float, gate: GateConfig
                     ) -> np.ndarray | None:
    """The registration relative to its wheel guide (vehicle frame, ``guide^-1 @ registered``), or None where the
    gate would reject the pair against its guide (``gate_edge``, planar): a failed registration must not steer the
    next one."""
    if not gate_edge(registered_v, guide_v, fitness, True, min_fitness=gate.min_fitness,
                     max_deviation_m=gate.max_deviation_guide_m, max_deviation_rad=gate.max_deviation_guide_rad,
                     planar=True):
        return None
    return se3_inverse(guide_v) @ registered_v


def with_road(src: PreparedScan, tgt: PreparedScan, res: RegistrationResult) -> np.ndarray:
    """The registration with height, roll and pitch from the two scans' road planes."""
    return on_road_planes(res.T_target_source, res.converged, src.plane, tgt.plane)


def deskew_own_sweep(prepared: list[PreparedScan], pairs: _Pairs, results: dict[int, RegistrationResult],
                     T_vehicle_lidar: np.ndarray, cfg: PrepareConfig, with_cov: bool
                     ) -> tuple[list[PreparedScan], dict[int, np.ndarray]]:
    """Step 4 (``deskew``): each timed scan deskewed with the motion over *its own* sweep (the edge to the next
    scan; the last scan uses the edge before it), prepared again. Returns the scans and the motions (lidar
    frame), which are the next registration's initial guesses. The sweep motion includes the road planes'
    height/roll/pitch: structure-only ICP leaves them weak, and a wrong roll rate tilts the deskewed scan
    (measured: 0.09 deg roll error per edge)."""
    motion = {k: with_road(prepared[k], prepared[k - 1], r) for k, r in results.items()}
    out = list(prepared)
    for i, p in enumerate(prepared):
        if p.time_offset_s is None:
            continue
        own = next((k for k in (i + 1, i) if k in results and results[k].converged and pairs.dt_s[k] > 0), None)
        if own is None:
            continue
        pts = deskew_with_transform(p.points_m, p.time_offset_s, motion[own], pairs.dt_s[own])
        out[i] = prepare_scan(pts, None, T_vehicle_lidar, cfg, with_cov)
    return out, motion


def vehicle_edge(src: PreparedScan, tgt: PreparedScan, res: RegistrationResult, T_vehicle_lidar: np.ndarray,
                 cfg: OdometryParams) -> tuple[np.ndarray, np.ndarray]:
    """Vehicle-frame increment (road planes applied) and its information: the structure's point-to-plane
    Hessian, plus the ground's on the target's road plane where the road planes were used (height, roll, pitch;
    ``registration.plane_hessian``); floored; a rotation term in turns."""
    info = cfg.information
    H = res.hessian  # the structure's, computed by register_clouds with the same max_corr_m / point_sigma_m
    T_l = with_road(src, tgt, res)
    if T_l is not res.T_target_source and src.ground_points_m is not None and tgt.ground_points_m is not None:
        H = H + plane_hessian(src.ground_voxels_m, tgt.ground_voxels_m, tgt.plane.normal, T_l, cfg.icp.max_corr_m,
                              info.point_sigma_m)
    T_v, info_v = lidar_to_vehicle_edge(T_l, floor_information(H, info.min_sigma_m, info.min_sigma_rad),
                                        T_vehicle_lidar)
    if info.rot_sigma_per_rad > 0:  # turns: residual rotation error grows with the edge's rotation
        info_v = floor_information(info_v, 1e-9, info.rot_sigma_per_rad * rotation_angle_rad(T_v) + 1e-12)
    return T_v, info_v


def consecutive_edges(scans: list[Scan], prepared: list[PreparedScan], pairs: _Pairs,
                      results: dict[int, RegistrationResult], T_vehicle_lidar: np.ndarray, cfg: OdometryParams
                      ) -> list[Edge]:
    """Step 5: every pair's vehicle edge with the gate's decision (guided pairs: the planar guide gate)."""
    from stages.odometry.keyframes import keyframe_information, plausible_motion, widened_limits

    g = cfg.gate
    edges: list[Edge] = []
    for k in pairs.k:
        res = results[k]
        T_v, info_v = vehicle_edge(prepared[k], prepared[k - 1], res, T_vehicle_lidar, cfg)
        guided = k in pairs.guided
        limit_m, limit_rad = (pairs.limits or {}).get(k, (g.max_deviation_m, g.max_deviation_rad))
        if k in pairs.keyframe:
            distance_m = float(np.linalg.norm(T_v[:3, 3]))
            limit_m, limit_rad = widened_limits(limit_m, limit_rad, distance_m, cfg.keyframe)
            info_v = keyframe_information(info_v, distance_m, cfg.keyframe)
        accepted = gate_edge(T_v, pairs.reference_v.get(k), res.fitness, res.converged, min_fitness=g.min_fitness,
                             max_deviation_m=limit_m, max_deviation_rad=limit_rad, planar=guided)
        if k in pairs.keyframe:
            accepted = accepted and plausible_motion(T_v, cfg.keyframe.max_sideslip_rad)
        edges.append(Edge(scans[k].scan_id, scans[k].stamp_ns, T_v, res.fitness, res.inlier_rmse_m, info_v,
                          accepted))
    return edges


def span_edges(scans: list[Scan], prepared: list[PreparedScan], pairs: _Pairs, edges: list[Edge],
               T_vehicle_lidar: np.ndarray, cfg: OdometryParams) -> list[Edge]:
    """Step 6 (``span_scans``): each scan at a position i that is a multiple of N registered onto the scan N
    positions before, from the chain of the N accepted consecutive edges between them and gated against it."""
    g = cfg.gate
    T_lidar_vehicle = se3_inverse(T_vehicle_lidar)
    by_position = dict(zip(pairs.k, edges))
    out: list[Edge] = []
    for span in sorted(set(int(n) for n in cfg.span_scans if int(n) > 1)):
        for i in range(span, len(scans), span):
            chain = [by_position.get(k) for k in range(i - span + 1, i + 1)]
            if any(k in pairs.keyframe for k in range(i - span + 1, i + 1)):
                continue  # N keyframes span tens of metres: no span edge
            if any(e is None or not e.accepted for e in chain):
                continue  # a gap or a rejected edge inside: no reference to start from or gate against
            T_chain_v = np.eye(4)
            for e in chain:
                T_chain_v = T_chain_v @ e.T_prev_curr
            src, tgt = prepared[i], prepared[i - span]
            res = register_clouds(src.structure, tgt.structure, T_lidar_vehicle @ T_chain_v @ T_vehicle_lidar,
                                  **cfg.registration_kwargs())
            T_v, info_v = vehicle_edge(src, tgt, res, T_vehicle_lidar, cfg)
            accepted = gate_edge(T_v, T_chain_v, res.fitness, res.converged, min_fitness=g.min_fitness,
                                 max_deviation_m=g.max_deviation_m, max_deviation_rad=g.max_deviation_rad)
            out.append(Edge(scans[i].scan_id, scans[i].stamp_ns, T_v, res.fitness, res.inlier_rmse_m, info_v,
                            accepted, span))
    return out


def estimate_edges(scans: list[Scan], T_vehicle_lidar: np.ndarray, gnss_poses: dict[int, np.ndarray],
                   cfg: OdometryParams, guide_increments: dict[int, np.ndarray] | None = None, *,
                   release_points: bool = False, prior: PriorPoses | None = None) -> list[Edge]:
    """Register each scan onto its predecessor (``scans`` sorted by id; pairs need consecutive ids).

    ``gnss_poses`` maps scan_id -> T_map_vehicle for scans with a valid GNSS/INS solution (initial guesses and
    the deviation gate). Scans whose ``time_offset_s`` is None are taken as already motion-compensated (e.g.
    with wheel odometry by the stage). With ``ground_split`` the road plane is fitted per scan, the structure
    above it is registered (GICP) and the ground planes then fix height, roll and pitch; the information sums
    the point-to-plane Hessians of structure and ground (the latter on the road plane). With ``deskew`` and
    per-point times, a first pass estimates every edge, each scan is then deskewed with the motion over its own
    sweep and registered again (deskewing both scans of a pair with the pair's motion cancels nothing in turns).
    ``guide_increments`` (scan_id -> vehicle increment from the previous scan, e.g. wheel odometry) replace the
    GNSS/INS increments as initial guess and gate reference where given: a multipath jump makes a GNSS
    increment tens of centimetres wrong, which rejected correct ICP edges (measured on the simulator). Edges
    with a guide are gated at ``max_deviation_guide_m`` / ``_rad`` (the guide is far better than GNSS/INS).
    Span edges (``Edge.span`` = N, after the consecutive ones in the returned list) carry the same information
    model; each spans N scans with one registration error instead of N, which cuts the random walk and the
    per-edge bias of chained scan-to-scan ICP.
    With ``release_points`` the raw points of ``scans`` are released once the scans are prepared (each item of the
    list is replaced by the same scan without points): a chunk of 100 real HDL-64E scans holds 0.4 GB of them.
    ``prior`` (a prior trajectory's poses) gives reference increments where there is no guide, in place of the GNSS/
    INS's, gated at its stated std. Pairs further apart in time than ``cfg.keyframe.min_dt_s`` are keyframe pairs
    (``keyframes.py``).
    """
    with_cov = cfg.icp.method == "gicp"
    prepared = prepare_scans(scans, T_vehicle_lidar, cfg.prepare, with_cov)
    if release_points:
        scans[:] = [Scan(s.scan_id, s.stamp_ns, np.zeros((0, 3)), None) for s in scans]
    pairs = pair_scans(scans, gnss_poses, guide_increments, prior, cfg)
    results = register_pairs(prepared, pairs, T_vehicle_lidar, cfg)
    if cfg.own_sweep_deskew and any(p.time_offset_s is not None for p in prepared):
        prepared, motion = deskew_own_sweep(prepared, pairs, results, T_vehicle_lidar, cfg.prepare, with_cov)
        results = register_pairs(prepared, pairs, T_vehicle_lidar, cfg, guesses_l=motion)
    edges = consecutive_edges(scans, prepared, pairs, results, T_vehicle_lidar, cfg)
    return edges + span_edges(scans, prepared, pairs, edges, T_vehicle_lidar, cfg)
