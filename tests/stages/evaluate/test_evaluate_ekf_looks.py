"""Repeated looks at a corner from nearly the same place (``corner_decorrelation_m``): a corner's extraction error
that drifts with the travel (a Gauss-Markov process along the road, as the viewpoint-dependent part of a real
corner's error does) is repeated by every scan of a slow drive. Counting each scan as new evidence, the filter
averages that error away and believes it; with each look weighted by min(1, travel since the corner's last look /
d) and d the process's independent-sample spacing (twice its correlation length) the Monte-Carlo NEES stays near
its expectation. The weights themselves are checked on a hand-made sequence of looks."""
from __future__ import annotations

import numpy as np

from fixtures.evaluate import relative_increments, road_trajectory, roadside_corners
from stages.common.geometry import wrap_angle_rad
from stages.evaluate import ekf
from stages.evaluate.localize_ekf import CornerMap, CornerObservations, EkfConfig, _Looks, run_ekf
from tests.stages.evaluate.ekf_settings import bare_ekf

EXTRACT_SIGMA_M = 0.05  # per scan, all of it correlated along the road
CORR_LENGTH_M = 0.5
SPEED_MPS = 0.5  # 0.05 m per scan: ten scans share most of a corner's error
ICP_XY, ICP_YAW_DEG = 0.005, 0.01
ICP_YAW = np.deg2rad(ICP_YAW_DEG)
N_EPOCHS, N_RUNS = 400, 30


def one_run(rng: np.random.Generator, cfg: EkfConfig) -> np.ndarray:
    truth = road_trajectory(N_EPOCHS, speed_mps=SPEED_MPS)
    corners, dirs = roadside_corners(float(truth[-1, 0] + 60.0), 20.0, np.random.default_rng(5))
    inc = relative_increments(truth)
    icp = inc + rng.standard_normal(inc.shape) * [ICP_XY, ICP_XY, ICP_YAW]
    step = SPEED_MPS / 10.0
    rho = np.exp(-step / CORR_LENGTH_M)
    err = EXTRACT_SIGMA_M * rng.standard_normal(corners.shape)  # per corner, stationary Gauss-Markov in travel
    ep, xy, cdirs = [], [], []
    for k, (x, y, yaw) in enumerate(truth):
        if k:
            err = rho * err + np.sqrt(1 - rho**2) * EXTRACT_SIGMA_M * rng.standard_normal(corners.shape)
        d = corners - [x, y]
        c, s = np.cos(yaw), np.sin(yaw)
        v = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
        vis = np.hypot(*d.T) <= 40.0
        ep.append(np.full(vis.sum(), k)), xy.append(v[vis] + err[vis]), cdirs.append(wrap_angle_rad(dirs[vis] - yaw))
    xy = np.concatenate(xy)
    obs = CornerObservations(np.concatenate(ep), xy, np.tile(np.eye(2) * EXTRACT_SIGMA_M**2, (len(xy), 1, 1)),
                             np.concatenate(cdirs))
    cmap = CornerMap(corners, np.tile(np.eye(2) * 1e-6, (len(corners), 1, 1)), dirs)
    P0 = np.diag([0.3**2, 0.3**2, np.deg2rad(0.5) ** 2])
    q0 = truth[0] + rng.multivariate_normal(np.zeros(3), P0)
    run = run_ekf(icp, obs, cmap, q0, P0, 0, cfg)
    return ekf.nees(run.q, run.P, truth)


def mc_nees(decorrelation_m: float) -> np.ndarray:
    cfg = bare_ekf(icp={"sigma_frac": 0.0, "sigma_xy_m": ICP_XY, "sigma_yaw_deg": ICP_YAW_DEG},
                   corners={"sensor_range_m": 40.0, "range_sigma_floor_m": 0.0, "bearing_sigma_floor_deg": 0.0,
                            "wall_heading_sigma_deg": 0.0, "gate_probability": 0.9999,
                            "decorrelation_m": decorrelation_m})
    rng = np.random.default_rng(3)
    return np.mean([one_run(rng, cfg) for _ in range(N_RUNS)], axis=0)


def test_looks_weighted_by_travel_keep_a_slow_drive_consistent():
    sel = np.arange(N_EPOCHS) >= 40
    weighted = mc_nees(2 * CORR_LENGTH_M)[sel].mean()
    every = mc_nees(0.0)[sel].mean()
    assert 1.5 <= weighted <= 4.5, weighted
    assert every > 2.0 * weighted and every > 6.0, (every, weighted)


def test_a_look_weighs_the_travel_since_the_corners_last_look():
    looks = _Looks(0.5)
    np.testing.assert_allclose(looks.weights(np.array([3, 4]), 10.0), [1.0, 1.0])  # never seen: full weight
    looks.used(np.array([3]), 10.0)
    np.testing.assert_allclose(looks.weights(np.array([3, 4]), 10.1), [0.2, 1.0])
    np.testing.assert_allclose(looks.weights(np.array([3]), 11.0), [1.0])
    np.testing.assert_allclose(_Looks(0.0).weights(np.array([3]), 0.0), [1.0])  # off: every look counts
