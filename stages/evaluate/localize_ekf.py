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
from stages.evaluate.ekf_params import EkfConfig
from stages.evaluate.mcl_params import MarkingLikelihood

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


def icp_yaw_sigma_rad(cov_info: np.ndarray | None, cfg: EkfConfig) -> float:
    """One ICP increment's heading std: ``cfg.icp.registration_yaw_scale`` times the registration's own stated std
    (``cov_info[2, 2]``, the planar marginal of the edge's information, less the floor odometry adds to every edge,
    ``registration_yaw_floor_deg``) when both are there, else ``cfg.icp.sigma_yaw_deg``. The registration's figure
    follows the scene and the sensor scan by scan (demo's dense facades register 2-3x better in heading than
    tiny's); its scale is not the truth's (the point-to-plane Hessian at a fixed point std ignores the residuals'
    correlation), hence one global factor chosen on calibration seeds."""
    scale = cfg.icp.registration_yaw_scale
    if scale > 0 and cov_info is not None:
        v = float(np.asarray(cov_info)[2, 2])
        if np.isfinite(v) and v > 0:
            return scale * float(np.sqrt(max(v - cfg.icp.registration_yaw_floor_rad**2, 0.0)))
    return cfg.icp.sigma_yaw_rad


def increment_covariance(increment: np.ndarray, cfg: EkfConfig, cov_info: np.ndarray | None = None) -> np.ndarray:
    """Diagonal covariance of one ICP increment, growing with distance and turn; its heading part from the
    registration's own covariance ``cov_info`` (3,3) when given (``icp_yaw_sigma_rad``)."""
    dist = float(np.hypot(increment[0], increment[1]))
    s_xy = cfg.icp.sigma_frac * dist + cfg.icp.sigma_xy_m
    s_yaw = cfg.icp.sigma_yaw_frac * abs(float(increment[2])) + icp_yaw_sigma_rad(cov_info, cfg)
    return np.diag([s_xy**2, s_xy**2, s_yaw**2])


def gyro_sigma_yaw_rad(dyaw_rad: float, cfg: EkfConfig) -> float:
    """The gyro's heading-change std over one step beside its bias: a floor plus a scale error per radian."""
    return cfg.wheel.gyro_sigma_yaw_frac * abs(float(dyaw_rad)) + cfg.wheel.gyro_sigma_yaw_rad


def wheel_covariance(wheel: np.ndarray, cfg: EkfConfig) -> np.ndarray:
    """Covariance (vehicle frame) of a wheel/gyro increment beside its scale and bias (which are states)."""
    dist = float(np.hypot(wheel[0], wheel[1]))
    s_along = cfg.wheel.sigma_frac * dist + cfg.wheel.sigma_xy_m
    s_lat = cfg.wheel.sigma_lateral_frac * dist + cfg.wheel.sigma_xy_m
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
    own = None if icp_cov is None or fg else icp_cov[k]  # the registration's covariance of an ICP increment
    if (len(state.q) == 4 and wheel_fallback is not None and not fg and gyro_yaw is not None
            and cfg.icp.gyro_gate_chi2 > 0 and np.all(np.isfinite(inc))):
        # ICP against the bias-corrected gyro, with the innovation's own variance (instead of a fixed angle)
        dt = float(dt_s[k])
        nu = float(wrap_angle_rad(gyro_yaw[k] - inc[2] - state.q[3] * dt))
        S = increment_covariance(inc, cfg, own)[2, 2] + dt**2 * state.P[3, 3] + gyro_sigma_yaw_rad(inc[2], cfg) ** 2
        if nu**2 > cfg.icp.gyro_gate_chi2 * S:
            inc, fg, own = wheel_fallback[k], True, None
    if wheel is None and np.all(np.isfinite(inc)):
        Q = increment_covariance(inc, cfg, own)
        if dt_s is not None:  # the heading random walk (cfg.icp.heading_rw_rad_per_sqrt_s)
            Q[2, 2] += cfg.icp.heading_rw_rad_per_sqrt_s**2 * float(dt_s[k])
        if len(state.q) == 4:  # with the gyro bias state
            dt = float(dt_s[k])
            g = None if gyro_yaw is None else float(gyro_yaw[k])
            state, Phi = ekf.predict_gyro_bias(state, inc, Q, dt, fg, cfg.wheel.gyro_bias_rw_rad_s_per_sqrt_s**2 * dt,
                                               g, gyro_sigma_yaw_rad(inc[2], cfg) ** 2)
            return state, not fg, Phi
        return ekf.predict(state, inc, Q), True, ekf.predict_jacobian(state.q, inc)
    if wheel is None:
        # no ICP edge: inflate as if standing still with a large uncertainty
        inflate = np.diag([1.0, 1.0, np.deg2rad(2.0) ** 2, 0.0][:len(state.q)])
        return ekf.EkfState(state.q, state.P + inflate), False, np.eye(len(state.q))
    dt = float(dt_s[k])
    dist = float(np.hypot(wheel[k, 0], wheel[k, 1]))
    Q_bias = np.diag([cfg.wheel.gyro_bias_rw_rad_s_per_sqrt_s**2 * dt, cfg.wheel.scale_rw_per_sqrt_m**2 * dist])
    ok = bool(np.all(np.isfinite(inc)))
    Q_icp = icp_covariance(inc, None if icp_cov is None else icp_cov[k], cfg) if ok else None
    state, chi2, Phi = ekf.predict_wheel_icp_transition(state, wheel[k], dt, wheel_covariance(wheel[k], cfg),
                                                        inc if ok else None, Q_icp, Q_bias, cfg.icp.gate_chi2)
    return state, bool(ok and chi2 <= cfg.icp.gate_chi2), Phi


def run_ekf(increments: np.ndarray, obs: CornerObservations, cmap: CornerMap, q0: np.ndarray, P0: np.ndarray,
            start_epoch: int, cfg: EkfConfig = EkfConfig(), wheel_increments: np.ndarray | None = None,
            stamps_ns: np.ndarray | None = None, icp_cov: np.ndarray | None = None,
            from_gyro: np.ndarray | None = None, gyro_yaw_rad: np.ndarray | None = None,
            wheel_fallback: np.ndarray | None = None, feature_epoch: np.ndarray | None = None,
            features_vehicle_m: np.ndarray | None = None, fetch=None,
            likelihood: MarkingLikelihood = MarkingLikelihood()) -> EkfRun:
    """Run the filter from ``start_epoch`` (initialised with q0, P0 there) to the last epoch.

    With ``wheel_increments`` (E,3) and ``stamps_ns`` the state carries the gyro bias and the wheel scale error
    (``ekf.predict_wheel_icp``): ICP increments (NaN = failed; ``icp_cov`` (E,3,3) their registration covariance)
    are fused with the bias-corrected wheel/gyro increments. Without them: the paper's ICP-only motion model; with
    ``cfg.icp.gyro_bias_state``, ``from_gyro`` (E,) (the epochs whose increment is the wheel/gyro one, ICP having
    failed or been gated) and ``stamps_ns``, the state carries the gyro bias those increments drift with; ``icp_cov``
    then gives each ICP increment's heading std (``icp_yaw_sigma_rad``).
    With ``cfg.markings.enabled``, ``feature_epoch`` (F,) sorted, ``features_vehicle_m`` (F,2) and ``fetch`` (a
    marking raster fetcher, as the MCL's), every scan's road features also measure the pose (``ekf_markings``) with the
    MCL's ``likelihood``.
    """
    from scipy.spatial import cKDTree

    n = len(increments)
    q_out = np.full((n, 3), np.nan)
    P_out = np.full((n, 3, 3), np.nan)
    n_assoc = np.zeros(n, dtype=np.int32)
    a_epoch, a_map = [], []
    off = obs.slices(n)
    if cfg.map.cov_scale != 1.0:
        cmap = CornerMap(cmap.en_m, cmap.cov_m2 * cfg.map.cov_scale, cmap.dirs_enu_rad)
    tree = cKDTree(cmap.en_m) if len(cmap.en_m) else None
    floor = np.diag([cfg.corners.range_sigma_floor_m**2, cfg.corners.bearing_sigma_floor_rad**2])
    # until the first corner update: the start-up floors (a start from a fix metres off linearises badly)
    startup = np.maximum(floor, np.diag([cfg.corners.startup_range_sigma_floor_m**2,
                                         cfg.corners.startup_bearing_sigma_floor_rad**2]))
    localized = False
    q_init, P_init = np.asarray(q0, dtype=float).copy(), np.asarray(P0, dtype=float).copy()
    dt_s = None if stamps_ns is None else np.concatenate([[0.0], np.diff(np.asarray(stamps_ns, np.int64)) * 1e-9])
    # extra states beside (x, y, yaw), with their initial variances: the gyro bias, and the wheel scale error
    if wheel_increments is not None:
        extra, needs = [cfg.wheel.gyro_bias_sigma_rad_s**2, cfg.wheel.scale_sigma**2], "wheel_increments need"
    elif cfg.icp.gyro_bias_state and from_gyro is not None:
        extra, needs = [cfg.wheel.gyro_bias_sigma_rad_s**2], "from_gyro needs"
    else:
        extra, needs = [], ""
    if extra:
        if dt_s is None:
            raise ValueError(f"run_ekf: {needs} stamps_ns")
        q_init = np.concatenate([q_init[:3], np.zeros(len(extra))])
        P_init = np.diag(np.concatenate([np.zeros(3), extra]))
        P_init[:3, :3] = np.asarray(P0, dtype=float)[:3, :3]
    state = ekf.EkfState(q_init, P_init)
    gyro_fused = gyro_yaw_rad if cfg.icp.gyro_fusion else None
    held = consider.empty(len(q_init))
    corr = consider.MapCorrelation(cfg.map.corr_share, cfg.map.corr_length_m)
    n_icp = 0
    marks = _Markings(cfg, likelihood, feature_epoch, features_vehicle_m, fetch, n) if cfg.markings.enabled else None
    if marks is not None and (cfg.markings.map_sigma_m > 0 or cfg.markings.map_sigma_yaw_rad > 0):
        held = consider.with_map_offset(held, len(q_init), np.diag([cfg.markings.map_sigma_m**2,
                                                                   cfg.markings.map_sigma_m**2,
                                                                   cfg.markings.map_sigma_yaw_rad**2]))
    looks = _Looks(cfg.corners.decorrelation_m)
    odometer_m = 0.0
    for k in range(start_epoch, n):
        if k > start_epoch:
            step = _travel_m(increments[k])
            odometer_m += step
            state, used, Phi = _motion(state, k, increments, wheel_increments, dt_s, icp_cov, cfg, from_gyro,
                                       gyro_fused, wheel_fallback)
            held = consider.forget(consider.propagate(held, Phi), state.q, cmap.en_m, cfg.map.consider_forget_m)
            n_icp += used
            if marks is not None:
                marks.travel += step
                held = consider.decay_map_offset(held, float(np.exp(-step / cfg.markings.map_length_m)))
        lo, hi = off[k], off[k + 1]
        if hi > lo and tree is not None:
            near = np.asarray(tree.query_ball_point(state.q[:2], cfg.corners.sensor_range_m), dtype=np.int64)
            if len(near):
                a = associate(state.q[:3], state.P[:3, :3], obs.xy_vehicle_m[lo:hi], obs.cov_vehicle_m2[lo:hi],
                              obs.dirs_vehicle_rad[lo:hi], cmap.en_m[near],
                              cmap.cov_m2[near], cmap.dirs_enu_rad[near], sensor_range_m=cfg.corners.sensor_range_m,
                              gate_chi2=cfg.corners.gate_chi2, angle_tol_rad=cfg.corners.angle_tol_rad,
                              method=cfg.corners.association,
                              noise_floor_rb=floor if localized else startup)
                if len(a.meas_idx):
                    idx = near[a.map_idx]
                    n_assoc[k] = len(idx)
                    a_epoch.append(np.full(len(idx), k)), a_map.append(idx)
                    alpha = looks.weights(idx, odometer_m)
                    use = alpha >= MIN_LOOK_WEIGHT
                    idx, alpha = idx[use], alpha[use]
                    if len(idx):
                        localized = True
                        looks.used(idx, odometer_m)
                        yaw_walls, yaw_sigma = None, 0.0
                        if cfg.corners.wall_heading_sigma_rad > 0:
                            yaw_walls = wall_headings_rad(obs.dirs_vehicle_rad[lo:hi][a.meas_idx[use]],
                                                          cmap.dirs_enu_rad[idx])
                            yaw_sigma = np.repeat(cfg.corners.wall_heading_sigma_rad / np.sqrt(alpha), 2)
                        R_scan = (a.R_blocks - a.R_map_blocks)[use] / alpha[:, None, None]
                        if cfg.map.consider:
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

    def __init__(self, cfg: EkfConfig, likelihood: MarkingLikelihood, feature_epoch, features_vehicle_m, fetch,
                 n: int):
        if fetch is None or feature_epoch is None or features_vehicle_m is None:
            raise ValueError("run_ekf: the marking update needs feature_epoch, features_vehicle_m and fetch")
        from scipy.stats import chi2

        self.cfg, self.lk, self.fetch = cfg, likelihood, fetch
        self.feats = np.asarray(features_vehicle_m, dtype=float).reshape(-1, 2)
        self.off = np.searchsorted(np.asarray(feature_epoch), np.arange(n + 1))
        self.raster = None
        self.travel = np.inf  # the first scan is a full measurement
        self.rows = np.zeros(n, dtype=np.int32)
        self.gate = {r: float(chi2.ppf(cfg.markings.gate_probability, r)) for r in (1, 2, 3)}

    def update(self, k: int, state: ekf.EkfState, held: consider.ConsiderSet
               ) -> tuple[ekf.EkfState, consider.ConsiderSet]:
        from stages.evaluate.ekf_markings import marking_measurement

        cfg, lk = self.cfg, self.lk
        feats = self.feats[self.off[k]:self.off[k + 1]]
        alpha = min(1.0, self.travel / lk.decorrelation_m) if lk.decorrelation_m > 0 else 1.0
        if len(feats) < cfg.markings.min_features or alpha <= 0:
            return state, held
        if len(feats) > lk.max_features:  # evenly spaced, deterministic
            feats = feats[np.linspace(0, len(feats) - 1, lk.max_features).astype(np.int64)]
        reach = lk.feature_range_m + 4.0 * float(np.sqrt(np.max(np.diag(state.P)[:2])))
        if self.raster is None or not self.raster.contains(state.q[0] - reach, state.q[1] - reach,
                                                           state.q[0] + reach, state.q[1] + reach):
            half = 0.5 * max(cfg.markings.window_m, 2.0 * reach)
            self.raster = self.fetch(state.q[0] - half, state.q[1] - half, state.q[0] + half, state.q[1] + half)
        if self.raster.observed is not None:
            feats = feats[mcl.observed_features(feats, state.q[:3], self.raster)]
            if len(feats) < cfg.markings.min_features:
                return state, held
        gain = alpha * lk.sharpness * min(float(len(feats)), lk.effective_points)
        m = marking_measurement(state.q[:3], state.P[:3, :3], feats, self.raster, gain, cfg.markings.min_info,
                                cfg.markings.grid_n)
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
