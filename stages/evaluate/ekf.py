"""Extended Kalman filter on (x, y, yaw) with range/bearing updates to map corners (Im et al. 2016 s.4).

State ``q = (x_m, y_m, yaw_rad)``: the vehicle reference point in the map's ENU frame and its heading
(counter-clockwise from east). Pure numpy; every function returns new arrays.

Motion (eq. 2): ``q_{k+1} = q_k + G(yaw_k) u_k`` with ``u = (dx, dy, dyaw)`` the ICP increment expressed in the
previous vehicle frame. The paper writes ``F = I``; the exact linearisation keeps the heading column
``dG/dyaw u`` so that the covariance grows with heading uncertainty (needed for a consistent NEES).
``predict_wheel_icp`` is the alternative motion model of the 5-state filter (gyro bias and wheel scale as states,
the wheel/gyro increment as the prior, the ICP increment with its registration covariance as a measurement of it);
the measurement updates below work on either state size (the corners observe the first three states).

Measurement (eqs. 3-5): for each associated corner i, ``r_i = |p_i - p|`` and
``alpha_i = atan2(y_i - y, x_i - x) - yaw``; the rows of ``H`` follow eq. (5).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.common.geometry import wrap_angle_rad


@dataclass(frozen=True)
class EkfState:
    q: np.ndarray  # (3,) x_m, y_m, yaw_rad in ENU
    P: np.ndarray  # (3, 3)


def rotation_2d(yaw_rad: float) -> np.ndarray:
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s], [s, c]])


def predict(state: EkfState, increment: np.ndarray, Q: np.ndarray) -> EkfState:
    """Motion update with an increment ``(dx_m, dy_m, dyaw_rad)`` in the previous vehicle frame.

    ``Q`` (3x3) is the increment's covariance in that same vehicle frame; it is rotated into ENU by G.
    """
    x, y, yaw = state.q
    dx, dy, dyaw = np.asarray(increment, dtype=float)
    c, s = np.cos(yaw), np.sin(yaw)
    G = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    F = predict_jacobian(state.q, increment)
    q = np.array([x + c * dx - s * dy, y + s * dx + c * dy, float(wrap_angle_rad(yaw + dyaw))])
    P = F @ state.P @ F.T + G @ Q @ G.T
    return EkfState(q, 0.5 * (P + P.T))


def predict_jacobian(q: np.ndarray, increment: np.ndarray) -> np.ndarray:
    """(3,3) Jacobian of ``predict``'s new pose with respect to the old one (the state transition of the errors)."""
    dx, dy = float(increment[0]), float(increment[1])
    c, s = np.cos(q[2]), np.sin(q[2])
    return np.array([[1.0, 0.0, -s * dx - c * dy], [0.0, 1.0, c * dx - s * dy], [0.0, 0.0, 1.0]])


def predict_gyro_bias(state: EkfState, increment: np.ndarray, Q: np.ndarray, dt_s: float, from_gyro: bool,
                      q_bias_rad2_s2: float, gyro_yaw_rad: float | None = None, gyro_var_rad2: float = 0.0
                      ) -> tuple[EkfState, np.ndarray]:
    """Motion update of the 4-state filter ``(x, y, yaw, gyro_bias_rad_s)`` of the ICP motion model.

    The true increment ``d`` is a latent. A wheel/gyro increment (ICP failed or was gated, ``from_gyro``) gives
    ``d = increment - (0, 0, b dt) + w``, ``w ~ N(0, Q)``: its heading carries the gyro's bias, so the heading error
    of a run of such increments grows with the bias's uncertainty times the time, not with the square root of the
    number of increments as white noise would. An ICP increment gives ``d = increment + w``; when ``gyro_yaw_rad``
    (the gyro's heading change over the step) is given it also measures ``d``: ``gyro = d_yaw + b dt + v``,
    ``v ~ N(0, gyro_var_rad2)``, which estimates the bias while ICP holds. The pose is then composed with ``d``.
    ``q_bias_rad2_s2`` is the bias random walk's variance over the step. Returns the state and the (4,4) transition
    of the errors (for ``consider``)."""
    q, P = state.q, state.P
    inc = np.asarray(increment, dtype=float).copy()
    if from_gyro:
        inc[2] -= q[3] * dt_s
    X = np.concatenate([q, inc])
    J = np.zeros((3, 4))  # d(d)/d(state)
    if from_gyro:
        J[2, 3] = -dt_s
    PA = np.zeros((7, 7))
    PA[:4, :4] = P
    PA[:4, 4:] = P @ J.T
    PA[4:, :4] = J @ P
    PA[4:, 4:] = J @ P @ J.T + np.asarray(Q, dtype=float)
    M = np.eye(7)
    if not from_gyro and gyro_yaw_rad is not None and np.isfinite(gyro_yaw_rad):
        H = np.zeros(7)
        H[3], H[6] = dt_s, 1.0
        S = float(H @ PA @ H) + gyro_var_rad2
        K = PA @ H / S
        X = X + K * float(wrap_angle_rad(gyro_yaw_rad - X[6] - X[3] * dt_s))
        M = np.eye(7) - np.outer(K, H)
        PA = M @ PA @ M.T + np.outer(K, K) * gyro_var_rad2
    x, y, yaw, b = X[:4]
    dx, dy, dyaw = X[4:]
    c, s = np.cos(yaw), np.sin(yaw)
    A = np.zeros((4, 7))
    A[:3, :3] = [[1.0, 0.0, -s * dx - c * dy], [0.0, 1.0, c * dx - s * dy], [0.0, 0.0, 1.0]]
    A[:3, 4:] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    A[3, 3] = 1.0
    q_new = np.array([x + c * dx - s * dy, y + s * dx + c * dy, float(wrap_angle_rad(yaw + dyaw)), b])
    P_new = A @ PA @ A.T
    P_new[3, 3] += q_bias_rad2_s2
    Phi = A @ M @ np.vstack([np.eye(4), J])
    return EkfState(q_new, 0.5 * (P_new + P_new.T)), Phi


def predict_wheel_icp(state: EkfState, wheel: np.ndarray, dt_s: float, Q_wheel: np.ndarray,
                      icp: np.ndarray | None, Q_icp: np.ndarray | None, Q_bias: np.ndarray,
                      gate_chi2: float) -> tuple[EkfState, float]:
    """``predict_wheel_icp_transition`` without the transition matrix."""
    new, chi2, _ = predict_wheel_icp_transition(state, wheel, dt_s, Q_wheel, icp, Q_icp, Q_bias, gate_chi2)
    return new, chi2


def predict_wheel_icp_transition(state: EkfState, wheel: np.ndarray, dt_s: float, Q_wheel: np.ndarray,
                                 icp: np.ndarray | None, Q_icp: np.ndarray | None, Q_bias: np.ndarray,
                                 gate_chi2: float) -> tuple[EkfState, float, np.ndarray]:
    """Motion update of the 5-state filter ``(x, y, yaw, gyro_bias_rad_s, wheel_scale_err)``.

    The true increment ``d`` (vehicle frame of the previous epoch) is a latent with the wheel/gyro prior
    ``d = ((1 - s) dx_w, (1 - s) dy_w, dyaw_w - b dt) + w``, ``w ~ N(0, Q_wheel)``; an ICP increment, when given,
    measures it, ``icp = d + v``, ``v ~ N(0, Q_icp)`` (``Q_icp`` from the registration's own information, so a
    degenerate direction weighs nothing). The update of the augmented state ``(q, b, s, d)`` estimates the gyro bias
    and the wheel scale while ICP agrees with the wheels; an ICP increment whose innovation exceeds ``gate_chi2``
    (3 dof) is not used. The pose is then composed with ``d``. ``Q_bias`` (2x2) is the random walk of (b, s) over
    the step. Returns the new state, the ICP innovation's chi-square (NaN without ICP) and the (5,5) transition of
    the state's errors (for cross-covariances with states kept outside, e.g. ``consider``).
    """
    q, P = state.q, state.P
    dx_w, dy_w, dyaw_w = np.asarray(wheel, dtype=float)
    b, sc = q[3], q[4]
    d = np.array([(1.0 - sc) * dx_w, (1.0 - sc) * dy_w, dyaw_w - b * dt_s])
    J = np.zeros((3, 5))  # d(d)/d(state)
    J[0, 4], J[1, 4], J[2, 3] = -dx_w, -dy_w, -dt_s
    X = np.concatenate([q, d])
    PA = np.zeros((8, 8))
    PA[:5, :5] = P
    PA[:5, 5:] = P @ J.T
    PA[5:, :5] = J @ P
    PA[5:, 5:] = J @ P @ J.T + Q_wheel
    chi2 = float("nan")
    M = np.eye(8)  # the ICP update's action on the augmented errors
    if icp is not None and np.all(np.isfinite(icp)) and Q_icp is not None:
        nu = np.asarray(icp, dtype=float) - d
        nu[2] = wrap_angle_rad(nu[2])
        S = PA[5:, 5:] + Q_icp
        chi2 = float(nu @ np.linalg.solve(S, nu))
        if chi2 <= gate_chi2:
            K = np.linalg.solve(S, PA[5:, :]).T  # PA H^T S^-1 with H = [0 | I3]
            X = X + K @ nu
            I_KH = np.eye(8)
            I_KH[:, 5:] -= K
            PA = I_KH @ PA @ I_KH.T + K @ Q_icp @ K.T
            M = I_KH
    x, y, yaw = X[:3]
    dx, dy, dyaw = X[5:]
    c, s = np.cos(yaw), np.sin(yaw)
    A = np.zeros((5, 8))
    A[:3, :3] = [[1.0, 0.0, -s * dx - c * dy], [0.0, 1.0, c * dx - s * dy], [0.0, 0.0, 1.0]]
    A[:3, 5:] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    A[3, 3] = A[4, 4] = 1.0
    q_new = np.array([x + c * dx - s * dy, y + s * dx + c * dy, float(wrap_angle_rad(yaw + dyaw)), X[3], X[4]])
    P_new = A @ PA @ A.T
    P_new[3:, 3:] += Q_bias
    Phi = A @ M @ np.vstack([np.eye(5), J])
    return EkfState(q_new, 0.5 * (P_new + P_new.T)), chi2, Phi


def predict_range_bearing(q: np.ndarray, corners_en_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Predicted (range_m, bearing_rad) of map corners (N,2) and the stacked Jacobian H (2N, 3), eq. (5).

    Rows alternate range, bearing per corner. Bearing is in the vehicle frame, wrapped to [-pi, pi).
    """
    d = np.asarray(corners_en_m, dtype=float).reshape(-1, 2) - q[:2]
    r2 = np.maximum(np.einsum("ij,ij->i", d, d), 1e-12)
    r = np.sqrt(r2)
    z = np.empty((len(d), 2))
    z[:, 0] = r
    z[:, 1] = wrap_angle_rad(np.arctan2(d[:, 1], d[:, 0]) - q[2])
    H = np.zeros((len(d), 2, 3))
    H[:, 0, 0] = -d[:, 0] / r
    H[:, 0, 1] = -d[:, 1] / r
    H[:, 1, 0] = d[:, 1] / r2
    H[:, 1, 1] = -d[:, 0] / r2
    H[:, 1, 2] = -1.0
    return z, H.reshape(-1, 3)


def map_corner_jacobian(H: np.ndarray) -> np.ndarray:
    """(2N, 3) vehicle Jacobian -> (N, 2, 2) Jacobians of each (range, bearing) w.r.t. its corner's (e, n)."""
    return -H[:, :2].reshape(-1, 2, 2)


def update(state: EkfState, z_meas: np.ndarray, corners_en_m: np.ndarray, R_blocks: np.ndarray,
           yaw_meas_rad: np.ndarray | None = None, yaw_sigma_rad: float | np.ndarray = 0.0
           ) -> tuple[EkfState, np.ndarray]:
    """Measurement update with N associated corners (eqs. 3-5), Joseph form.

    ``z_meas`` (N,2) measured range/bearing; ``corners_en_m`` (N,2) associated map corners; ``R_blocks``
    (N,2,2) the total measurement noise per corner (extraction + map-corner covariance in range/bearing).
    Optional direct heading measurements ``yaw_meas_rad`` (M,) with std ``yaw_sigma_rad`` (one for all, or (M,)
    one each) are stacked below.
    Returns the updated state and the stacked innovation (2N+M,).
    """
    z_meas = np.asarray(z_meas, dtype=float).reshape(-1, 2)
    yaw_meas = np.zeros(0) if yaw_meas_rad is None else np.asarray(yaw_meas_rad, dtype=float).reshape(-1)
    n, m = len(z_meas), len(yaw_meas)
    if n + m == 0:
        return state, np.zeros(0)
    z_pred, H_rb = predict_range_bearing(state.q, np.asarray(corners_en_m, dtype=float).reshape(-1, 2))
    nu_rb = z_meas - z_pred
    nu_rb[:, 1] = wrap_angle_rad(nu_rb[:, 1])
    H = np.zeros((2 * n + m, len(state.q)))
    H[:2 * n, :3] = H_rb
    H[2 * n:, 2] = 1.0
    nu = np.concatenate([nu_rb.reshape(-1), wrap_angle_rad(yaw_meas - state.q[2])])
    R = np.zeros((2 * n + m, 2 * n + m))
    idx = np.arange(n) * 2
    R[idx[:, None, None] + np.arange(2)[None, :, None], idx[:, None, None] + np.arange(2)[None, None, :]] = R_blocks
    R[np.arange(2 * n, 2 * n + m), np.arange(2 * n, 2 * n + m)] = yaw_sigma_rad**2
    PHt = state.P @ H.T
    S = H @ PHt + R
    K = np.linalg.solve(S, PHt.T).T  # P H^T S^-1 (S, P symmetric)
    q = state.q + K @ nu
    q[2] = wrap_angle_rad(q[2])
    I_KH = np.eye(len(q)) - K @ H
    P = I_KH @ state.P @ I_KH.T + K @ R @ K.T
    return EkfState(q, 0.5 * (P + P.T)), nu


def update_heading(state: EkfState, yaw_meas_rad: np.ndarray, sigma_rad: float) -> EkfState:
    """Linear update with direct heading measurements (N,), e.g. from wall directions, Joseph form."""
    yaw_meas = np.asarray(yaw_meas_rad, dtype=float).reshape(-1)
    if len(yaw_meas) == 0:
        return state
    H = np.zeros((len(yaw_meas), len(state.q)))
    H[:, 2] = 1.0
    R = np.eye(len(yaw_meas)) * sigma_rad**2
    nu = wrap_angle_rad(yaw_meas - state.q[2])
    S = H @ state.P @ H.T + R
    K = np.linalg.solve(S, H @ state.P).T
    q = state.q + K @ nu
    q[2] = wrap_angle_rad(q[2])
    I_KH = np.eye(len(q)) - K @ H
    P = I_KH @ state.P @ I_KH.T + K @ R @ K.T
    return EkfState(q, 0.5 * (P + P.T))


def nees(q_est: np.ndarray, P: np.ndarray, q_ref: np.ndarray) -> np.ndarray:
    """Normalised estimation error squared per epoch: (M,3) estimates, (M,3,3) covariances, (M,3) reference."""
    e = np.asarray(q_est, dtype=float) - np.asarray(q_ref, dtype=float)
    e[:, 2] = wrap_angle_rad(e[:, 2])
    return np.einsum("ij,ij->i", e, np.linalg.solve(P, e[:, :, None])[:, :, 0])


def nees_band(n_epochs: float, dof: int = 3, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided chi-square band of the mean NEES over ``n_epochs`` independent epochs (a float: an effective
    number of epochs, ``effective_epochs``, when consecutive epochs are correlated)."""
    from scipy.stats import chi2

    if not n_epochs or n_epochs <= 0:
        return float("nan"), float("nan")
    a = (1.0 - confidence) / 2.0
    k = dof * n_epochs
    return float(chi2.ppf(a, k) / n_epochs), float(chi2.ppf(1.0 - a, k) / n_epochs)


def integrated_autocorr_time(x: np.ndarray, window_c: float = 5.0) -> float:
    """Integrated autocorrelation time ``tau = 1 + 2 sum_k rho_k`` of a series (in samples), with Sokal's automatic
    window: the sum stops at the first lag ``M >= window_c * tau(M)`` (the estimator of emcee's
    ``autocorr.integrated_time`` and of Sokal 1997). ``N / tau`` independent samples carry the information of the
    ``N`` correlated ones. Floored at 1 (an anti-correlated series is not counted as more than its samples); 1 for
    fewer than 2 samples or a constant series."""
    x = np.asarray(x, dtype=float)
    n = len(x)
    if n < 2:
        return 1.0
    d = x - x.mean()
    f = np.fft.rfft(d, n=2 * n)  # zero-padded: the linear (not circular) autocovariance
    acov = np.fft.irfft(f * np.conj(f))[:n]
    if acov[0] <= 0:
        return 1.0
    taus = 2.0 * np.cumsum(acov / acov[0]) - 1.0  # tau(M) = 1 + 2 sum_{k=1..M} rho_k
    m = np.arange(n) >= window_c * taus
    tau = taus[int(np.argmax(m))] if m.any() else taus[-1]
    return float(max(tau, 1.0))


def effective_epochs(nees_series: np.ndarray) -> float:
    """The number of independent epochs a NEES series (in time order) is worth: ``N / integrated_autocorr_time``.
    An EKF's consecutive errors are correlated (the same map corners, the same drift), so the mean NEES spreads
    far wider than the chi-square band of ``N`` independent epochs (``nees_band``) says."""
    n = len(nees_series)
    return n / integrated_autocorr_time(nees_series) if n else 0.0
