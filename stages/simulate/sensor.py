"""Spinning lidar models (Velodyne HDL-32E, the default, and HDL-64E): published elevation tables, firing order
and timing, ray casting against the city, range noise, dropouts, angular jitter / beam divergence / mixed pixels /
sector dropouts (``sensor_effects.py``), intensity from reflectance and incidence with per-laser (uncalibrated) gain
and offset, self-occlusion by the ego body, and motion distortion (each firing uses the pose at its own time).

The lidar sits at ``T_vehicle_lidar`` in the vehicle frame (x forward, y left, z up; origin on the ground at the
vehicle's reference point): a height, a horizontal lever arm and a mount yaw. Output points are in the
instantaneous lidar frame, as a driver writes them.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from stages.simulate.markings import REFLECTANCE, Raster
from stages.simulate.mesh import GROUND, Scene
from stages.simulate.sensor_effects import (
    SensorEffects,
    column_jitter_rotations,
    divergence_range_sigma_m,
    dropped_columns,
    mix_edge_ranges,
)

# Elevation of each ring (ring 0 = lowest beam), degrees, from the HDL-32E manual.
ELEVATION_DEG = np.array([-30.67, -29.33, -28.00, -26.67, -25.33, -24.00, -22.67, -21.33, -20.00, -18.67, -17.33,
                          -16.00, -14.67, -13.33, -12.00, -10.67, -9.33, -8.00, -6.67, -5.33, -4.00, -2.67, -1.33,
                          0.00, 1.33, 2.67, 4.00, 5.33, 6.67, 8.00, 9.33, 10.67])
# Firing order: laser id -> ring (the HDL-32E interleaves low and high beams).
LASER_TO_RING = np.array([0, 16, 1, 17, 2, 18, 3, 19, 4, 20, 5, 21, 6, 22, 7, 23,
                          8, 24, 9, 25, 10, 26, 11, 27, 12, 28, 13, 29, 14, 30, 15, 31])
N_AZIMUTH = 2250  # HDL-32E: 0.16 deg steps at 10 Hz
SCAN_PERIOD_S = 0.1
FIRING_DT_S = 1.152e-6
MAX_RANGE_M, MIN_RANGE_M = 100.0, 1.0
RANGE_SIGMA_M = 0.02
MOUNT_HEIGHT_M = 1.9  # the default lidar height above the road (presets' lidar_z_m)
# Ego body in the vehicle frame (origin on the ground at the vehicle's reference point): cabin and body boxes,
# x/y/z min-max.
EGO_BOXES_M = (np.array([[-1.7, 0.8], [-0.82, 0.82], [0.0, 1.50]]), np.array([[-2.7, 1.9], [-0.95, 0.95], [0.0, 1.0]]))


@dataclass(frozen=True)
class LidarModel:
    """A spinning lidar: beam elevations by ring (ring 0 = lowest), the ring of each laser in firing order,
    azimuth columns per revolution and the time between two firings of a column."""

    name: str
    elevation_deg: np.ndarray  # (R,) by ring, ascending
    laser_to_ring: np.ndarray  # (R,) firing order: laser id -> ring
    n_azimuth: int
    firing_dt_s: float

    @property
    def n_rings(self) -> int:
        return len(self.elevation_deg)


# HDL-64E elevations by ring (deg): the unit of the KITTI samples in ../shared/data (median over the 22 scans of
# ``stages.corners.layers.estimate_ring_elevation_deg``; spread 0.2 deg at most). Its upper lasers reach +2.84 deg,
# the nominal S2 table +2.0 (-24.33 .. +2.0): a unit's calibration moves the upper rings' facade band by 0.2 m at
# 15 m, which decides what the eight upper layers see (window and door tops at 2.1-2.4 m).
HDL64E_KITTI_ELEVATION_DEG = np.array([
    -23.66, -23.18, -22.66, -22.03, -21.58, -21.18, -20.68, -20.09, -19.58, -19.03, -18.57, -18.16, -17.65, -17.19,
    -16.61, -16.10, -15.48, -15.11, -14.62, -14.18, -13.59, -13.10, -12.54, -12.11, -11.66, -11.22, -10.72, -10.14,
    -9.65, -9.24, -8.77, -8.23, -7.58, -7.19, -6.98, -6.60, -6.21, -5.92, -5.64, -5.33, -4.93, -4.60, -4.30, -3.93,
    -3.66, -3.26, -2.98, -2.59, -2.29, -1.94, -1.62, -1.28, -0.90, -0.57, -0.29, 0.11, 0.44, 0.80, 1.08, 1.49, 1.76,
    2.21, 2.47, 2.84])


def _hdl64e_model() -> LidarModel:
    """Velodyne HDL-64E (S2) as in KITTI: 64 lasers at ``HDL64E_KITTI_ELEVATION_DEG``, an upper block (rings 32-63)
    and a lower block (rings 0-31) firing in pairs (upper k with lower k), 2000 columns per 0.1 s revolution
    (0.18 deg; the KITTI samples: 0.1797 deg, ~1980 returns per upper ring)."""
    lasers = np.empty(64, np.intp)
    lasers[0::2], lasers[1::2] = np.arange(32, 64), np.arange(32)  # pair k: upper k then lower k
    return LidarModel("hdl64e", HDL64E_KITTI_ELEVATION_DEG, lasers, 2000, SCAN_PERIOD_S / 2000 / 64)


def _os1_64_model() -> LidarModel:
    """Ouster OS1-64 (first generation): the 64 elevations of a real unit's metadata (``stages.common.beam_tables``
    ``OS1_64_GEN1``, 33.2 deg), every laser of a column firing at once (ring = laser, lowest first), 1024 columns per
    0.1 s revolution (the 1024x10 mode)."""
    from stages.common.beam_tables import OS1_64_GEN1

    return LidarModel("os1-64", np.asarray(OS1_64_GEN1[::-1], float), np.arange(64), 1024, 0.0)


LIDARS: dict[str, LidarModel] = {
    "hdl32e": LidarModel("hdl32e", ELEVATION_DEG, LASER_TO_RING, N_AZIMUTH, FIRING_DT_S),
    "hdl64e": _hdl64e_model(),
    "os1-64": _os1_64_model(),
}


def mount_matrix(x_m: float, y_m: float, z_m: float, yaw_deg: float) -> np.ndarray:
    """T_vehicle_lidar of a lidar at (x, y, z) in the vehicle frame turned by ``yaw_deg`` about z (counter-clockwise
    seen from above: the lidar's x axis points ``yaw_deg`` to the left of the vehicle's)."""
    T = np.eye(4)
    if yaw_deg:
        c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
        T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = (x_m, y_m, z_m)
    return T


@dataclass(frozen=True)
class LaserCalibration:
    gain: np.ndarray  # (R,) by ring
    offset: np.ndarray  # (R,) by ring

    @staticmethod
    def draw(rng: np.random.Generator, n_rings: int = 32) -> "LaserCalibration":
        return LaserCalibration(rng.uniform(0.55, 1.45, n_rings), rng.uniform(-6.0, 22.0, n_rings))


@dataclass(frozen=True)
class BeamTable:
    """All firings of one revolution, in firing order: azimuth column major, then laser id."""

    dirs_lidar: np.ndarray  # (n_azimuth * n_lasers, 3)
    ring: np.ndarray  # (N,) uint16
    time_s: np.ndarray  # (N,) seconds after the scan start
    column: np.ndarray  # (N,) azimuth column index
    ego_range_m: np.ndarray  # (N,) distance at which the beam enters the ego body (inf if never)
    n_azimuth: int = N_AZIMUTH
    n_lasers: int = 32
    T_vehicle_lidar: np.ndarray = field(default_factory=lambda: mount_matrix(0.0, 0.0, MOUNT_HEIGHT_M, 0.0))


def build_beam_table(model: LidarModel | None = None, T_vehicle_lidar: np.ndarray | None = None) -> BeamTable:
    """The firings of ``model`` (default HDL-32E) mounted at ``T_vehicle_lidar`` (default (0, 0, 1.9 m), no
    rotation); the ego body is cast from the mount."""
    m = LIDARS["hdl32e"] if model is None else model
    T = mount_matrix(0.0, 0.0, MOUNT_HEIGHT_M, 0.0) if T_vehicle_lidar is None else np.asarray(T_vehicle_lidar, float)
    n_az, n_l = m.n_azimuth, m.n_rings
    col = np.repeat(np.arange(n_az), n_l)
    laser = np.tile(np.arange(n_l), n_az)
    ring = m.laser_to_ring[laser]
    az = np.pi - 2 * np.pi * col / n_az  # starts facing backwards, spins clockwise seen from above
    el = np.radians(m.elevation_deg[ring])
    dirs = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    time_s = col * (SCAN_PERIOD_S / n_az) + laser * m.firing_dt_s
    dirs_vehicle = dirs @ T[:3, :3].T
    ego = np.min([_ray_box_entry(T[:3, 3], dirs_vehicle, box) for box in EGO_BOXES_M], axis=0)
    return BeamTable(dirs, ring.astype(np.uint16), time_s, col, ego, n_az, n_l, T)


def _ray_box_entry(origin: np.ndarray, dirs: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Slab test: distance at which each ray enters an axis-aligned box (inf if it misses)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (box[:, 0] - origin) / dirs
        t2 = (box[:, 1] - origin) / dirs
    t_near = np.nanmax(np.minimum(t1, t2), axis=1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=1)
    return np.where((t_far >= t_near) & (t_far > 0), np.maximum(t_near, 0), np.inf)


def rotations_enu_vehicle(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """(K,) angles -> (K, 3, 3) R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    return np.stack([np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
                     np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
                     np.stack([-sp, cp * sr, cp * cr], -1)], -2)


def simulate_scan(beams: BeamTable, poses_col: np.ndarray, static: Scene, dynamic: Scene, markings: Raster,
                  albedo: Raster, calib: LaserCalibration, rng: np.random.Generator,
                  effects: SensorEffects | None = None, rng_effects: np.random.Generator | None = None
                  ) -> dict[str, np.ndarray]:
    """One revolution. ``poses_col``: (n_azimuth, 5) east, north, yaw, pitch, roll of the vehicle at each
    azimuth column's time (all rows equal = no motion distortion); the lidar sits at ``beams.T_vehicle_lidar``.
    ``effects`` (with their own generator ``rng_effects``): None = range noise only. Returns PCD-ready arrays."""
    fx = effects if effects is not None and effects.active else None
    n_az, n_l, T_vl = beams.n_azimuth, beams.n_lasers, beams.T_vehicle_lidar
    R = rotations_enu_vehicle(poses_col[:, 2], poses_col[:, 3], poses_col[:, 4])  # (C, 3, 3) R_enu_vehicle
    lever = np.einsum("cij,j->ci", R, T_vl[:3, 3])
    lidar_origin = np.column_stack([poses_col[:, :2], np.zeros(len(poses_col))]) + lever
    R_lidar = R if np.array_equal(T_vl[:3, :3], np.eye(3)) else np.matmul(R, T_vl[:3, :3])  # R_enu_lidar
    d_lidar = beams.dirs_lidar.reshape(n_az, n_l, 3)
    R_cast = R_lidar
    if fx is not None and fx.angular_jitter_deg > 0:  # cast along the jittered direction, report the nominal one
        az = np.pi - 2 * np.pi * np.arange(n_az) / n_az
        R_cast = np.matmul(R_lidar, column_jitter_rotations(az, fx.angular_jitter_deg, rng_effects))
    dirs_w = np.matmul(d_lidar, R_cast.transpose(0, 2, 1)).reshape(-1, 3)
    origins_w = np.repeat(lidar_origin, n_l, axis=0)
    t_s, prim_s = static.cast(origins_w, dirs_w)
    t_d, prim_d = dynamic.cast(origins_w, dirs_w)
    use_dyn = t_d < t_s
    r_true = np.where(use_dyn, t_d, t_s).astype(np.float64)
    hit = np.isfinite(r_true) & (r_true < MAX_RANGE_M) & (r_true > MIN_RANGE_M) & (r_true < beams.ego_range_m)
    if fx is not None:
        if fx.mixed_pixel_share > 0:
            grid = np.where(hit, r_true, np.inf).reshape(n_az, n_l)
            r_true = mix_edge_ranges(grid, fx.mixed_pixel_share, fx.mixed_min_jump_m, rng_effects)[0].reshape(-1)
        if fx.sector_dropout_scan_share > 0:
            hit &= ~dropped_columns(n_az, fx.sector_dropout_scan_share, fx.sector_dropout_deg,
                                    rng_effects)[beams.column]
    idx = np.flatnonzero(hit)
    dyn = use_dyn[idx]
    prim = np.where(dyn, prim_d[idx], prim_s[idx])
    refl = np.empty(len(idx), np.float64)
    normal = np.empty((len(idx), 3), np.float32)
    cls = np.empty(len(idx), np.uint8)
    for mask, scene in ((dyn, dynamic), (~dyn, static)):
        refl[mask] = scene.soup.refl[prim[mask]]
        normal[mask] = scene.normals[prim[mask]]
        cls[mask] = scene.soup.cls[prim[mask]]
    r = r_true[idx]
    d = dirs_w[idx]
    cos_inc = np.clip(np.abs(np.sum(normal * d, axis=1)), 0.02, 1.0)
    ground = ~dyn & (cls == GROUND)
    if ground.any():
        p = origins_w[idx[ground]] + d[ground] * r[ground, None]
        paint = markings.lookup(p[:, 0], p[:, 1])
        g_refl = albedo.lookup(p[:, 0], p[:, 1]).astype(np.float64)
        for cls, value in REFLECTANCE.items():
            g_refl = np.where(paint == cls, value, g_refl)
        refl[ground] = g_refl
    refl = refl * rng.lognormal(0.0, 0.12, len(idx))
    # detection: returned power ~ reflectance * cos / r^2 against a noisy threshold, plus random dropouts
    power = refl * cos_inc * (20.0 / r) ** 2
    keep = (power > 1.2e-3 * rng.lognormal(0.0, 0.5, len(idx))) & (rng.random(len(idx)) > 0.01)
    idx, r, refl, cos_inc = idx[keep], r[keep], refl[keep], cos_inc[keep]
    ring = beams.ring[idx]
    raw = 200.0 * refl * (0.35 + 0.65 * cos_inc) * (10.0 / np.maximum(r, 3.0)) ** 0.25
    intensity = np.clip(np.round(calib.gain[ring] * raw + calib.offset[ring] + rng.normal(0, 1.5, len(idx))), 0, 255)
    sigma = RANGE_SIGMA_M
    if fx is not None and fx.divergence_mrad > 0:  # range noise and the footprint's spread, independent
        sigma = np.sqrt(RANGE_SIGMA_M ** 2 + divergence_range_sigma_m(r, cos_inc, fx.divergence_mrad) ** 2)
    r_meas = r + rng.normal(0.0, sigma, len(idx))
    xyz = beams.dirs_lidar[idx] * r_meas[:, None]
    return {"x": xyz[:, 0].astype(np.float32), "y": xyz[:, 1].astype(np.float32), "z": xyz[:, 2].astype(np.float32),
            "intensity": intensity.astype(np.float32), "ring": ring, "time": beams.time_s[idx].astype(np.float32)}
