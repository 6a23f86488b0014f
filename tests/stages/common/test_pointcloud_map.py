"""Point-cloud map blocks: a car present in one pass and gone in the next is dropped, the wall and road stay;
deskewed scans land where the scene is; voxel downsampling and the grid split keep every point once."""
from __future__ import annotations

import numpy as np

from stages.common.pointcloud_map import (
    VoxelSums,
    free_space_evidence,
    free_space_keep,
    grid_split,
    interpolate_poses,
    merge_counts,
    scan_to_map,
    voxel_keys,
)


def _box(rng, e0, e1, n0, n1, z0, z1, n):
    return np.column_stack([rng.uniform(e0, e1, n), rng.uniform(n0, n1, n), rng.uniform(z0, z1, n)])


def test_a_car_seen_in_one_pass_and_seen_through_in_the_other_is_dropped():
    rng = np.random.default_rng(0)
    wall = _box(rng, 0, 40, 10, 10.2, 0.0, 6.0, 20000)  # building face north of the road
    road = _box(rng, 0, 40, -5, 10, -0.02, 0.02, 20000)
    car = _box(rng, 18, 22, 4, 5.8, 0.3, 1.5, 3000)  # parked at north 4..5.8 during pass 0 only
    sensor = np.array([20.0, 0.0, 1.9])
    pts = [wall, road, car, wall.copy(), road.copy()]
    pid = [np.full(len(x), k) for k, x in zip((0, 0, 0, 1, 1), pts)]
    pts, pid = np.vstack(pts), np.concatenate(pid)
    origins = np.tile(sensor, (len(pts), 1))
    keep = free_space_keep(pts, origins, pid, np.zeros(len(pts)), voxel_m=0.5, ray_stride=1, min_free=2)
    is_car = np.zeros(len(pts), bool)
    is_car[40000:43000] = True
    assert keep[is_car].mean() < 0.05  # pass 1 saw the wall through the car's place
    assert keep[~is_car].mean() > 0.98  # wall and road kept
    # the wall is not dropped when only the car's own pass looked (nobody saw through it)
    keep0 = free_space_keep(pts[pid == 0], origins[pid == 0], pid[pid == 0], np.zeros((pid == 0).sum()))
    assert keep0.all()


def test_scan_to_map_deskews_with_the_pose_at_each_point_time():
    stamps = np.array([0, 100_000_000], np.int64)  # 0.1 s, vehicle moves 1 m east and turns 90 deg left
    xyz = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    q = np.array([[0, 0, 0, 1.0], [0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)]])
    R, t = interpolate_poses(stamps, xyz, q, np.array([50_000_000]))
    np.testing.assert_allclose(t, [[0.5, 0, 0]])
    np.testing.assert_allclose(R[0][:2, 0], [np.cos(np.pi / 4), np.sin(np.pi / 4)], atol=1e-12)
    T_vl = np.eye(4)
    T_vl[2, 3] = 1.9
    pts, origins = scan_to_map(np.array([[1.0, 0, 0], [1.0, 0, 0]]), np.array([0, 100_000_000]), T_vl, stamps, xyz, q)
    np.testing.assert_allclose(pts, [[1.0, 0, 1.9], [1.0, 1.0, 1.9]], atol=1e-12)
    np.testing.assert_allclose(origins[1], [1.0, 0, 1.9], atol=1e-12)


def test_voxel_sums_in_batches_equal_open3d_voxel_downsampling_and_drop_only_above_road_points():
    import open3d as o3d

    rng = np.random.default_rng(1)
    xyz = rng.uniform(-30, 30, (5000, 3))
    xyz[0] = -32.5  # open3d's grid starts half a voxel below the minimum: put it on a multiple of 5 m
    inten = rng.uniform(0, 1, len(xyz))
    sums = VoxelSums(5.0, 0.5, compact_rows=1000)  # small: batches are merged several times
    for a in range(0, len(xyz), 700):  # batches, in any order of points
        sums.add(xyz[a:a + 700], inten[a:a + 700], np.zeros(700, bool)[:len(xyz[a:a + 700])])
    down, down_i, n_dropped = sums.centroids(np.unique(voxel_keys(xyz, 0.5)))  # nothing above road: none dropped
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    pc.colors = o3d.utility.Vector3dVector(np.column_stack([inten] * 3))
    ref = pc.voxel_down_sample(5.0)
    order, ref_order = np.lexsort(down.T), np.lexsort(np.asarray(ref.points).T)
    assert n_dropped == 0 and len(down) == len(ref.points)
    np.testing.assert_allclose(down[order], np.asarray(ref.points)[ref_order], atol=1e-9)
    np.testing.assert_allclose(down_i[order], np.asarray(ref.colors)[ref_order, 0], atol=1e-9)
    # the above-road points of a dropped free-space voxel leave; the road points in it stay
    sums = VoxelSums(0.2, 0.5)
    sums.add(np.array([[0.1, 0.1, 0.1], [0.15, 0.1, 0.1], [0.1, 0.1, 0.05]]), np.ones(3), np.array([True, True, False]))
    down, _, n_dropped = sums.centroids(voxel_keys(np.array([[0.1, 0.1, 0.1]]), 0.5))
    assert n_dropped == 2
    np.testing.assert_allclose(down, [[0.1, 0.1, 0.05]])


def test_free_space_evidence_of_batches_merges_to_the_evidence_of_the_whole():
    rng = np.random.default_rng(2)
    pts = np.vstack([_box(rng, 0, 40, 10, 10.2, 0.0, 6.0, 4000), _box(rng, 18, 22, 4, 5.8, 0.3, 1.5, 600)])
    origins = np.tile([20.0, 0.0, 1.9], (len(pts), 1))
    pid = rng.integers(0, 3, len(pts))
    whole = free_space_evidence(pts, origins, pid, np.zeros(len(pts)), sample_budget=5000)
    parts = [
        free_space_evidence(
            pts[a : a + 999],
            origins[a : a + 999],
            pid[a : a + 999],
            np.zeros(999)[: len(pts[a : a + 999])],
            first_index=a,
        )
        for a in range(0, len(pts), 999)
    ]
    hits = np.unique(np.vstack([p[0] for p in parts]), axis=0)
    free, n = merge_counts(np.vstack([p[1] for p in parts]), np.concatenate([p[2] for p in parts]))
    np.testing.assert_array_equal(hits, whole[0])
    np.testing.assert_array_equal(free, whole[1])
    np.testing.assert_array_equal(n, whole[2])


def test_grid_split_keeps_every_point_once():
    rng = np.random.default_rng(1)
    xyz = rng.uniform(-30, 30, (5000, 3))
    cells = grid_split(xyz, 20.0)
    assert sorted(np.concatenate(list(cells.values())).tolist()) == list(range(len(xyz)))
    for (i, j), idx in cells.items():
        assert (np.floor(xyz[idx, :2] / 20.0) == [i, j]).all()
