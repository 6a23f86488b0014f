"""Epoch loop of the corner-map EKF and of the ICP dead-reckoning baseline (arrays in, arrays out).

Epoch k is scan k of the evaluation drive. ``increments[k]`` is the ICP increment from scan k-1 to scan k in
the vehicle frame of scan k-1 (row 0 is ignored). Extracted corners come as flat arrays tagged with the epoch
they belong to, already in the vehicle frame (see ``corners_to_vehicle``).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from stages.common.geometry import wrap_angle_rad
from stages.evaluate import consider, ekf, mcl
from stages.evaluate.association import associate, wall_headings_rad

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CornerObservations:
    epoch: np.ndarray  # (C,) int, sorted ascending
    xy_vehicle_m: np.ndarray  # (C,2)
    cov_vehicle_m2: np.ndarray  # (C,2,2)
    dirs_vehicle_rad: np.ndarray  # (C,2) wall directions from the corner

    def slices(self, n_epochs: int) -> np.ndarray:
        """(n_epochs+1,) offsets: the corners of epoch k are ``[off[k], off[k+1])``."""
        return np.searchsorted(self.epoch, np.arange(n_epochs + 1))


@dataclass(frozen=True)
class CornerMap:
    en_m: np.ndarray  # (K,2) east, north
    cov_m2: np.ndarray  # (K,2,2)
    dirs_enu_rad: np.ndarray  # (K,2)


@dataclass(frozen=True)
class EkfConfig:
    icp_sigma_frac: float = 0.02  # translation noise per metre travelled
    icp_sigma_xy_m: float = 0.01  # translation noise floor per step
    icp_sigma_yaw_rad: float = np.deg2rad(0.05)  # heading noise floor per step
    icp_sigma_yaw_frac: float = 0.02  # heading noise per radian turned
    sensor_range_m: float = 60.0
    gate_chi2: float = 9.21  # chi-square 2 dof, 99 %
    angle_tol_rad: float = np.deg2rad(15.0)
    association: str = "gnn"
    range_sigma_floor_m: float = 0.02
    bearing_sigma_floor_rad: float = np.deg2rad(0.1)
    # Heading measured by the associated corners' wall directions (0 = off, the paper's range/bearing only).
    # Range/bearing to a single corner leaves the rotation about that corner unobservable (see docs).
    wall_heading_sigma_rad: float = np.deg2rad(1.5)
    # Wheel/gyro motion model with the gyro bias and the wheel scale as states (used when run_ekf is given the
    # wheel increments): the simulator's / a MEMS gyro's bias spec and random walk, a wheel scale of 1 %.
    gyro_bias_sigma_rad_s: float = np.deg2rad(0.115)
    gyro_bias_rw_rad_s_per_sqrt_s: float = np.deg2rad(0.0057)
    wheel_scale_sigma: float = 0.01
    wheel_scale_rw_per_sqrt_m: float = 1e-3
    wheel_sigma_frac: float = 0.005  # along-track wheel noise per metre (beside the scale)
    wheel_sigma_lateral_frac: float = 0.002  # across-track (slip) per metre
    wheel_sigma_xy_m: float = 0.005  # floor per step
    gyro_sigma_yaw_rad: float = np.deg2rad(0.01)  # gyro white noise per step
    gyro_sigma_yaw_frac: float = 0.005  # gyro scale error per radian turned
    icp_gate_chi2: float = 16.27  # ICP vs wheel/gyro increment, chi-square 3 dof, 99.9 %
    # Map-corner errors as Schmidt "consider" states (``consider``): shared by every epoch that uses the corner,
    # not fresh noise at each; a corner farther than consider_forget_m leaves the set. False: the paper's R only.
    map_consider: bool = True
    consider_forget_m: float = 120.0
    map_cov_scale: float = 1.0  # multiplies the map's stored corner covariances (see params.ekf_map_cov_scale)
    # Correlation of two map corners' errors at distance d, share * exp(-d^2 / 2 length^2) (consider.MapCorrelation)
    map_corr_share: float = 0.0
    map_corr_length_m: float = 50.0
    # ICP motion model: the gyro bias as a 4th state carried by the wheel/gyro increments that replace failed or
    # gated ICP ones (``run_ekf``'s ``from_gyro``), with gyro_bias_sigma_rad_s / gyro_bias_rw_rad_s_per_sqrt_s.
    icp_gyro_bias_state: bool = False
    icp_gyro_fusion: bool = False  # with the bias state: the gyro's heading change also measures ICP's increment
    heading_rw_rad_per_sqrt_s: float = 0.0  # ICP motion model: heading random walk beside the per-step noise
    # With the fusion and ``run_ekf``'s ``wheel_fallback``: an ICP increment whose heading change is this far
    # (chi-square 1 dof) from the bias-corrected gyro's is replaced by the wheel/gyro increment (0 = off).
    icp_gyro_gate_chi2: float = 0.0
    # Road markings (``ekf_markings``): each scan's road features against the map's marking raster, with the MCL's
    # likelihood (gain per effective point, effective points, decorrelation travel, features per scan), applied
    # along the directions it informs beyond marking_min_info (in units of the prior's information), gated at
    # marking_gate_probability (chi-square, as many dof as directions). Needs ``run_ekf``'s features and fetcher.
    markings: bool = False
    marking_sharpness: float = 5.0
    marking_effective_points: float = 60.0
    marking_decorrelation_m: float = 0.5
    marking_max_features: int = 400
    marking_min_features: int = 10
    marking_min_info: float = 0.05
    marking_gate_probability: float = 0.999
    marking_grid_n: int = 7
    marking_window_m: float = 240.0
    marking_feature_range_m: float = 30.0
    # The raster's own local error (the mapping drive's pose error where it painted), a Gauss-Markov offset along
    # the road held as a consider parameter (``consider.with_map_offset``); 0 = the raster is taken as exact.
    marking_map_sigma_m: float = 0.0
    marking_map_sigma_yaw_rad: float = 0.0
    marking_map_length_m: float = 50.0
    # Repeated looks at a corner from nearly the same place repeat most of its extraction error (the per-scan
    # errors of one landmark correlate 0.2-0.5 between scans 0.25-5 m apart on demo calibration seed 1): a corner's
    # range/bearing and wall-heading noise is divided by min(1, travel since the corner last measured the pose /
    # corner_decorrelation_m), as the road markings' likelihood is tempered; 0 = every look counts fully.
    corner_decorrelation_m: float = 0.0


@dataclass(frozen=True)
class EkfRun:
    q: np.ndarray  # (E,3) estimates (NaN before initialisation)
    P: np.ndarray  # (E,3,3)
    n_associated: np.ndarray  # (E,) int
    assoc_epoch: np.ndarray  # (A,) epoch of every association
    assoc_map_idx: np.ndarray  # (A,) index into CornerMap rows
    marking_rows: np.ndarray | None = None  # (E,) directions the road markings measured (-1: gated out)


def corners_to_vehicle(T_vehicle_lidar: np.ndarray, xy_lidar_m: np.ndarray, cov_lidar_m2: np.ndarray,
                       dirs_lidar_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Move corners from the lidar frame into the vehicle frame with the planar part of a 4x4 extrinsic."""
    T = np.asarray(T_vehicle_lidar, dtype=float)
    yaw = np.arctan2(T[1, 0], T[0, 0])
    R = ekf.rotation_2d(yaw)
    xy = np.asarray(xy_lidar_m, dtype=float).reshape(-1, 2) @ R.T + T[:2, 3]
    cov = R @ np.asarray(cov_lidar_m2, dtype=float).reshape(-1, 2, 2) @ R.T
    return xy, cov, wrap_angle_rad(np.asarray(dirs_lidar_rad, dtype=float).reshape(-1, 2) + yaw)


def increment_covariance(increment: np.ndarray, cfg: EkfConfig) -> np.ndarray:
    """Diagonal covariance of one ICP increment, growing with distance and turn."""
    dist = float(np.hypot(increment[0], increment[1]))
    s_xy = cfg.icp_sigma_frac * dist + cfg.icp_sigma_xy_m
    s_yaw = cfg.icp_sigma_yaw_frac * abs(float(increment[2])) + cfg.icp_sigma_yaw_rad
    return np.diag([s_xy**2, s_xy**2, s_yaw**2])


def gyro_sigma_yaw_rad(dyaw_rad: float, cfg: EkfConfig) -> float:
    """The gyro's heading-change std over one step beside its bias: a floor plus a scale error per radian."""
    return cfg.gyro_sigma_yaw_frac * abs(float(dyaw_rad)) + cfg.gyro_sigma_yaw_rad


def wheel_covariance(wheel: np.ndarray, cfg: EkfConfig) -> np.ndarray:
    """Covariance (vehicle frame) of a wheel/gyro increment beside its scale and bias (which are states)."""
    dist = float(np.hypot(wheel[0], wheel[1]))
    s_along = cfg.wheel_sigma_frac * dist + cfg.wheel_sigma_xy_m
    s_lat = cfg.wheel_sigma_lateral_frac * dist + cfg.wheel_sigma_xy_m
    return np.diag([s_along**2, s_lat**2, gyro_sigma_yaw_rad(wheel[2], cfg) ** 2])


def icp_covariance(increment: np.ndarray, cov_info: np.ndarray | None, cfg: EkfConfig) -> np.ndarray:
    """The ICP increment's covariance: the registration's own (planar marginal of its information; large along a
    degenerate street's axis) plus the per-step floors of ``increment_covariance``."""
    Q = increment_covariance(increment, cfg)
    if cov_info is not None and np.all(np.isfinite(cov_info)):
        Q = Q + cov_info
    return Q


def _motion(state: ekf.EkfState, k: int, increments: np.ndarray, wheel: np.ndarray | None, dt_s: np.ndarray | None,
            icp_cov: np.ndarray | None, cfg: EkfConfig, from_gyro: np.ndarray | None = None,
            gyro_yaw: np.ndarray | None = None, wheel_fallback: np.ndarray | None = None
            ) -> tuple[ekf.EkfState, bool, np.ndarray]:
    """One motion update; returns the state, whether an ICP increment was used and the errors' transition."""
    inc = increments[k]
    fg = None if from_gyro is None else bool(from_gyro[k])
    if (len(state.q) == 4 and wheel_fallback is not None and not fg and gyro_yaw is not None
            and cfg.icp_gyro_gate_chi2 > 0 and np.all(np.isfinite(inc))):
        # ICP against the bias-corrected gyro, with the innovation's own variance (instead of a fixed angle)
        dt = float(dt_s[k])
        nu = float(wrap_angle_rad(gyro_yaw[k] - inc[2] - state.q[3] * dt))
        S = increment_covariance(inc, cfg)[2, 2] + dt**2 * state.P[3, 3] + gyro_sigma_yaw_rad(inc[2], cfg) ** 2
        if nu**2 > cfg.icp_gyro_gate_chi2 * S:
            inc, fg = wheel_fallback[k], True
    if wheel is None and np.all(np.isfinite(inc)):
        Q = increment_covariance(inc, cfg)
        if dt_s is not None:  # the heading random walk (cfg.heading_rw_rad_per_sqrt_s)
            Q[2, 2] += cfg.heading_rw_rad_per_sqrt_s**2 * float(dt_s[k])
        if len(state.q) == 4:  # with the gyro bias state
            dt = float(dt_s[k])
            g = None if gyro_yaw is None else float(gyro_yaw[k])
            state, Phi = ekf.predict_gyro_bias(state, inc, Q, dt, fg, cfg.gyro_bias_rw_rad_s_per_sqrt_s**2 * dt,
                                               g, gyro_sigma_yaw_rad(inc[2], cfg) ** 2)
            return state, not fg, Phi
        return ekf.predict(state, inc, Q), True, ekf.predict_jacobian(state.q, inc)
    if wheel is None:
        # no ICP edge: inflate as if standing still with a large uncertainty
        inflate = np.diag([1.0, 1.0, np.deg2rad(2.0) ** 2, 0.0][:len(state.q)])
        return ekf.EkfState(state.q, state.P + inflate), False, np.eye(len(state.q))
    dt = float(dt_s[k])
    dist = float(np.hypot(wheel[k, 0], wheel[k, 1]))
    Q_bias = np.diag([cfg.gyro_bias_rw_rad_s_per_sqrt_s**2 * dt, cfg.wheel_scale_rw_per_sqrt_m**2 * dist])
    ok = bool(np.all(np.isfinite(inc)))
    Q_icp = icp_covariance(inc, None if icp_cov is None else icp_cov[k], cfg) if ok else None
    state, chi2, Phi = ekf.predict_wheel_icp_transition(state, wheel[k], dt, wheel_covariance(wheel[k], cfg),
                                                        inc if ok else None, Q_icp, Q_bias, cfg.icp_gate_chi2)
    return state, bool(ok and chi2 <= cfg.icp_gate_chi2), Phi


def run_ekf(increments: np.ndarray, obs: CornerObservations, cmap: CornerMap, q0: np.ndarray, P0: np.ndarray,
            start_epoch: int, cfg: EkfConfig = EkfConfig(), wheel_increments: np.ndarray | None = None,
            stamps_ns: np.ndarray | None = None, icp_cov: np.ndarray | None = None,
            from_gyro: np.ndarray | None = None, gyro_yaw_rad: np.ndarray | None = None,
            wheel_fallback: np.ndarray | None = None, feature_epoch: np.ndarray | None = None,
            features_vehicle_m: np.ndarray | None = None, fetch=None) -> EkfRun:
    """Run the filter from ``start_epoch`` (initialised with q0, P0 there) to the last epoch.

    With ``wheel_increments`` (E,3) and ``stamps_ns`` the state carries the gyro bias and the wheel scale error
    (``ekf.predict_wheel_icp``): ICP increments (NaN = failed; ``icp_cov`` (E,3,3) their registration covariance)
    are fused with the bias-corrected wheel/gyro increments. Without them: the paper's ICP-only motion model; with
    ``cfg.icp_gyro_bias_state``, ``from_gyro`` (E,) (the epochs whose increment is the wheel/gyro one, ICP having
    failed or been gated) and ``stamps_ns``, the state carries the gyro bias those increments drift with.
    With ``cfg.markings``, ``feature_epoch`` (F,) sorted, ``features_vehicle_m`` (F,2) and ``fetch`` (a marking
    raster fetcher, as the MCL's), every scan's road features also measure the pose (``ekf_markings``).
    """
    from scipy.spatial import cKDTree

    n = len(increments)
    q_out = np.full((n, 3), np.nan)
    P_out = np.full((n, 3, 3), np.nan)
    n_assoc = np.zeros(n, dtype=np.int32)
    a_epoch, a_map = [], []
    off = obs.slices(n)
    if cfg.map_cov_scale != 1.0:
        cmap = CornerMap(cmap.en_m, cmap.cov_m2 * cfg.map_cov_scale, cmap.dirs_enu_rad)
    tree = cKDTree(cmap.en_m) if len(cmap.en_m) else None
    floor = np.diag([cfg.range_sigma_floor_m**2, cfg.bearing_sigma_floor_rad**2])
    q_init, P_init = np.asarray(q0, dtype=float).copy(), np.asarray(P0, dtype=float).copy()
    dt_s = None if stamps_ns is None else np.concatenate([[0.0], np.diff(np.asarray(stamps_ns, np.int64)) * 1e-9])
    # extra states beside (x, y, yaw), with their initial variances: the gyro bias, and the wheel scale error
    if wheel_increments is not None:
        extra, needs = [cfg.gyro_bias_sigma_rad_s**2, cfg.wheel_scale_sigma**2], "wheel_increments need"
    elif cfg.icp_gyro_bias_state and from_gyro is not None:
        extra, needs = [cfg.gyro_bias_sigma_rad_s**2], "from_gyro needs"
    else:
        extra, needs = [], ""
    if extra:
        if dt_s is None:
            raise ValueError(f"run_ekf: {needs} stamps_ns")
        q_init = np.concatenate([q_init[:3], np.zeros(len(extra))])
        P_init = np.diag(np.concatenate([np.zeros(3), extra]))
        P_init[:3, :3] = np.asarray(P0, dtype=float)[:3, :3]
    state = ekf.EkfState(q_init, P_init)
    gyro_fused = gyro_yaw_rad if cfg.icp_gyro_fusion else None
    held = consider.empty(len(q_init))
    corr = consider.MapCorrelation(cfg.map_corr_share, cfg.map_corr_length_m)
    n_icp = 0
    marks = _Markings(cfg, feature_epoch, features_vehicle_m, fetch, n) if cfg.markings else None
    if marks is not None and (cfg.marking_map_sigma_m > 0 or cfg.marking_map_sigma_yaw_rad > 0):
        held = consider.with_map_offset(held, len(q_init), np.diag([cfg.marking_map_sigma_m**2,
                                                                   cfg.marking_map_sigma_m**2,
                                                                   cfg.marking_map_sigma_yaw_rad**2]))
    looks = _Looks(cfg.corner_decorrelation_m)
    odometer_m = 0.0
    for k in range(start_epoch, n):
        if k > start_epoch:
            step = _travel_m(increments[k])
            odometer_m += step
            state, used, Phi = _motion(state, k, increments, wheel_increments, dt_s, icp_cov, cfg, from_gyro,
                                       gyro_fused, wheel_fallback)
            held = consider.forget(consider.propagate(held, Phi), state.q, cmap.en_m, cfg.consider_forget_m)
            n_icp += used
            if marks is not None:
                marks.travel += step
                held = consider.decay_map_offset(held, float(np.exp(-step / cfg.marking_map_length_m)))
        lo, hi = off[k], off[k + 1]
        if hi > lo and tree is not None:
            near = np.asarray(tree.query_ball_point(state.q[:2], cfg.sensor_range_m), dtype=np.int64)
            if len(near):
                a = associate(state.q[:3], state.P[:3, :3], obs.xy_vehicle_m[lo:hi], obs.cov_vehicle_m2[lo:hi],
                              obs.dirs_vehicle_rad[lo:hi], cmap.en_m[near],
                              cmap.cov_m2[near], cmap.dirs_enu_rad[near], sensor_range_m=cfg.sensor_range_m,
                              gate_chi2=cfg.gate_chi2, angle_tol_rad=cfg.angle_tol_rad, method=cfg.association,
                              noise_floor_rb=floor)
                if len(a.meas_idx):
                    idx = near[a.map_idx]
                    n_assoc[k] = len(idx)
                    a_epoch.append(np.full(len(idx), k)), a_map.append(idx)
                    alpha = looks.weights(idx, odometer_m)
                    use = alpha >= MIN_LOOK_WEIGHT
                    idx, alpha = idx[use], alpha[use]
                    if len(idx):
                        looks.used(idx, odometer_m)
                        yaw_walls, yaw_sigma = None, 0.0
                        if cfg.wall_heading_sigma_rad > 0:
                            yaw_walls = wall_headings_rad(obs.dirs_vehicle_rad[lo:hi][a.meas_idx[use]],
                                                          cmap.dirs_enu_rad[idx])
                            yaw_sigma = np.repeat(cfg.wall_heading_sigma_rad / np.sqrt(alpha), 2)
                        R_scan = (a.R_blocks - a.R_map_blocks)[use] / alpha[:, None, None]
                        if cfg.map_consider:
                            held, _ = consider.add(held, idx, cmap.cov_m2[idx], cmap.en_m, corr)
                            state, held, _ = consider.update(state, held, a.z_meas[use], idx, cmap.en_m[idx], R_scan,
                                                             yaw_walls, yaw_sigma)
                        else:
                            state, _ = ekf.update(state, a.z_meas[use], cmap.en_m[idx],
                                                  a.R_map_blocks[use] + R_scan, yaw_walls, yaw_sigma)
        if marks is not None:
            state, held = marks.update(k, state, held)
        q_out[k], P_out[k] = state.q[:3], state.P[:3, :3]
    if marks is not None:
        used = marks.rows[marks.rows > 0]
        log.info("ekf: road markings measured the pose at %d epochs (%.1f directions on average), %d gated out",
                 len(used), float(used.mean()) if len(used) else 0.0, int((marks.rows < 0).sum()))
    if wheel_increments is not None:
        log.info("ekf: %d of %d motion updates used ICP; gyro bias at the end %.4f +- %.4f deg/s, wheel scale error "
                 "%.4f +- %.4f", n_icp, n - start_epoch - 1, np.degrees(state.q[3]), np.degrees(np.sqrt(state.P[3, 3])),
                 state.q[4], np.sqrt(state.P[4, 4]))
    cat = (lambda parts: np.concatenate(parts) if parts else np.zeros(0, np.int64))
    return EkfRun(q_out, P_out, n_assoc, cat(a_epoch), cat(a_map), None if marks is None else marks.rows)


MIN_LOOK_WEIGHT = 0.02  # a look weighted less than this is skipped (its travel keeps counting toward the next)


class _Looks:
    """Travel since each map corner last measured the pose; a look's weight is min(1, that travel /
    ``decorrelation_m``) (1 for a corner not seen yet; every look weighs 1 with ``decorrelation_m`` 0)."""

    def __init__(self, decorrelation_m: float):
        self.decorrelation_m = decorrelation_m
        self.last_m: dict[int, float] = {}

    def weights(self, idx: np.ndarray, odometer_m: float) -> np.ndarray:
        if self.decorrelation_m <= 0:
            return np.ones(len(idx))
        since = np.array([odometer_m - self.last_m.get(int(i), -np.inf) for i in idx])
        return np.minimum(1.0, since / self.decorrelation_m)

    def used(self, idx: np.ndarray, odometer_m: float) -> None:
        for i in idx:
            self.last_m[int(i)] = odometer_m


def _travel_m(increment: np.ndarray) -> float:
    """Length of an increment's translation, zero where it is missing."""
    t = np.asarray(increment, dtype=float)[:2]
    return float(np.hypot(*np.where(np.isfinite(t), t, 0.0)))


class _Markings:
    """The EKF's road-marking measurement over a drive (``ekf_markings``): features per epoch, the raster window
    about the vehicle, the travel since the last update (consecutive scans repeat most of their evidence: the
    log-likelihood is tempered by ``min(1, travel / marking_decorrelation_m)``, as the MCL's)."""

    def __init__(self, cfg: EkfConfig, feature_epoch, features_vehicle_m, fetch, n: int):
        if fetch is None or feature_epoch is None or features_vehicle_m is None:
            raise ValueError("run_ekf: cfg.markings needs feature_epoch, features_vehicle_m and fetch")
        from scipy.stats import chi2

        self.cfg, self.fetch = cfg, fetch
        self.feats = np.asarray(features_vehicle_m, dtype=float).reshape(-1, 2)
        self.off = np.searchsorted(np.asarray(feature_epoch), np.arange(n + 1))
        self.raster = None
        self.travel = np.inf  # the first scan is a full measurement
        self.rows = np.zeros(n, dtype=np.int32)
        self.gate = {r: float(chi2.ppf(cfg.marking_gate_probability, r)) for r in (1, 2, 3)}

    def update(self, k: int, state: ekf.EkfState, held: consider.ConsiderSet
               ) -> tuple[ekf.EkfState, consider.ConsiderSet]:
        from stages.evaluate.ekf_markings import marking_measurement

        cfg = self.cfg
        feats = self.feats[self.off[k]:self.off[k + 1]]
        alpha = min(1.0, self.travel / cfg.marking_decorrelation_m) if cfg.marking_decorrelation_m > 0 else 1.0
        if len(feats) < cfg.marking_min_features or alpha <= 0:
            return state, held
        if len(feats) > cfg.marking_max_features:  # evenly spaced, deterministic
            feats = feats[np.linspace(0, len(feats) - 1, cfg.marking_max_features).astype(np.int64)]
        reach = cfg.marking_feature_range_m + 4.0 * float(np.sqrt(np.max(np.diag(state.P)[:2])))
        if self.raster is None or not self.raster.contains(state.q[0] - reach, state.q[1] - reach,
                                                           state.q[0] + reach, state.q[1] + reach):
            half = 0.5 * max(cfg.marking_window_m, 2.0 * reach)
            self.raster = self.fetch(state.q[0] - half, state.q[1] - half, state.q[0] + half, state.q[1] + half)
        if self.raster.observed is not None:
            feats = feats[mcl.observed_features(feats, state.q[:3], self.raster)]
            if len(feats) < cfg.marking_min_features:
                return state, held
        gain = alpha * cfg.marking_sharpness * min(float(len(feats)), cfg.marking_effective_points)
        m = marking_measurement(state.q[:3], state.P[:3, :3], feats, self.raster, gain, cfg.marking_min_info,
                                cfg.marking_grid_n)
        self.travel = 0.0
        r = len(m.innovation)
        if r == 0:
            return state, held
        state, held, chi2 = consider.update_linear(state, held, m.H, m.innovation, m.variance, self.gate[r])
        self.rows[k] = r if chi2 <= self.gate[r] else -1
        return state, held


def dead_reckon(increments: np.ndarray, q0: np.ndarray, start_epoch: int) -> np.ndarray:
    """Chain increments from ``q0`` at ``start_epoch`` (vectorised; missing increments count as zero)."""
    n = len(increments)
    inc = np.where(np.isfinite(increments), increments, 0.0)[start_epoch + 1:]
    out = np.full((n, 3), np.nan)
    yaw = q0[2] + np.concatenate([[0.0], np.cumsum(inc[:, 2])])
    c, s = np.cos(yaw[:-1]), np.sin(yaw[:-1])
    de = c * inc[:, 0] - s * inc[:, 1]
    dn = s * inc[:, 0] + c * inc[:, 1]
    out[start_epoch:, 0] = q0[0] + np.concatenate([[0.0], np.cumsum(de)])
    out[start_epoch:, 1] = q0[1] + np.concatenate([[0.0], np.cumsum(dn)])
    out[start_epoch:, 2] = wrap_angle_rad(yaw)
    return out
