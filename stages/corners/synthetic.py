"""A tiny numpy ray caster for corner-extraction oracles and benchmarks (not the drive simulator).

World: ground z = 0, prismatic buildings (footprint polygon + height), tree crowns (spheres of leaves: a ray that
enters a crown stops at an exponentially distributed depth with a given probability). A multi-beam lidar at
(x, y, yaw) and height h fires ``n_azimuth`` rays per ring. Points come back in the lidar frame (x forward,
y left, z up) with Gaussian range noise, and ring 0 = the lowest beam.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

HDL32E_ELEVATION_DEG = np.linspace(-30.67, 10.67, 32)


@dataclass(frozen=True)
class Building:
    footprint_xy_m: np.ndarray  # (V, 2) polygon in the world frame, either orientation
    height_m: float


@dataclass(frozen=True)
class TreeCrown:
    center_xyz_m: tuple[float, float, float]
    radius_m: float
    hit_probability: float = 0.9
    mean_depth_m: float = 0.6


@dataclass(frozen=True)
class Scene:
    buildings: list[Building]
    trees: list[TreeCrown] = field(default_factory=list)

    def walls(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Wall segments (start (W,2), end (W,2), height (W,))."""
        a, b, h = [], [], []
        for bld in self.buildings:
            v = np.asarray(bld.footprint_xy_m, float)
            a.append(v)
            b.append(np.roll(v, -1, axis=0))
            h.append(np.full(len(v), bld.height_m))
        if not a:
            return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0)
        return np.concatenate(a), np.concatenate(b), np.concatenate(h)


def polygon_interior_angles_rad(footprint_xy_m: np.ndarray) -> np.ndarray:
    """Interior angle of the building (material side) at each vertex of a simple polygon, in (0, 2 pi)."""
    v = np.asarray(footprint_xy_m, float)
    area2 = np.sum(v[:, 0] * np.roll(v[:, 1], -1) - np.roll(v[:, 0], -1) * v[:, 1])
    if area2 < 0:
        v = v[::-1]
    e_in = v - np.roll(v, 1, axis=0)
    e_out = np.roll(v, -1, axis=0) - v
    turn = np.arctan2(e_in[:, 0] * e_out[:, 1] - e_in[:, 1] * e_out[:, 0], np.einsum("ij,ij->i", e_in, e_out))
    angles = np.pi - turn
    return angles if area2 >= 0 else angles[::-1]


def cast_scan(scene: Scene, pose_xy_yaw: tuple[float, float, float], *, sensor_height_m: float = 1.8,
              elevation_deg: np.ndarray = HDL32E_ELEVATION_DEG, n_azimuth: int = 2250, range_sigma_m: float = 0.02,
              max_range_m: float = 100.0, seed: int = 0, speed_mps: float = 0.0, yaw_rate_radps: float = 0.0,
              scan_period_s: float = 0.1, return_time: bool = False):
    """Ray-cast one scan. Returns points (N, 3) float32 in the lidar frame and ring (N,) int16, in firing order
    (and, with ``return_time``, each point's time after the scan start [s]).

    With ``speed_mps`` / ``yaw_rate_radps`` the sensor moves during the revolution (forward along its x axis,
    constant twist from ``pose_xy_yaw`` at time 0); each point is in the lidar frame at its own firing time.
    """
    from stages.common.wheel_deskew import vehicle_motion_xy_yaw

    rng = np.random.default_rng(seed)
    elev = np.radians(np.asarray(elevation_deg, float))
    order = np.argsort(elev)
    elev = elev[order]
    az = np.arange(n_azimuth) * (2.0 * np.pi / n_azimuth) - np.pi
    az_s, el = np.meshgrid(az, elev, indexing="xy")  # (rings, n_azimuth)
    ring = np.broadcast_to(np.arange(elev.size)[:, None], az_s.shape)
    az_s, el, ring = az_s.T.ravel(), el.T.ravel(), ring.T.ravel()  # firing order: azimuth-major
    t_ray = np.repeat(np.arange(n_azimuth) * (scan_period_s / n_azimuth), elev.size)
    mx, my, myaw = vehicle_motion_xy_yaw(t_ray, speed_mps, yaw_rate_radps)
    c0, s0 = np.cos(pose_xy_yaw[2]), np.sin(pose_xy_yaw[2])
    x0 = pose_xy_yaw[0] + c0 * mx - s0 * my  # (R,) sensor position per ray
    y0 = pose_xy_yaw[1] + s0 * mx + c0 * my
    yaw = pose_xy_yaw[2] + myaw
    d_xy = np.column_stack([np.cos(az_s + yaw), np.sin(az_s + yaw)])
    tan_el = np.tan(el)
    s_best = np.full(az_s.size, np.inf)  # 3D range along the ray
    wa, wb, wh = scene.walls()
    if wa.size:
        e = wb - wa
        rel_x = wa[None, :, 0] - x0[:, None]  # (R, W)
        rel_y = wa[None, :, 1] - y0[:, None]
        denom = d_xy[:, 0:1] * e[None, :, 1] - d_xy[:, 1:2] * e[None, :, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (rel_x * e[None, :, 1] - rel_y * e[None, :, 0]) / denom
            u = (rel_x * d_xy[:, 1:2] - rel_y * d_xy[:, 0:1]) / denom
        z = sensor_height_m + t * tan_el[:, None]
        hit = (t > 0) & (u >= 0) & (u <= 1) & (z >= 0) & (z <= wh[None, :])
        t_hit = np.where(hit, t, np.inf).min(axis=1)
        s_best = np.minimum(s_best, t_hit / np.cos(el))
    ground = el < 0
    s_best[ground] = np.minimum(s_best[ground], sensor_height_m / np.sin(-el[ground]))
    d3 = np.column_stack([d_xy * np.cos(el)[:, None], np.sin(el)])
    origin = np.column_stack([x0, y0, np.full(x0.size, sensor_height_m)])
    for tree in scene.trees:
        oc = origin - np.asarray(tree.center_xyz_m, float)
        bq = np.einsum("ij,ij->i", d3, oc)
        disc = bq * bq - (np.einsum("ij,ij->i", oc, oc) - tree.radius_m ** 2)
        inside = disc > 0
        s0 = -bq - np.sqrt(np.where(inside, disc, 0.0))
        s1 = -bq + np.sqrt(np.where(inside, disc, 0.0))
        depth = rng.exponential(tree.mean_depth_m, az_s.size)
        leaf = inside & (s1 > 0) & (rng.random(az_s.size) < tree.hit_probability) & (np.maximum(s0, 0) + depth < s1)
        s_best = np.where(leaf, np.minimum(s_best, np.maximum(s0, 0.0) + depth), s_best)
    valid = np.isfinite(s_best) & (s_best * np.cos(el) <= max_range_m)
    s = s_best[valid] + rng.normal(0.0, range_sigma_m, valid.sum())
    ce = np.cos(el[valid])
    pts = np.column_stack([s * ce * np.cos(az_s[valid]), s * ce * np.sin(az_s[valid]), s * np.sin(el[valid])])
    if return_time:
        return pts.astype(np.float32), ring[valid].astype(np.int16), t_ray[valid].astype(np.float32)
    return pts.astype(np.float32), ring[valid].astype(np.int16)


def box_building(center_xy_m: tuple[float, float], size_xy_m: tuple[float, float], yaw_rad: float = 0.0,
                 height_m: float = 15.0) -> Building:
    cx, cy = center_xy_m
    hx, hy = 0.5 * size_xy_m[0], 0.5 * size_xy_m[1]
    local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return Building(local @ np.array([[c, s], [-s, c]]) + [cx, cy], height_m)


def city_block_scene(seed: int = 0, n_buildings: int = 14, n_trees: int = 10, half_width_m: float = 45.0) -> Scene:
    """Buildings (boxes and L shapes, random yaw) on both sides of a 20 m street along x, with street trees."""
    rng = np.random.default_rng(seed)
    buildings = []
    for k in range(n_buildings):
        side = 1 if k % 2 == 0 else -1
        cx = -half_width_m + (k // 2 + 0.5) * (2 * half_width_m / max(n_buildings // 2, 1))
        w, d = rng.uniform(8, 14), rng.uniform(8, 16)
        cy = side * (10.0 + 0.5 * d + rng.uniform(0, 4))
        buildings.append(box_building((cx, cy), (w, d), rng.uniform(-0.3, 0.3), rng.uniform(6, 25)))
    trees = [TreeCrown((rng.uniform(-half_width_m, half_width_m), rng.choice([-1, 1]) * rng.uniform(7.5, 9.0),
                        rng.uniform(3.5, 6.0)), rng.uniform(1.5, 3.0)) for _ in range(n_trees)]
    return Scene(buildings, trees)


def rounded_box_building(size_xy_m: tuple[float, float], radius_m: float, height_m: float = 14.0,
                         step_deg: float = 3.0) -> Building:
    """Box [0, W] x [0, H] whose corner at (W, H) is rounded by a quarter arc of ``radius_m`` (polygon vertices
    every ``step_deg``); radius 0 gives the sharp box. The walls' intersection stays at (W, H)."""
    w, h = size_xy_m
    if radius_m <= 0:
        return Building(np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]]), height_m)
    a = np.radians(np.arange(0.0, 90.0 + 1e-9, step_deg))
    arc = np.array([w - radius_m, h - radius_m]) + radius_m * np.column_stack([np.cos(a), np.sin(a)])
    return Building(np.vstack([[0.0, 0.0], [w, 0.0], arc, [0.0, h]]), height_m)
