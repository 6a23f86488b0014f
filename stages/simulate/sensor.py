"""Velodyne HDL-32E model: published elevation table, firing order and timing, ray casting against the city,
range noise, dropouts, angular jitter / beam divergence / mixed pixels / sector dropouts
(``sensor_effects.py``), intensity from reflectance and incidence with per-laser (uncalibrated) gain and
offset, self-occlusion by the ego roof, and motion distortion (each firing uses the pose at its own time).

Output points are in the instantaneous lidar frame (x forward, y left, z up), as a driver writes them.
"""
from __future__ import annotations

from dataclasses import dataclass

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
N_AZIMUTH = 2250  # 0.16 deg steps at 10 Hz
SCAN_PERIOD_S = 0.1
FIRING_DT_S = 1.152e-6
MAX_RANGE_M, MIN_RANGE_M = 100.0, 1.0
RANGE_SIGMA_M = 0.02
MOUNT_HEIGHT_M = 1.9
# Ego body in the vehicle frame (origin on the ground under the lidar): cabin and body boxes, x/y/z min-max.
EGO_BOXES_M = (np.array([[-1.7, 0.8], [-0.82, 0.82], [0.0, 1.50]]), np.array([[-2.7, 1.9], [-0.95, 0.95], [0.0, 1.0]]))


@dataclass(frozen=True)
class LaserCalibration:
    gain: np.ndarray  # (32,) by ring
    offset: np.ndarray  # (32,) by ring

    @staticmethod
    def draw(rng: np.random.Generator) -> "LaserCalibration":
        return LaserCalibration(rng.uniform(0.55, 1.45, 32), rng.uniform(-6.0, 22.0, 32))


@dataclass(frozen=True)
class BeamTable:
    """All firings of one revolution, in firing order: azimuth column major, then laser id."""

    dirs_lidar: np.ndarray  # (N_AZIMUTH*32, 3)
    ring: np.ndarray  # (N,) uint16
    time_s: np.ndarray  # (N,) seconds after the scan start
    column: np.ndarray  # (N,) azimuth column index
    ego_range_m: np.ndarray  # (N,) distance at which the beam enters the ego body (inf if never)


def build_beam_table() -> BeamTable:
    col = np.repeat(np.arange(N_AZIMUTH), 32)
    laser = np.tile(np.arange(32), N_AZIMUTH)
    ring = LASER_TO_RING[laser]
    az = np.pi - 2 * np.pi * col / N_AZIMUTH  # starts facing backwards, spins clockwise seen from above
    el = np.radians(ELEVATION_DEG[ring])
    dirs = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    time_s = col * (SCAN_PERIOD_S / N_AZIMUTH) + laser * FIRING_DT_S
    ego = np.min([_ray_box_entry(np.array([0.0, 0.0, MOUNT_HEIGHT_M]), dirs, box) for box in EGO_BOXES_M], axis=0)
    return BeamTable(dirs, ring.astype(np.uint16), time_s, col, ego)


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
    """One revolution. ``poses_col``: (N_AZIMUTH, 5) east, north, yaw, pitch, roll of the vehicle at each
    azimuth column's time (all rows equal = no motion distortion). ``effects`` (with their own generator
    ``rng_effects``): None = range noise only. Returns PCD-ready arrays."""
    fx = effects if effects is not None and effects.active else None
    R = rotations_enu_vehicle(poses_col[:, 2], poses_col[:, 3], poses_col[:, 4])  # (C, 3, 3)
    lidar_origin = np.column_stack([poses_col[:, :2], np.zeros(len(poses_col))]) + R[:, :, 2] * MOUNT_HEIGHT_M
    d_lidar = beams.dirs_lidar.reshape(N_AZIMUTH, 32, 3)
    R_cast = R
    if fx is not None and fx.angular_jitter_deg > 0:  # cast along the jittered direction, report the nominal one
        az = np.pi - 2 * np.pi * np.arange(N_AZIMUTH) / N_AZIMUTH
        R_cast = np.matmul(R, column_jitter_rotations(az, fx.angular_jitter_deg, rng_effects))
    dirs_w = np.matmul(d_lidar, R_cast.transpose(0, 2, 1)).reshape(-1, 3)
    origins_w = np.repeat(lidar_origin, 32, axis=0)
    t_s, prim_s = static.cast(origins_w, dirs_w)
    t_d, prim_d = dynamic.cast(origins_w, dirs_w)
    use_dyn = t_d < t_s
    r_true = np.where(use_dyn, t_d, t_s).astype(np.float64)
    hit = np.isfinite(r_true) & (r_true < MAX_RANGE_M) & (r_true > MIN_RANGE_M) & (r_true < beams.ego_range_m)
    if fx is not None:
        if fx.mixed_pixel_share > 0:
            grid = np.where(hit, r_true, np.inf).reshape(N_AZIMUTH, 32)
            r_true = mix_edge_ranges(grid, fx.mixed_pixel_share, fx.mixed_min_jump_m, rng_effects)[0].reshape(-1)
        if fx.sector_dropout_scan_share > 0:
            hit &= ~dropped_columns(N_AZIMUTH, fx.sector_dropout_scan_share, fx.sector_dropout_deg,
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
