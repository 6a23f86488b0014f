"""One drive over the city: its lane and direction, trajectory, traffic, lidar scans, GNSS/INS solution,
wheel/gyro stream and ground-truth poses, written into ``drive_dir`` and ``truth_dir``.

Drive 0 follows the loop counter-clockwise in the outer lane (the mapping drive, ``map_laps`` laps);
odd drives run the same streets the other way round, even drives use the inner lane; every drive starts
at a different point of the loop.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from stages.simulate import writers
from stages.simulate.gnss import (
    GNSS_RATE_HZ,
    course_over_ground_errors,
    simulate_gnss_errors,
    simulate_odometry,
    sky_blocked_fraction,
)
from stages.simulate.lead_vehicle import plan_lead_traffic
from stages.simulate.mesh import VEHICLE, Scene, TriangleSoup, box_triangles
from stages.simulate.presets import Preset
from stages.simulate.sensor import SCAN_PERIOD_S, rotations_enu_vehicle, simulate_scan
from stages.simulate.sensor_effects import SensorEffects
from stages.simulate.traffic import ego_lanes, generate_traffic
from stages.simulate.trajectory import lane_polyline, plan_drive

GPS_START_S = 200_000.0
ANTENNA_HEIGHT_M = 2.0


@dataclass(frozen=True)
class DriveSpec:
    index: int
    loop: list  # intersection nodes in driving order
    lane: int  # 0 = next to the centre line; large = outermost
    laps: int
    gps_t0_s: float

    @staticmethod
    def for_index(k: int, loop: list, p: Preset, city, seed: int) -> "DriveSpec":
        nodes = loop[::-1] if k % 2 == 1 else list(loop)
        shift = (k * len(nodes)) // 3 % len(nodes)
        nodes = nodes[shift:] + nodes[:shift]
        lane = 9 if k % 4 in (0, 3) else 0
        return DriveSpec(k, nodes, lane, p.map_laps if k == 0 else p.eval_laps, GPS_START_S + 5000.0 * k)


@dataclass(frozen=True)
class DriveResult:
    n_scans: int
    gnss_stats: dict
    scan_positions_en: np.ndarray  # (n_scans, 2) the lidar's horizontal position at each scan start
    route_en: np.ndarray
    lead_scan_share: float  # scans with a vehicle ahead in the ego lane
    start: dict | None = None  # a drive without GNSS: its drive file's start: section


def simulate_drive(spec: DriveSpec, p: Preset, city, static: Scene, buildings: Scene, marks, albedo, beams,
                   calib, origin, drive_dir: Path, truth_dir: Path, motion_distortion: bool,
                   scan_limit: int | None, rng: np.random.Generator,
                   progress: Callable[[int, int], None] | None = None) -> DriveResult:
    from stages.common.geometry import write_tum
    from stages.common.trajectory_frame import frame_header, write_sidecar

    rng_route, rng_traffic, rng_sensor, rng_gnss, rng_odo, rng_lead, rng_effects = rng.spawn(7)
    poly, turns = lane_polyline(city, spec.loop, spec.lane)
    traj = plan_drive(poly, turns, spec.laps, p.cruise_mps, p.stop_share, rng_route, queue_share=p.queue_stop_share)
    traffic = generate_traffic(city, p.traffic_per_km, ego_lanes(city, spec.loop, spec.lane), rng_traffic)
    lead = plan_lead_traffic(traj, p.lead_vehicle_share, rng_lead)
    effects = SensorEffects(p.angular_jitter_deg, p.beam_divergence_mrad, p.mixed_pixel_share,
                            sector_dropout_scan_share=p.sector_dropout_scan_share,
                            sector_dropout_deg=p.sector_dropout_deg)
    scan_dir = drive_dir / "scans"
    scan_dir.mkdir(parents=True, exist_ok=True)

    duration = float(traj.t_s[-1])
    n_scans = int((duration - SCAN_PERIOD_S) / SCAN_PERIOD_S) + 1
    t_scan = np.arange(n_scans) * SCAN_PERIOD_S
    if p.keyframe_spacing_m > 0:
        t_scan = keyframe_times(t_scan, traj, p.keyframe_spacing_m, rng.spawn(1)[0])
    if scan_limit is not None:
        t_scan = t_scan[:int(scan_limit)]
    n_scans = len(t_scan)
    n_az = beams.n_azimuth
    t_col = np.arange(n_az) * (SCAN_PERIOD_S / n_az)
    ahead = np.zeros((n_scans, 2))  # vehicles ahead in the ego lane, bumper gap of the nearest (m)
    for i, t0 in enumerate(t_scan):
        poses = traj.sample(t0 + t_col) if motion_distortion else np.repeat(traj.sample(np.array([t0])), n_az, 0)
        boxes, refl = traffic.boxes_at(float(t0), poses[0, :2])
        lead_boxes, lead_refl, gaps = lead.vehicles_at(float(t0))
        ahead[i] = len(gaps), gaps[0] if len(gaps) else np.nan
        dyn_tris = box_triangles(np.concatenate([boxes, lead_boxes]))
        dynamic = Scene(TriangleSoup(dyn_tris.astype(np.float32), np.full(len(dyn_tris), VEHICLE, np.uint8),
                                     np.repeat(np.concatenate([refl, lead_refl]), 12).astype(np.float32)))
        pts = simulate_scan(beams, poses, static, dynamic, marks, albedo, calib, rng_sensor, effects, rng_effects)
        writers.write_pcd(scan_dir / f"{i:06d}.pcd", pts)
        if progress and (i % 10 == 9 or i == n_scans - 1):
            progress(i + 1, n_scans)
    gps_scan = spec.gps_t0_s + t_scan
    writers.write_csv(truth_dir / f"drive_{spec.index}_vehicles_ahead.csv", ["scan_id", "vehicles_ahead", "gap_m"],
                      [np.arange(n_scans), ahead[:, 0], ahead[:, 1]], ["%d", "%d", "%.2f"])
    writers.write_csv(scan_dir / "stamps.csv", ["scan_id", "gps_week", "gps_seconds"],
                      [np.arange(n_scans), np.full(n_scans, p.gps_week), gps_scan], ["%d", "%d", "%.6f"])

    truth = traj.sample(t_scan)
    T = np.tile(np.eye(4), (n_scans, 1, 1))
    T[:, :3, :3] = rotations_enu_vehicle(truth[:, 2], truth[:, 3], truth[:, 4])
    T[:, :2, 3] = truth[:, :2]
    # TUM time = the drive's time base as ingested: GPS seconds since the GPS epoch (week * 604800 + seconds).
    # The frame (ENU about the simulator's origin) is stated in a header line and a sidecar JSON.
    tum = truth_dir / f"drive_{spec.index}_poses_tum.txt"
    write_tum(tum, p.gps_week * 604800.0 + gps_scan, T, header=frame_header(origin))
    write_sidecar(tum, origin, time="GPS seconds since the GPS epoch (week * 604800 + seconds of week)",
                  body="vehicle: x forward, y left, z up; origin on the ground under the lidar")

    stats = _write_gnss(spec, p, traj, buildings, origin, drive_dir, truth_dir, rng_gnss)
    if not p.gnss:
        (drive_dir / "gnss_inspva.csv").unlink()  # simulated all the same: the other drives' errors stay as they were
    if p.prior != "none":
        write_prior(drive_dir / "prior.txt", p, p.gps_week * 604800.0 + gps_scan, T, rng.spawn(1)[0])
    wheel, gyro = simulate_odometry(traj.speed_mps, traj.yaw_rate_radps, 0.01, rng_odo)
    writers.write_csv(drive_dir / "wheel_gyro.csv", ["gps_week", "gps_seconds", "wheel_speed_mps", "yaw_rate_radps"],
                      [np.full(len(traj.t_s), p.gps_week), spec.gps_t0_s + traj.t_s, wheel, gyro],
                      ["%d", "%.3f", "%.3f", "%.6f"])
    start = None if p.gnss else start_pose(p, T[0], origin, rng.spawn(1)[0])
    return DriveResult(n_scans, stats, lidar_positions_en(truth, beams.T_vehicle_lidar), poly,
                       round(float((ahead[:, 0] > 0).mean()), 4), start)


def keyframe_times(t_scan: np.ndarray, traj, spacing_m: float, rng: np.random.Generator) -> np.ndarray:
    """The sweep start times kept as keyframes: each the first sweep 0.5-1.5 x ``spacing_m`` of travel (uniform)
    after the previous keyframe, the first sweep first (a keyframe dataset: irregular spacing, metres apart)."""
    travelled = np.concatenate([[0.0], np.cumsum(np.diff(traj.t_s) * traj.speed_mps[1:])])
    d = np.interp(t_scan, traj.t_s, travelled)
    keep, k = [0], 0
    while True:
        nxt = np.searchsorted(d, d[k] + spacing_m * rng.uniform(0.5, 1.5))
        if nxt >= len(d):
            return t_scan[keep]
        keep.append(int(nxt))
        k = int(nxt)


def gauss_markov(t_s: np.ndarray, sigma: float, tau_s: float, dims: int, rng: np.random.Generator) -> np.ndarray:
    """(len(t_s), dims) first-order Gauss-Markov errors of stationary std ``sigma`` at irregular times."""
    out = np.zeros((len(t_s), dims))
    out[0] = rng.normal(0, sigma, dims)
    for k in range(1, len(t_s)):
        a = np.exp(-(t_s[k] - t_s[k - 1]) / tau_s)
        out[k] = a * out[k - 1] + rng.normal(0, sigma * np.sqrt(1 - a * a), dims)
    return out


def write_prior(path: Path, p: Preset, stamps_s: np.ndarray, T_true: np.ndarray, rng: np.random.Generator) -> None:
    """A prior trajectory of the vehicle at the scans (TUM): the truth with slowly varying horizontal and heading
    errors (Gauss-Markov, ``prior_std_m`` / ``prior_std_deg``, ``prior_tau_s``). ``enu``: in ENU about the
    simulator's origin; ``local``: in the frame of the vehicle's first pose (a SLAM trajectory starting at the
    identity), its errors zero there."""
    from stages.common.geometry import write_tum

    e_en = gauss_markov(stamps_s, p.prior_std_m / np.sqrt(2), p.prior_tau_s, 2, rng)
    e_yaw = np.radians(gauss_markov(stamps_s, p.prior_std_deg, p.prior_tau_s, 1, rng)[:, 0])
    if p.prior_heading_walk_deg > 0:
        walk_en, walk_yaw = heading_walk(T_true[:, :2, 3], p.prior_heading_walk_deg, rng)
        e_en, e_yaw = e_en + walk_en, e_yaw + walk_yaw
    if p.prior == "local":
        e_en, e_yaw = e_en - e_en[0], e_yaw - e_yaw[0]
    T = T_true.copy()
    c, s = np.cos(e_yaw), np.sin(e_yaw)
    Rz = np.zeros((len(T), 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
    T[:, :3, :3] = Rz @ T_true[:, :3, :3]
    T[:, :2, 3] += e_en
    if p.prior == "local":
        T = np.linalg.inv(T_true[0]) @ T
    write_tum(path, stamps_s, T)


def heading_walk(positions_en: np.ndarray, deg_per_sqrt_km: float, rng: np.random.Generator
                 ) -> tuple[np.ndarray, np.ndarray]:
    """A drifting trajectory's errors ((N,2) east/north m, (N,) heading rad, zero at the first pose): its heading
    random-walks ``deg_per_sqrt_km`` per sqrt(km) of travel, and each step's displacement is turned by the heading
    error accumulated so far, so the position error is the heading error integrated along the path (a lidar
    odometry or SLAM without loop closures)."""
    step = np.diff(positions_en, axis=0)
    d_km = np.linalg.norm(step, axis=1) / 1000.0
    yaw = np.concatenate([[0.0], np.cumsum(rng.normal(0.0, 1.0, len(step)) * np.radians(deg_per_sqrt_km)
                                           * np.sqrt(d_km))])
    c, s = np.cos(yaw[:-1]), np.sin(yaw[:-1])
    turned = np.column_stack([c * step[:, 0] - s * step[:, 1], s * step[:, 0] + c * step[:, 1]])
    drifted = positions_en[0] + np.concatenate([np.zeros((1, 2)), np.cumsum(turned, axis=0)])
    return drifted - positions_en, yaw


def start_pose(p: Preset, T_first: np.ndarray, origin, rng: np.random.Generator) -> dict:
    """The drive file's ``start:`` of a drive without GNSS: the first scan's true heading and position with errors
    drawn at the stated stds (``start_heading_std_deg``, ``start_position_std_m``)."""
    from stages.common.geodesy import enu_to_geodetic

    yaw = np.arctan2(T_first[1, 0], T_first[0, 0]) + np.radians(rng.normal(0, p.start_heading_std_deg))
    en = T_first[:2, 3] + rng.normal(0, p.start_position_std_m, 2)
    lat, lon, h = enu_to_geodetic(np.array([[en[0], en[1], T_first[2, 3]]]), origin)[0]
    return {"heading_deg": round(float((90.0 - np.degrees(yaw)) % 360.0), 4),
            "heading_convention": "azimuth_cw_from_north", "std_heading_deg": p.start_heading_std_deg,
            "position": {"lat_deg": round(float(lat), 9), "lon_deg": round(float(lon), 9), "h_m": round(float(h), 3)},
            "std_m": max(p.start_position_std_m, 0.01)}


def lidar_positions_en(states: np.ndarray, T_vehicle_lidar: np.ndarray) -> np.ndarray:
    """(K, >=3) vehicle states (east, north, yaw, ...) -> (K, 2) the lidar's horizontal position: the vehicle's
    plus its horizontal lever arm turned by the yaw (roll and pitch left out: centimetres on the simulator's flat
    roads)."""
    lever = np.asarray(T_vehicle_lidar, float)[:2, 3]
    if not lever.any():
        return states[:, :2].copy()
    c, s = np.cos(states[:, 2]), np.sin(states[:, 2])
    return states[:, :2] + np.column_stack([c * lever[0] - s * lever[1], s * lever[0] + c * lever[1]])


def gnss_errors_for(traj, buildings: Scene, p: Preset, rng: np.random.Generator):
    """GNSS epochs (20 Hz, s from drive start), true states there, blocked-sky fraction and errors."""
    t = np.arange(0.0, float(traj.t_s[-1]), 1.0 / GNSS_RATE_HZ)
    state = traj.sample(t)
    t1 = np.arange(0.0, float(traj.t_s[-1]) + 1.0, 1.0)
    s1 = traj.sample(t1)
    canyon = np.interp(t, t1, sky_blocked_fraction(
        buildings, np.column_stack([s1[:, :2], np.full(len(t1), ANTENNA_HEIGHT_M)])))
    dist = np.interp(t, traj.t_s, np.cumsum(traj.speed_mps) * (traj.t_s[1] - traj.t_s[0]))
    err = simulate_gnss_errors(t, canyon, dist, p.gnss_target_rms_m, p.gnss_bias_open_m, p.gnss_bias_canyon_m,
                               p.multipath_per_km, p.outage_per_km, rng, bias_tau_s=p.gnss_bias_tau_s,
                               multipath_m=p.gnss_multipath_m, outage_s=p.gnss_outage_s, std_share=p.gnss_std_share)
    if not p.gnss_attitude:  # a receiver alone: the heading is the course over ground
        yaw_err, yaw_std = course_over_ground_errors(np.interp(t, traj.t_s, traj.speed_mps), rng)
        err = replace(err, err_yaw_rad=yaw_err, std_yaw_rad=yaw_std)
    return t, state, canyon, err


def _write_gnss(spec: DriveSpec, p: Preset, traj, buildings: Scene, origin, drive_dir: Path, truth_dir: Path,
                rng: np.random.Generator) -> dict:
    from stages.common.geodesy import enu_to_geodetic

    t, state, canyon, err = gnss_errors_for(traj, buildings, p, rng)
    enu = np.column_stack([state[:, :2], np.zeros(len(t))]) + err.err_enu_m
    v = err.valid
    llh = enu_to_geodetic(enu[v], origin)
    azimuth = (90.0 - np.degrees(state[:, 2] + err.err_yaw_rad)) % 360.0
    writers.write_gnss_csv(
        drive_dir / "gnss_inspva.csv",
        p.gps_week,
        spec.gps_t0_s + t[v],
        llh,
        np.degrees(state[v, 4] + err.err_roll_rad[v]) if p.gnss_attitude else None,
        np.degrees(state[v, 3] + err.err_pitch_rad[v]) if p.gnss_attitude else None,
        azimuth[v],
        err.std_enu_m[v],
        np.degrees(err.std_yaw_rad[v]),
        status="INS_SOLUTION_GOOD" if p.gnss_attitude else "SINGLE",
    )
    h = np.linalg.norm(err.err_enu_m[v, :2], axis=1)
    stats = {"rms_m": round(float(np.sqrt(np.mean(h ** 2))), 4), "max_m": round(float(h.max()), 4),
             "seconds_above_1m": round(float((h > 1.0).sum() / GNSS_RATE_HZ), 2),
             "heading_rms_deg": round(float(np.degrees(np.sqrt(np.mean(err.err_yaw_rad[v] ** 2)))), 4),
             "mean_reported_std_h_m": round(float(np.mean(np.hypot(err.std_enu_m[v, 0], err.std_enu_m[v, 1]))), 4),
             "outage_seconds": round(float((~v).sum() / GNSS_RATE_HZ), 2),
             "mean_sky_blocked": round(float(canyon.mean()), 4), "epochs": int(v.sum())}
    writers.write_json(truth_dir / f"drive_{spec.index}_gnss_stats.json", stats)
    return stats
