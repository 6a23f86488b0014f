"""Oracle tests of the road-feature extraction and the marking MCL (Kim, Liu & Myung s.2.2-2.3).

Over 300 lines on purpose: road-feature extraction and the MCL share one scripted world; the oracles
read in the order of the paper's sections.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import distance_transform_edt

from fixtures.evaluate import ground_ring_scan, paint_markings, relative_increments
from stages.common.road_features import extract_road_features, ring_adaptive_threshold, voxel_filter_per_ring
from stages.evaluate import mcl
from stages.evaluate.localize_mcl import MclConfig, odometry_increments, run_mcl
from stages.evaluate.metrics import compute_errors

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


# --- issue 10, MCL sixth pass: deskew, distance field, odometry calibration, tempering, recovery -------------------

def _ring_drive(n: int, rng: np.random.Generator, x0: float = 40.0):
    """Truth weaving across the lane along the synthetic road at 1 m per scan, and its ring features."""
    s = x0 + np.arange(n) * 1.0
    truth = np.column_stack([s, 18.25 + 0.5 * np.sin(s / 15.0), np.zeros(n)])
    truth[:, 2] = np.arctan2(np.gradient(truth[:, 1]), np.gradient(truth[:, 0]))
    mask, origin = _world()
    ep, pts = [], []
    for k in range(n):
        xyz, inten, ring = ground_ring_scan(truth[k], mask, origin, CELL, rng)
        f = extract_road_features(xyz, inten, ring, T_VEHICLE_LIDAR)
        ep.append(np.full(len(f), k)), pts.append(f)
    return truth, np.concatenate(ep), np.concatenate(pts)


def _distance_fetch(mask, origin, sigma_m=0.2):
    field = mcl.distance_likelihood_field(mask, CELL, sigma_m)
    return lambda e0, n0, e1, n1: mcl.Raster(field, origin, CELL)


def _wheel_gyro(truth, rng, scale=1.02, gyro_bias_deg_per_scan=0.01):
    """Wheel + gyro increments with a wheel scale error, a gyro bias and a little white noise."""
    n = len(truth)
    odo = relative_increments(truth)
    odo[1:, 0] *= scale
    odo[1:, 2] += np.deg2rad(gyro_bias_deg_per_scan)
    odo[1:] += np.column_stack([0.002 * rng.standard_normal(n - 1), np.zeros(n - 1),
                                np.deg2rad(0.005) * rng.standard_normal(n - 1)])
    return odo


@pytest.fixture(scope="module")
def ring_drive():
    rng = np.random.default_rng(7)
    truth, ep, pts = _ring_drive(150, rng)
    return truth, ep, pts, _wheel_gyro(truth, rng)


def test_distance_field_is_a_gaussian_of_the_distance_to_paint():
    mask = np.zeros((50, 80), np.uint8)
    mask[20, 10:70] = 1  # a one-cell line along row 20
    mask[30:33, 40] = 1
    field = mcl.distance_likelihood_field(mask, 0.1, 0.2)
    assert field.dtype == np.float32 and field[20, 30] == pytest.approx(1.0)
    # straight above the line, k cells away: d = 0.1 k m
    for k in (1, 2, 4, 6):
        assert field[20 - k, 20] == pytest.approx(np.exp(-0.5 * (0.1 * k / 0.2) ** 2), rel=1e-5)
    # cross-check against scipy's exact Euclidean distance transform everywhere
    d = distance_transform_edt(mask == 0) * 0.1
    np.testing.assert_allclose(field, np.exp(-0.5 * (d / 0.2) ** 2), atol=1e-6)
    assert not mcl.distance_likelihood_field(np.zeros((4, 4)), 0.1, 0.2).any()


def test_prediction_applies_each_particles_wheel_scale_gyro_bias_and_gyro_gain():
    rng = np.random.default_rng(0)
    particles = np.array([[0.0, 0.0, 0.0], [10.0, 5.0, np.pi / 2]])
    calib = np.array([[1.02, 0.0], [0.98, np.deg2rad(1.0)]])  # scale, gyro bias rad/s
    out = mcl.predict_particles(particles, np.array([1.0, 0.0, np.deg2rad(2.0)]), 0.0, 0.0, 0.0, rng, calib,
                                dt_s=0.5)
    np.testing.assert_allclose(out[0], [1.02, 0.0, np.deg2rad(2.0)], atol=1e-12)
    np.testing.assert_allclose(out[1], [10.0, 5.98, np.pi / 2 + np.deg2rad(2.0 - 0.5)], atol=1e-12)
    # a third column is the gyro's gain: true turn = gain * (gyro turn - bias dt)
    gained = np.column_stack([calib, [1.01, 0.99]])
    out = mcl.predict_particles(particles, np.array([1.0, 0.0, np.deg2rad(2.0)]), 0.0, 0.0, 0.0, rng, gained,
                                dt_s=0.5)
    np.testing.assert_allclose(out[:, 2], [np.deg2rad(2.0 * 1.01), np.pi / 2 + np.deg2rad(1.5 * 0.99)], atol=1e-12)
    assert mcl.init_calibration(5, 0.01, 0.001, rng).shape == (5, 2)
    assert mcl.init_calibration(5, 0.01, 0.001, rng, sigma_gyro_gain=0.005).shape == (5, 3)
    # noise: along track sigma_frac * d + floor, across track its own fraction (vehicle frame, not the axes)
    many = np.zeros((20000, 3))
    out = mcl.predict_particles(many, np.array([2.0, 0.0, 0.0]), 0.01, 0.005, 0.0, rng, sigma_lateral_frac=0.0)
    assert np.std(out[:, 0]) == pytest.approx(0.025, rel=0.05)
    assert np.std(out[:, 1]) == pytest.approx(0.005, rel=0.05)


def test_tempering_step_keeps_the_effective_sample_size():
    rng = np.random.default_rng(4)
    n = 1000
    log_w = np.full(n, -np.log(n))
    loglik = -0.5 * (rng.standard_normal(n) / 0.02) ** 2  # a likelihood 50x narrower than the cloud
    assert mcl.effective_sample_size(mcl.normalized_weights(log_w + loglik)) < 50
    beta = mcl.tempering_step(log_w, loglik, 1.0, min_ess=0.3 * n)
    assert 0.0 < beta < 1.0
    assert mcl.effective_sample_size(mcl.normalized_weights(log_w + beta * loglik)) >= 0.3 * n
    assert mcl.effective_sample_size(mcl.normalized_weights(log_w + 1.1 * beta * loglik)) < 0.31 * n
    assert mcl.tempering_step(log_w, 1e-3 * loglik, 1.0, min_ess=0.3 * n) == 1.0  # a gentle one goes in whole


def test_mcl_absorbs_a_two_percent_wheel_scale_error_along_and_across(ring_drive):
    truth, ep, pts, odo = ring_drive
    mask, origin = _world()
    q0 = truth[0] + [0.4, -0.3, np.deg2rad(0.3)]
    run = run_mcl(odo, ep, pts, _distance_fetch(mask, origin), q0, 0, np.random.default_rng(3), MclConfig())
    e = compute_errors(run.q, truth)
    after = slice(30, None)
    assert np.mean(np.abs(e.err_longitudinal_m[after])) < 0.05, np.abs(e.err_longitudinal_m[after]).max()
    assert np.max(np.abs(e.err_longitudinal_m[after])) < 0.15
    assert np.mean(np.abs(e.err_lateral_m[after])) < 0.02
    assert np.mean(np.abs(np.rad2deg(e.err_yaw_rad[after]))) < 0.05
    assert run.calibration[-1, 0] == pytest.approx(1 / 1.02, abs=0.006)  # the wheel scale it found
    # the same filter without the scale state (and the along-track noise of the true odometry) drifts along track
    no_scale = MclConfig(init_sigma_scale=0.0, sigma_scale_per_sqrt_m=0.0, sigma_frac=0.002, sigma_xy_m=0.005)
    run0 = run_mcl(odo, ep, pts, _distance_fetch(mask, origin), q0, 0, np.random.default_rng(3), no_scale)
    e0 = compute_errors(run0.q, truth)
    assert np.mean(np.abs(e0.err_longitudinal_m[after])) > 5 * np.mean(np.abs(e.err_longitudinal_m[after]))


def test_injection_recovers_from_a_sideways_slip_that_reweighting_cannot(ring_drive):
    truth, ep, pts, odo = ring_drive
    mask, origin = _world()
    slipped = odo.copy()
    slipped[70, 1] += 0.8  # the odometry misses a 0.8 m sideways jump at epoch 70
    q0 = truth[0] + [0.4, -0.3, np.deg2rad(0.3)]
    err = {}
    for share in (0.3, 0.0):
        run = run_mcl(slipped, ep, pts, _distance_fetch(mask, origin), q0, 0, np.random.default_rng(3),
                      MclConfig(recovery={"max_inject": share}))
        err[share] = np.hypot(*compute_errors(run.q, truth).err_xy_m.T)
        assert (run.injected[:70] == 0).all()  # never while the particles fit the scans
    assert err[0.3][71] > 0.5 and err[0.0][71] > 0.5
    assert err[0.3][80:].max() < 0.15  # back within 10 scans (filter seeds 0-9: recovered by scan 75-77)
    assert err[0.0][76:96].min() > 0.5  # without it still lost 25 scans later (seeds 0-9; some never recover)


def test_standstill_holds_the_pose_despite_the_gyro_bias():
    rng = np.random.default_rng(12)
    mask, origin = _world()
    truth = np.tile([95.0, 18.25, 0.0], (40, 1))
    ep, pts = [], []
    for k in range(len(truth)):
        xyz, inten, ring = ground_ring_scan(truth[k], mask, origin, CELL, rng)
        f = extract_road_features(xyz, inten, ring, T_VEHICLE_LIDAR)
        ep.append(np.full(len(f), k)), pts.append(f)
    odo = np.zeros((len(truth), 3))
    odo[1:, 2] = np.deg2rad(0.05)  # a gyro bias of 0.5 deg/s, speed 0: 2 deg of phantom turn over 4 s
    run = run_mcl(odo, np.concatenate(ep), np.concatenate(pts), _distance_fetch(mask, origin), truth[0], 0,
                  np.random.default_rng(1), MclConfig(init_sigma_xy_m=0.1, init_sigma_yaw_deg=0.1))
    np.testing.assert_allclose(run.q[1:], np.repeat(run.q[:1], len(truth) - 1, axis=0), atol=1e-12)
    assert np.isnan(run.ess[1:]).all()  # one update: a scan repeated without moving brings nothing new


def _moving_scan(q_start, speed_mps, rng, period_s=0.1, slots=50):
    """A raw revolution while the vehicle drives: each azimuth slot is seen from the pose at its firing time,
    azimuth falling with time like the simulator's lidar. Returns lidar-frame xyz, intensity, ring, time offsets."""
    mask, origin = _world()
    xyz, inten, ring, t_off = [], [], [], []
    for j in range(slots):
        t_mid = (j + 0.5) / slots * period_s
        q = q_start + [speed_mps * t_mid * np.cos(q_start[2]), speed_mps * t_mid * np.sin(q_start[2]), 0.0]
        p, i, r = ground_ring_scan(q, mask, origin, CELL, rng)
        t = (np.pi - np.arctan2(p[:, 1], p[:, 0])) / (2 * np.pi) * period_s
        keep = np.floor(t / period_s * slots) == j
        xyz.append(p[keep]), inten.append(i[keep]), ring.append(r[keep]), t_off.append(t[keep])
    return np.concatenate(xyz), np.concatenate(inten), np.concatenate(ring), np.concatenate(t_off)


def test_extract_features_deskews_each_scan_with_the_wheel_odometry():
    import pyarrow as pa

    from pipeline.testing import make_context
    from schemas import schema_of
    from stages.common.wheel_odometry import OdometryTrack
    from stages.evaluate import compute as compute_mod
    from stages.evaluate.params import EvaluateParams

    rng = np.random.default_rng(9)
    q = np.array([50.0, 18.25, 0.0])  # the crosswalk at 60 m and the dashes give along-track evidence
    speed = 10.0
    xyz, inten, ring, t_off = _moving_scan(q, speed, rng)
    stamp = 10**12
    n = len(xyz)
    cols = {"drive": ["d1"] * n, "chunk": np.zeros(n, int), "scan_id": np.zeros(n, int), "stamp_ns": np.full(n, stamp),
            "x_m": xyz[:, 0], "y_m": xyz[:, 1], "z_m": xyz[:, 2], "intensity": inten, "ring": ring,
            "time_offset_s": t_off}
    schema = schema_of("scans_raw")
    scans = pa.table({f.name: pa.array(cols[f.name], type=f.type) for f in schema}, schema=schema)
    odo_t = stamp + np.arange(-20, 40) * 10_000_000  # 100 Hz around the scan
    track = OdometryTrack(odo_t, np.full(len(odo_t), speed), np.zeros(len(odo_t)))
    mask, origin = _world()
    raster = _distance_fetch(mask, origin, 0.1)(0, 0, 0, 0)
    shifts = np.arange(-1.0, 1.0001, 0.05)

    def best_shift(feats):
        cands = np.column_stack([q[0] + shifts, np.full(len(shifts), q[1]), np.zeros(len(shifts))])
        return shifts[np.argmax(mcl.correlation_scores(cands, feats, raster))]

    found = {}
    for deskew in (True, False):
        p = EvaluateParams(features={"deskew": deskew})
        ctx = make_context("evaluate", p, {"scans": scans})
        ep, feats = compute_mod.extract_features(ctx, "d1", np.array([0]), T_VEHICLE_LIDAR, p,
                                                 track if deskew else None)
        assert len(feats) > 100 and (ep == 0).all()
        found[deskew] = best_shift(feats)
    # raw points trail by speed * firing time (0.05 s on average): the scan-start pose must move ~0.5 m ahead to fit
    assert abs(found[True]) <= 0.05
    assert found[False] == pytest.approx(speed * 0.05, abs=0.15)


def test_the_mcl_section_states_degrees_and_the_filter_reads_radians():
    from stages.evaluate.params import EvaluateParams

    p = EvaluateParams(mcl={"sigma_yaw_deg": 0.5, "init_sigma_gyro_bias_deg_s": 1.0, "init_sigma_scale": 0.03,
                            "recovery": {"max_inject": 0.0}},
                       markings={"decorrelation_m": 2.0, "feature_range_m": 25.0})
    cfg = p.mcl
    assert cfg.sigma_yaw_rad == pytest.approx(np.deg2rad(0.5))
    assert cfg.init_sigma_gyro_bias_radps == pytest.approx(np.deg2rad(1.0))
    assert (cfg.init_sigma_scale, cfg.recovery.max_inject, p.markings.decorrelation_m,
            p.markings.feature_range_m) == (0.03, 0.0, 2.0, 25.0)
    assert EvaluateParams().mcl == MclConfig()  # the stage's section is the filter's default


def test_regularize_spreads_by_the_optimal_bandwidth_of_the_cloud():
    rng = np.random.default_rng(2)
    cloud = np.column_stack([rng.normal(5.0, 0.3, 4000), rng.normal(-2.0, 0.05, 4000), rng.normal(0.1, 0.01, 4000)])
    moved = mcl.regularize(cloud, rng)
    h = (4.0 / (4000 * 5.0)) ** (1.0 / 7.0)
    np.testing.assert_allclose(np.std(moved - cloud, axis=0), h * np.std(cloud, axis=0), rtol=0.05)
    np.testing.assert_allclose(moved.mean(axis=0), cloud.mean(axis=0), atol=0.02)
    floored = mcl.regularize(np.zeros((4000, 3)), rng, floor=(0.01, 0.01, 0.001))  # a collapsed cloud still moves
    np.testing.assert_allclose(np.std(floored, axis=0), [0.01, 0.01, 0.001], rtol=0.05)
