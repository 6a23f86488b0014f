"""Point-cloud map building blocks (pure, arrays in / arrays out): scans to the map frame, a free-space test
that drops what moved, streaming voxel downsampling and a grid split. Every step works on batches of points
whose results merge (unique keys with summed counts), so a map of any drive length is built in bounded memory.

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


def _ray_samples(o: np.ndarray, p: np.ndarray, step_m: float, stop_m: float, max_range_m: float,
                 budget: int):
    """Sample points every ``step_m`` along each ray o -> p, up to ``stop_m`` before p, in batches of rays whose
    samples stay under ``budget``: yields (ray index (M,), samples (M,3))."""
    d = p - o
    rng = np.linalg.norm(d, axis=1)
    n_steps = np.where((rng > stop_m + 2 * step_m) & (rng < max_range_m),
                       np.floor((rng - stop_m) / step_m), 0).astype(np.int64)
    ends = np.cumsum(n_steps)
    r0 = 0
    while r0 < len(rng):
        r1 = max(r0 + 1, int(np.searchsorted(ends, (ends[r0 - 1] if r0 else 0) + budget, side="right")))
        ns = n_steps[r0:r1]
        ray = np.repeat(np.arange(r0, r1), ns)
        k = np.arange(ns.sum()) - np.repeat(np.cumsum(ns) - ns, ns)
        yield ray, o[ray] + d[ray] * ((k + 0.5) * step_m / rng[ray])[:, None]
        r0 = r1


def merge_counts(keys: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique rows of ``keys`` (N, k) int64 with their ``counts`` summed."""
    if not len(keys):
        return np.zeros((0, keys.shape[1]), np.int64), np.zeros(0, np.int64)
    u, inv = np.unique(keys, axis=0, return_inverse=True)
    return u, np.bincount(inv.ravel(), weights=counts, minlength=len(u)).astype(np.int64)


def free_space_evidence(points_m: np.ndarray, origins_m: np.ndarray, pass_id: np.ndarray, ground_z_m: np.ndarray,
                        voxel_m: float = 0.5, ray_stride: int = 8, stop_m: float = 1.0, ground_clear_m: float = 0.3,
                        max_range_m: float = 40.0, first_index: int = 0, sample_budget: int = 2_000_000
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Evidence of one batch of points for the free-space test: unique (voxel, pass) hits (K, 2) of the points
    above the road, and unique (voxel, pass) free crossings (L, 2) with their ray counts (L,). Rays are every
    ``ray_stride``-th point counting from ``first_index`` (the batch's offset in the whole stream); evidence of
    batches merges by concatenation + ``merge_counts``. Memory: ``sample_budget`` ray samples at a time."""
    pts = np.asarray(points_m, float)
    pass_id = np.asarray(pass_id, np.int64)
    ground_z_m = np.asarray(ground_z_m, float)
    above = pts[:, 2] > ground_z_m + ground_clear_m
    hits = np.unique(np.column_stack([voxel_keys(pts[above], voxel_m), pass_id[above]]), axis=0)
    sel = np.arange((-first_index) % max(1, ray_stride), len(pts), max(1, ray_stride))
    keys, counts = [np.zeros((0, 2), np.int64)], [np.zeros(0, np.int64)]
    for ray, samples in _ray_samples(np.asarray(origins_m)[sel].astype(float), pts[sel], voxel_m / 2, stop_m,
                                     max_range_m, sample_budget):
        keep = samples[:, 2] > ground_z_m[sel][ray] + ground_clear_m
        u, n = np.unique(np.column_stack([voxel_keys(samples[keep], voxel_m), pass_id[sel][ray][keep]]), axis=0,
                         return_counts=True)
        keys.append(u)
        counts.append(n)
    free, free_n = merge_counts(np.vstack(keys), np.concatenate(counts))
    return hits, free, free_n


def dynamic_voxels(hits: np.ndarray, free: np.ndarray, free_n: np.ndarray, min_free: int = 2) -> np.ndarray:
    """Sorted keys of the voxels crossed by at least ``min_free`` rays of passes that never hit them, among
    the voxels some pass hit."""
    if not len(free) or not len(hits):
        return np.zeros(0, np.int64)
    vox_all, vox_idx = np.unique(np.r_[free[:, 0], hits[:, 0]], return_inverse=True)
    pas_all, pas_idx = np.unique(np.r_[free[:, 1], hits[:, 1]], return_inverse=True)
    code = vox_idx.astype(np.int64) * len(pas_all) + pas_idx
    free_code, hit_code = code[:len(free)], code[len(free):]
    foreign = ~np.isin(free_code, hit_code)
    n_free = np.bincount(vox_idx[:len(free)][foreign], weights=free_n[foreign], minlength=len(vox_all))
    hit_vox = np.zeros(len(vox_all), bool)
    hit_vox[vox_idx[len(free):]] = True
    return vox_all[(n_free >= min_free) & hit_vox]


def free_space_keep(points_m: np.ndarray, origins_m: np.ndarray, pass_id: np.ndarray, ground_z_m: np.ndarray,
                    voxel_m: float = 0.5, ray_stride: int = 8, stop_m: float = 1.0, min_free: int = 2,
                    ground_clear_m: float = 0.3, max_range_m: float = 40.0) -> np.ndarray:
    """Mask of the points to keep (see the module docstring), all points at once."""
    pts = np.asarray(points_m, float)
    hits, free, free_n = free_space_evidence(pts, origins_m, pass_id, ground_z_m, voxel_m, ray_stride, stop_m,
                                             ground_clear_m, max_range_m)
    above = pts[:, 2] > np.asarray(ground_z_m, float) + ground_clear_m
    return ~(above & np.isin(voxel_keys(pts, voxel_m), dynamic_voxels(hits, free, free_n, min_free)))


class VoxelSums:
    """Streaming voxel downsampling with a deferred drop: per (voxel of ``voxel_m``, free-space voxel of
    ``free_voxel_m``, above-road flag) the sum of positions and intensities and the point count. Batches add
    in any order (sums merge); ``centroids(dropped_free_voxels)`` leaves out the above-road points of the
    dropped free-space voxels and returns each voxel's centroid and mean intensity. Memory grows with the
    number of occupied voxels, not with the number of points."""

    def __init__(self, voxel_m: float, free_voxel_m: float, compact_rows: int = 4_000_000):
        self.voxel_m, self.free_voxel_m, self.compact_rows = voxel_m, free_voxel_m, compact_rows
        self._keys: list[np.ndarray] = []  # (n, 3) int64: voxel, free voxel, above
        self._sums: list[np.ndarray] = []  # (n, 5) float64: x, y, z, intensity, count
        self._rows = 0

    def add(self, xyz_m: np.ndarray, intensity: np.ndarray, above: np.ndarray) -> None:
        xyz_m = np.asarray(xyz_m, float)
        keys = np.column_stack([voxel_keys(xyz_m, self.voxel_m), voxel_keys(xyz_m, self.free_voxel_m),
                                np.asarray(above, np.int64)])
        self._append(keys, np.column_stack([xyz_m, np.asarray(intensity, float), np.ones(len(xyz_m))]))

    def _append(self, keys: np.ndarray, sums: np.ndarray) -> None:
        if not len(keys):
            return
        u, inv = np.unique(keys, axis=0, return_inverse=True)
        s = np.column_stack([np.bincount(inv.ravel(), weights=sums[:, c], minlength=len(u)) for c in range(5)])
        self._keys.append(u)
        self._sums.append(s)
        self._rows += len(u)
        if self._rows > self.compact_rows and len(self._keys) > 1:
            keys, sums = np.vstack(self._keys), np.vstack(self._sums)
            self._keys, self._sums, self._rows = [], [], 0
            self._append(keys, sums)

    def centroids(self, dropped_free_voxels: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """(centroids (M, 3), mean intensity (M,), points dropped)."""
        if not self._keys:
            return np.zeros((0, 3)), np.zeros(0), 0
        keys, sums = np.vstack(self._keys), np.vstack(self._sums)
        drop = (keys[:, 2] == 1) & np.isin(keys[:, 1], dropped_free_voxels)
        n_dropped = int(sums[drop, 4].sum())
        keys, sums = keys[~drop], sums[~drop]
        u, inv = np.unique(keys[:, 0], return_inverse=True)
        s = np.column_stack([np.bincount(inv.ravel(), weights=sums[:, c], minlength=len(u)) for c in range(5)])
        return s[:, :3] / s[:, 4:5], s[:, 3] / s[:, 4], n_dropped


def grid_split(xy_m: np.ndarray, cell_m: float) -> dict[tuple[int, int], np.ndarray]:
    """(ix, iy) -> indices of the points in the grid cell [ix c, (ix+1) c) x [iy c, (iy+1) c)."""
    if not len(xy_m):
        return {}
    ij = np.floor(np.asarray(xy_m, float)[:, :2] / cell_m).astype(np.int64)
    keys, inverse = np.unique(ij, axis=0, return_inverse=True)
    order = np.argsort(inverse.ravel(), kind="stable")
    bounds = np.r_[0, np.cumsum(np.bincount(inverse.ravel(), minlength=len(keys)))]
    return {(int(keys[k, 0]), int(keys[k, 1])): order[bounds[k]:bounds[k + 1]] for k in range(len(keys))}
