"""Oracle tests of the road-feature extraction and the marking MCL (Kim, Liu & Myung s.2.2-2.3)."""
from __future__ import annotations

import numpy as np

from stages.evaluate import mcl
from stages.evaluate.localize_mcl import MclConfig, odometry_increments, run_mcl
from stages.common.road_features import extract_road_features, ring_adaptive_threshold, voxel_filter_per_ring
from stages.evaluate.synthetic import ground_ring_scan, paint_markings, relative_increments

CELL = 0.1
T_VEHICLE_LIDAR = np.eye(4)
T_VEHICLE_LIDAR[2, 3] = 1.8


def _world():
    mask, origin = paint_markings(200.0, 40.0, CELL, road_y_m=20.0, crosswalks_x_m=(60.0, 130.0))
    return mask, origin


def _fetch(mask, origin, blur_m=0.2):
    field = mcl.smooth_marking_mask(mask, CELL, blur_m)

    def fetch(e0, n0, e1, n1):  # the whole synthetic world is one window
        return mcl.Raster(field, origin, CELL)
    return fetch


def test_ring_threshold_finds_bright_stripes_despite_per_ring_gain():
    rng = np.random.default_rng(3)
    az = np.deg2rad(np.arange(-180, 180, 0.2))
    xyz, inten, ring = [], [], []
    for r_i, (radius, gain, base) in enumerate([(5.0, 10.0, 3.0), (9.0, 80.0, 40.0)]):
        x, y = radius * np.cos(az), radius * np.sin(az)
        bright = np.abs(y - 1.75) < 0.08  # a lane line crossing the ring
        xyz.append(np.column_stack([x, y, np.zeros_like(x)]))
        inten.append(base + gain * bright + 0.3 * rng.standard_normal(len(x)))
        ring.append(np.full(len(x), r_i))
    xyz, inten, ring = np.concatenate(xyz), np.concatenate(inten), np.concatenate(ring)
    feat = ring_adaptive_threshold(xyz, inten, ring, window_m=3.0, offset_sigma=3.0)
    truth = np.abs(xyz[:, 1] - 1.75) < 0.08
    assert feat[truth].mean() > 0.9
    assert feat[~truth].mean() < 0.01
    # a global threshold cannot do this: ring 0's paint is darker than ring 1's asphalt
    assert inten[truth & (ring == 0)].max() < inten[~truth & (ring == 1)].min()


def test_voxel_filter_averages_per_ring_and_voxel():
    xyz = np.array([[0.01, 0.01, 0.0], [0.02, 0.03, 0.0], [0.01, 0.01, 0.0], [0.5, 0.0, 0.0]])
    pts, inten, ring = voxel_filter_per_ring(xyz, np.array([1.0, 3.0, 10.0, 7.0]), np.array([0, 0, 1, 0]), 0.1)
    assert len(pts) == 3
    got = {(int(r), round(float(i), 6)) for r, i in zip(ring, inten)}
    assert got == {(0, 2.0), (1, 10.0), (0, 7.0)}


def test_features_of_a_synthetic_scan_lie_on_paint():
    rng = np.random.default_rng(5)
    mask, origin = _world()
    q = np.array([95.0, 18.0, 0.05])  # crosswalks out of range: lane lines only
    xyz, inten, ring = ground_ring_scan(q, mask, origin, CELL, rng)
    feats = extract_road_features(xyz, inten, ring, T_VEHICLE_LIDAR, voxel_m=0.1)
    assert len(feats) > 50
    field = mcl.smooth_marking_mask(mask, CELL, 0.2)
    on_paint = mcl.correlation_scores(q[None], feats, mcl.Raster(field, origin, CELL))[0]
    off = mcl.correlation_scores((q + [0.0, 0.8, 0.0])[None], feats, mcl.Raster(field, origin, CELL))[0]
    assert on_paint > 0.8 and off < 0.4


def test_low_variance_resampling_keeps_proportions():
    rng = np.random.default_rng(1)
    w = np.array([0.5, 0.25, 0.125, 0.125])
    idx = mcl.low_variance_resample(np.repeat(w, 250) / 250, rng) // 250
    np.testing.assert_array_equal(np.bincount(idx, minlength=4), [500, 250, 125, 125])


def test_odometry_increments_integrate_a_circle():
    t_ns = np.arange(0, 10_000_000_001, 10_000_000)  # 100 Hz for 10 s
    v, w = np.full(len(t_ns), 5.0), np.full(len(t_ns), 0.1)
    scans = np.arange(0, 10_000_000_001, 100_000_000)
    inc = odometry_increments(t_ns, v, w, scans)
    truth_yaw = 0.1 * scans * 1e-9
    r = 50.0
    truth = np.column_stack([r * np.sin(truth_yaw), r * (1 - np.cos(truth_yaw)), truth_yaw])
    np.testing.assert_allclose(inc[1:], relative_increments(truth)[1:], atol=1e-6)


def test_mcl_converges_from_one_metre_offset():
    rng = np.random.default_rng(11)
    mask, origin = _world()
    n = 60
    truth = np.column_stack([40.0 + np.arange(n) * 1.0, np.full(n, 18.25), np.zeros(n)])
    truth[:, 1] += 0.5 * np.sin(np.arange(n) / 15.0)
    truth[1:, 2] = np.arctan2(np.diff(truth[:, 1]), np.diff(truth[:, 0]))
    truth[0, 2] = truth[1, 2]
    inc = relative_increments(truth)
    noisy = inc + np.column_stack([0.01 * rng.standard_normal(n), 0.005 * rng.standard_normal(n),
                                   np.deg2rad(0.05) * rng.standard_normal(n)])
    ep, pts = [], []
    for k in range(n):
        xyz, inten, ring = ground_ring_scan(truth[k], mask, origin, CELL, rng)
        f = extract_road_features(xyz, inten, ring, T_VEHICLE_LIDAR)
        ep.append(np.full(len(f), k)), pts.append(f)
    q0 = truth[0] + [0.7, -0.7, np.deg2rad(0.5)]  # ~1 m off
    cfg = MclConfig(n_particles=1000, init_sigma_xy_m=1.0)
    run = run_mcl(noisy, np.concatenate(ep), np.concatenate(pts), _fetch(mask, origin), q0, 0,
                  np.random.default_rng(2), cfg)
    err = run.q - truth
    h = np.hypot(err[:, 0], err[:, 1])
    assert np.hypot(*(q0 - truth[0])[:2]) > 0.95
    assert np.all(h[20:] < 0.2), h[20:].max()
    assert np.mean(np.abs(np.rad2deg(err[20:, 2]))) < 0.3
