"""A synthetic street (ground, staggered facades, poles) raycast with an HDL-32E-like beam pattern."""
from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest


def build_street_scene(seed: int) -> o3d.t.geometry.RaycastingScene:
    rng = np.random.default_rng(seed)
    scene = o3d.t.geometry.RaycastingScene()

    def add_box(w, d, h, x, y, z, yaw=0.0):
        box = o3d.geometry.TriangleMesh.create_box(w, d, h)
        box.translate((-w / 2, -d / 2, 0))
        R = box.get_rotation_matrix_from_xyz((0, 0, yaw))
        box.rotate(R, center=(0, 0, 0))
        box.translate((x, y, z))
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(box))

    add_box(400, 400, 0.1, 0, 0, -0.1)  # ground
    for side in (-1, 1):  # facades with setbacks, every ~12 m
        x = -150.0
        while x < 150:
            w = rng.uniform(6, 18)
            setback = rng.uniform(0, 3)
            add_box(w, 6, rng.uniform(8, 25), x + w / 2, side * (10 + setback + 3), 0,
                    yaw=rng.uniform(-0.05, 0.05))
            x += w + rng.uniform(0.5, 4)
    for _ in range(60):  # poles and small boxes
        add_box(0.4, 0.4, rng.uniform(2, 6), rng.uniform(-150, 150), rng.choice([-1, 1]) * rng.uniform(6, 9), 0)
    return scene


def hdl32_rays(T_world_lidar: np.ndarray, azimuth_step_deg: float = 0.4) -> np.ndarray:
    elev = np.deg2rad(np.linspace(-30.67, 10.67, 32))
    az = np.deg2rad(np.arange(0, 360, azimuth_step_deg))
    A, E = np.meshgrid(az, elev, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1).reshape(-1, 3)
    d_world = d @ T_world_lidar[:3, :3].T
    o = np.broadcast_to(T_world_lidar[:3, 3], d_world.shape)
    return np.hstack([o, d_world]).astype(np.float32), d


def raycast_scan(scene, T_world_lidar: np.ndarray, rng: np.random.Generator, noise_m: float = 0.01,
                 max_range_m: float = 100.0) -> np.ndarray:
    """Points in the lidar frame (N,3) with range noise."""
    rays, d_lidar = hdl32_rays(T_world_lidar)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    ok = np.isfinite(t) & (t < max_range_m)
    r = t[ok] + rng.normal(0, noise_m, ok.sum())
    return d_lidar[ok] * r[:, None]


@pytest.fixture(scope="session")
def street_scene():
    return build_street_scene(seed=7)
