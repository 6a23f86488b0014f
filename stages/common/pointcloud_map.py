"""Point-cloud map building blocks (pure, arrays in / arrays out): scans to the map frame, a free-space test
that drops what moved, voxel downsampling and a grid split.

Free-space test (``free_space_keep``): points are grouped in voxels (``voxel_m``) and in passes (any id: a
drive, or a time window of one). Each ray (sensor origin -> point; every ``ray_stride``-th point) marks the voxels
it crosses as free up to ``stop_m`` before its end. A voxel is *dynamic* when at least ``min_free`` rays of
passes that never hit it crossed it: one pass saw it occupied, another saw through it. Its points are dropped.
Points less than ``ground_clear_m`` above the road (``ground_z``, the vehicle's height nearby) are never dropped
and never marked free: rays graze the road at long range and would otherwise erase it. Limits: a voxel seen
occupied by every pass is kept (a car parked during the whole survey stays); thin structures hit at grazing
angles by one pass and crossed by another can be thinned.
"""
from __future__ import annotations

import numpy as np

_BITS = 21
_OFF = 1 << (_BITS - 1)
_RAY_CHUNK = 100_000


def voxel_keys(xyz_m: np.ndarray, voxel_m: float) -> np.ndarray:
    """int64 key of the voxel of each point (21 bits per axis: +-1048576 voxels)."""
    v = np.floor(np.asarray(xyz_m, float) / voxel_m).astype(np.int64) + _OFF
    return (v[:, 0] << (2 * _BITS)) | (v[:, 1] << _BITS) | v[:, 2]


def interpolate_poses(stamps_ns: np.ndarray, xyz_m: np.ndarray, quat_xyzw: np.ndarray,
                      query_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Poses at ``query_ns`` (linear position, slerp rotation; clamped at the ends): (R (M,3,3), t (M,3))."""
    from scipy.spatial.transform import Rotation, Slerp

    t0 = stamps_ns[0]
    ts = (stamps_ns - t0).astype(np.float64) * 1e-9
    q = np.clip((np.asarray(query_ns) - t0).astype(np.float64) * 1e-9, ts[0], ts[-1])
    trans = np.column_stack([np.interp(q, ts, xyz_m[:, k]) for k in range(3)])
    if len(ts) == 1:
        return np.repeat(Rotation.from_quat(quat_xyzw).as_matrix(), len(q), axis=0), trans
    return Slerp(ts, Rotation.from_quat(quat_xyzw))(q).as_matrix(), trans


def scan_to_map(points_lidar: np.ndarray, point_time_ns: np.ndarray, T_vehicle_lidar: np.ndarray,
                stamps_ns: np.ndarray, pose_xyz: np.ndarray, pose_qxyzw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lidar points -> map frame with the vehicle pose at each point's time (deskewed): (points (N,3), sensor
    origins (N,3)). ``T_map_lidar(t) = T_map_vehicle(t) T_vehicle_lidar``."""
    R, t = interpolate_poses(stamps_ns, pose_xyz, pose_qxyzw, point_time_ns)
    p_vehicle = np.asarray(points_lidar, float) @ T_vehicle_lidar[:3, :3].T + T_vehicle_lidar[:3, 3]
    pts = np.einsum("nij,nj->ni", R, p_vehicle) + t
    origins = np.einsum("nij,j->ni", R, T_vehicle_lidar[:3, 3]) + t
    return pts, origins


def free_space_keep(points_m: np.ndarray, origins_m: np.ndarray, pass_id: np.ndarray, ground_z_m: np.ndarray,
                    voxel_m: float = 0.5, ray_stride: int = 8, stop_m: float = 1.0, min_free: int = 2,
                    ground_clear_m: float = 0.3, max_range_m: float = 40.0) -> np.ndarray:
    """Mask of the points to keep (see the module docstring)."""
    pts = np.asarray(points_m, float)
    pass_id = np.asarray(pass_id, np.int64)
    above = pts[:, 2] > np.asarray(ground_z_m, float) + ground_clear_m
    hit_keys = voxel_keys(pts, voxel_m)
    hits = np.unique(np.column_stack([hit_keys[above], pass_id[above]]), axis=0)  # (voxel, pass) hit pairs
    # free samples along a subset of rays, in chunks of rays (memory), reduced to unique (voxel, pass) counts
    sel = np.arange(0, len(pts), max(1, ray_stride))
    origins_m = np.asarray(origins_m)
    ground_z_m = np.asarray(ground_z_m, float)
    parts = []
    for c0 in range(0, len(sel), _RAY_CHUNK):
        idx = sel[c0:c0 + _RAY_CHUNK]
        o, p = origins_m[idx].astype(float), pts[idx]
        d = p - o
        rng = np.linalg.norm(d, axis=1)
        ok = (rng > stop_m + voxel_m) & (rng < max_range_m)
        o, d, rng, pid, gz = o[ok], d[ok], rng[ok], pass_id[idx][ok], ground_z_m[idx][ok]
        n_steps = np.floor((rng - stop_m) / (voxel_m / 2)).astype(np.int64)
        ray = np.repeat(np.arange(len(rng)), n_steps)
        k = np.arange(n_steps.sum()) - np.repeat(np.cumsum(n_steps) - n_steps, n_steps)
        samples = o[ray] + d[ray] * ((k + 0.5) * (voxel_m / 2) / rng[ray])[:, None]
        keep_sample = samples[:, 2] > gz[ray] + ground_clear_m
        pairs = np.column_stack([voxel_keys(samples[keep_sample], voxel_m), pid[ray][keep_sample]])
        u, n = np.unique(pairs, axis=0, return_counts=True)
        parts.append((u, n))
    free = np.vstack([u for u, _ in parts]) if parts else np.zeros((0, 2), np.int64)
    counts = np.concatenate([n for _, n in parts]) if parts else np.zeros(0, np.int64)
    if not len(free) or not len(hits):
        return np.ones(len(pts), bool)
    # free crossings of passes that never hit the voxel: (voxel, pass) pairs as dense scalar codes
    free_u, inv = np.unique(free, axis=0, return_inverse=True)
    free_n = np.bincount(inv.ravel(), weights=counts, minlength=len(free_u))
    vox_all, vox_idx = np.unique(np.r_[free_u[:, 0], hits[:, 0]], return_inverse=True)
    pas_all, pas_idx = np.unique(np.r_[free_u[:, 1], hits[:, 1]], return_inverse=True)
    code = vox_idx.astype(np.int64) * len(pas_all) + pas_idx
    free_code, hit_code = code[:len(free_u)], code[len(free_u):]
    foreign = ~np.isin(free_code, hit_code)
    n_free = np.bincount(vox_idx[:len(free_u)][foreign], weights=free_n[foreign], minlength=len(vox_all))
    dyn_vox = vox_all[n_free >= min_free]
    return ~(above & np.isin(hit_keys, dyn_vox))


def voxel_downsample(xyz_m: np.ndarray, intensity: np.ndarray, voxel_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Centroid (and mean intensity) of the points in each voxel, via open3d."""
    import open3d as o3d

    if not len(xyz_m):
        return np.zeros((0, 3)), np.zeros(0)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(xyz_m, float)))
    inten = np.asarray(intensity, float)
    pc.colors = o3d.utility.Vector3dVector(np.column_stack([inten, inten, inten]))  # averaged like positions
    down = pc.voxel_down_sample(voxel_m)
    return np.asarray(down.points), np.asarray(down.colors)[:, 0]


def grid_split(xy_m: np.ndarray, cell_m: float) -> dict[tuple[int, int], np.ndarray]:
    """(ix, iy) -> indices of the points in the grid cell [ix c, (ix+1) c) x [iy c, (iy+1) c)."""
    if not len(xy_m):
        return {}
    ij = np.floor(np.asarray(xy_m, float)[:, :2] / cell_m).astype(np.int64)
    keys, inverse = np.unique(ij, axis=0, return_inverse=True)
    order = np.argsort(inverse.ravel(), kind="stable")
    bounds = np.r_[0, np.cumsum(np.bincount(inverse.ravel(), minlength=len(keys)))]
    return {(int(keys[k, 0]), int(keys[k, 1])): order[bounds[k]:bounds[k + 1]] for k in range(len(keys))}
