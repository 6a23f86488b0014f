"""Map-corner errors shared by consecutive epochs (Schmidt "consider" states): on a scripted drive whose map corners
carry an error drawn once per run (with the map's stated covariance), the filter that holds the corners' errors as
consider states stays consistent (Monte-Carlo NEES in its band), the one that counts them as fresh noise per epoch
does not; and the Schmidt update equals a full joint EKF's vehicle block at the first look."""
from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from fixtures.evaluate import relative_increments, road_trajectory, roadside_corners
from stages.common.geometry import wrap_angle_rad
from stages.evaluate import consider, ekf
from stages.evaluate.localize_ekf import CornerMap, CornerObservations, EkfConfig, run_ekf
from tests.stages.evaluate.ekf_settings import bare_ekf

MAP_SIGMA_M = 0.08  # per corner, fixed for a whole run: dominates the extraction noise below
EXTRACT_SIGMA_M = 0.01
ICP_XY, ICP_YAW_DEG = 0.01, 0.01
ICP_YAW = np.deg2rad(ICP_YAW_DEG)
N_EPOCHS, N_RUNS = 300, 30


def correlated_map_errors(rng: np.random.Generator, corners: np.ndarray, share: float, length_m: float
                          ) -> np.ndarray:
    """(K,2) map errors of std MAP_SIGMA_M per axis, correlated share * exp(-d^2 / 2 length_m^2) between
    corners."""
    d = np.linalg.norm(corners[:, None] - corners[None], axis=2)
    K = share * np.exp(-0.5 * (d / length_m) ** 2)
    np.fill_diagonal(K, 1.0)
    L = np.linalg.cholesky(K * MAP_SIGMA_M**2)
    return L @ rng.standard_normal((len(corners), 2))


def one_run(rng: np.random.Generator, cfg: EkfConfig, map_share: float = 0.0, map_length_m: float = 50.0
            ) -> tuple[np.ndarray, np.ndarray]:
    """(E,) NEES of one run and (E,) number of associated corners; the map errors correlated as
    ``correlated_map_errors`` when ``map_share`` > 0."""
    truth = road_trajectory(N_EPOCHS)
    corners, dirs = roadside_corners(float(truth[-1, 0] + 60.0), 20.0, np.random.default_rng(5))
    inc = relative_increments(truth)
    icp = inc + rng.standard_normal(inc.shape) * [ICP_XY, ICP_XY, ICP_YAW]
    ep, xy, cdirs = [], [], []
    for k, (x, y, yaw) in enumerate(truth):
        d = corners - [x, y]
        c, s = np.cos(yaw), np.sin(yaw)
        v = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
        vis = np.hypot(*d.T) <= 40.0
        ep.append(np.full(vis.sum(), k))
        xy.append(v[vis] + EXTRACT_SIGMA_M * rng.standard_normal((vis.sum(), 2)))
        cdirs.append(wrap_angle_rad(dirs[vis] - yaw))
    xy = np.concatenate(xy)
    obs = CornerObservations(np.concatenate(ep), xy, np.tile(np.eye(2) * EXTRACT_SIGMA_M**2, (len(xy), 1, 1)),
                             np.concatenate(cdirs))
    err = (correlated_map_errors(rng, corners, map_share, map_length_m) if map_share > 0
           else MAP_SIGMA_M * rng.standard_normal(corners.shape))
    cmap = CornerMap(corners + err,
                     np.tile(np.eye(2) * MAP_SIGMA_M**2, (len(corners), 1, 1)), dirs)
    P0 = np.diag([0.3**2, 0.3**2, np.deg2rad(0.5) ** 2])
    q0 = truth[0] + rng.multivariate_normal(np.zeros(3), P0)
    run = run_ekf(icp, obs, cmap, q0, P0, 0, cfg)
    return ekf.nees(run.q, run.P, truth), run.n_associated


def mc_nees(map_consider: bool) -> tuple[np.ndarray, np.ndarray]:
    cfg = bare_ekf(icp={"sigma_frac": 0.0, "sigma_xy_m": ICP_XY, "sigma_yaw_deg": ICP_YAW_DEG},
                   corners={"sensor_range_m": 40.0, "range_sigma_floor_m": 0.0, "bearing_sigma_floor_deg": 0.0,
                            "wall_heading_sigma_deg": 0.0, "gate_probability": 0.9999},
                   map={"consider": map_consider})
    rng = np.random.default_rng(11)
    runs = [one_run(rng, cfg) for _ in range(N_RUNS)]
    return np.mean([r[0] for r in runs], axis=0), np.min([r[1] for r in runs], axis=0)


def test_shared_map_errors_as_consider_states_keep_the_nees_in_its_band():
    lo, hi = chi2.ppf([0.005, 0.995], 3 * N_RUNS) / N_RUNS
    nees_c, n_assoc = mc_nees(True)
    nees_r, _ = mc_nees(False)
    sel = np.arange(N_EPOCHS) >= 20
    assert n_assoc[sel].min() >= 2  # corners in view all along: the shared errors matter at every epoch
    inside = np.mean((nees_c[sel] >= lo) & (nees_c[sel] <= hi))
    assert inside >= 0.9, (inside, nees_c[sel].mean())
    assert 2.5 <= nees_c[sel].mean() <= 3.5
    # fresh noise at every epoch: the filter averages the map errors away and believes it
    assert np.mean(nees_r[sel] > hi) >= 0.8, nees_r[sel].mean()
    assert nees_r[sel].mean() > 2 * nees_c[sel].mean()


def test_correlated_map_errors_need_the_correlation_in_the_consider_states():
    """Map errors correlated 0.6 exp(-d^2 / 2 (50 m)^2) between corners (the demo maps against the truth): the
    consider states that know the correlation keep the Monte-Carlo NEES near 3; independent ones average the
    shared part away over the 2-4 corners in view and are overconfident."""
    base = bare_ekf(icp={"sigma_frac": 0.0, "sigma_xy_m": ICP_XY, "sigma_yaw_deg": ICP_YAW_DEG},
                    corners={"sensor_range_m": 40.0, "range_sigma_floor_m": 0.0, "bearing_sigma_floor_deg": 0.0,
                             "wall_heading_sigma_deg": 0.0, "gate_probability": 0.9999}, map={"consider": True})
    out = {}
    for share in (0.0, 0.6):
        cfg = base.replace(map={"corr_share": share, "corr_length_m": 50.0})
        rng = np.random.default_rng(12)
        out[share] = np.mean([one_run(rng, cfg, 0.6, 50.0)[0] for _ in range(N_RUNS)], axis=0)
    sel = np.arange(N_EPOCHS) >= 20
    lo, hi = chi2.ppf([0.005, 0.995], 3 * N_RUNS) / N_RUNS
    assert 2.5 <= out[0.6][sel].mean() <= 3.5, out[0.6][sel].mean()
    assert np.mean((out[0.6][sel] >= lo) & (out[0.6][sel] <= hi)) >= 0.8
    assert out[0.0][sel].mean() > 1.3 * out[0.6][sel].mean(), (out[0.0][sel].mean(), out[0.6][sel].mean())


def test_uncorrelated_consider_states_are_unchanged_by_the_correlation_code():
    """share 0 and a share with a vanishing length give the same filter (the joint covariance is block
    diagonal either way)."""
    base = bare_ekf(icp={"sigma_frac": 0.0, "sigma_xy_m": ICP_XY, "sigma_yaw_deg": ICP_YAW_DEG},
                    corners={"sensor_range_m": 40.0, "gate_probability": 0.9999}, map={"consider": True})
    a = one_run(np.random.default_rng(4), base)[0]
    b = one_run(np.random.default_rng(4), base.replace(map={"corr_share": 0.5, "corr_length_m": 1e-6}))[0]
    np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)


def test_schmidt_update_equals_the_joint_filter_at_the_first_look():
    """With the corners' errors as full states of a joint EKF (x, c), the first update's vehicle block and the
    vehicle-corner cross-covariance equal the Schmidt update's (only the corners' own block differs)."""
    rng = np.random.default_rng(3)
    q = np.array([2.0, -1.0, 0.4])
    P = np.diag([0.2, 0.3, 0.01]) + 0.01
    corners = np.array([[12.0, 4.0], [-3.0, 15.0], [20.0, -8.0]])
    C = np.stack([np.diag([0.01, 0.02]), np.diag([0.03, 0.01]), np.eye(2) * 0.005])
    z_true, _ = ekf.predict_range_bearing(q + [0.1, -0.2, 0.02], corners)
    z = z_true + rng.normal(0, 0.01, z_true.shape)
    R = np.tile(np.diag([0.02**2, np.deg2rad(0.2) ** 2]), (3, 1, 1))
    held, _ = consider.add(consider.empty(3), np.arange(3), C)
    s_state, s_held, _ = consider.update(ekf.EkfState(q, P), held, z, np.arange(3), corners, R)
    # joint EKF: state (x, y, yaw, c1e, c1n, ...), measurement Jacobian [Hx | Hc]
    _, Hx = ekf.predict_range_bearing(q, corners)
    Jm = ekf.map_corner_jacobian(Hx)
    H = np.zeros((6, 9))
    H[:, :3] = Hx
    for j in range(3):
        H[2 * j:2 * j + 2, 3 + 2 * j:5 + 2 * j] = Jm[j]
    Pj = np.zeros((9, 9))
    Pj[:3, :3] = P
    for j in range(3):
        Pj[3 + 2 * j:5 + 2 * j, 3 + 2 * j:5 + 2 * j] = C[j]
    Rf = np.zeros((6, 6))
    for j in range(3):
        Rf[2 * j:2 * j + 2, 2 * j:2 * j + 2] = R[j]
    S = H @ Pj @ H.T + Rf
    K = Pj @ H.T @ np.linalg.inv(S)
    z_pred, _ = ekf.predict_range_bearing(q, corners)
    nu = (z - z_pred).reshape(-1)
    Pj_new = (np.eye(9) - K @ H) @ Pj
    np.testing.assert_allclose(s_state.q, q + (K @ nu)[:3], atol=1e-10)
    np.testing.assert_allclose(s_state.P, Pj_new[:3, :3], atol=1e-10)
    np.testing.assert_allclose(s_held.P_xc, Pj_new[:3, 3:], atol=1e-10)
    np.testing.assert_allclose(s_held.C, C)  # the map is not re-estimated
