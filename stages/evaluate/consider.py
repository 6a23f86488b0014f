"""Map-corner errors as Schmidt-Kalman "consider" states of the corner EKF.

A map corner's position error is fixed for the whole drive: every epoch that associates the corner sees the same
error. Counted as fresh measurement noise at every epoch (``R = extraction + J C J^T``, eqs. 3-5 with the map
covariance), it is averaged away: the filter's covariance shrinks below the error it carries (position NEES above
its band at corner epochs). The Schmidt-Kalman filter keeps the errors ``c_k ~ N(0, C_k)`` of the corners it has
used beside the vehicle state: ``C`` (the map's stored 2x2 covariances) is never updated (the map is not
re-estimated) and the state is not corrected along it, but the cross-covariance ``P_xc`` between the vehicle
errors and the corner errors is propagated through the motion and updated with every measurement, so a second look
at a corner knows how much of its error the estimate already holds. A corner farther than ``forget_m`` from the
vehicle leaves the set (its correlation is forgotten; seen again, it starts fresh).

Map corners' errors are not independent of one another: corners observed from the same stretch of a survey drive
share its pose error (demo seeds: residual vectors against the truth correlate by about 0.6 within 40 m). With
``MapCorrelation`` the joint covariance of the held corners is ``Cov(c_i, c_j) = k(d_ij) S_i S_j`` (``S`` the
symmetric square root of a corner's stored 2x2, ``k(d) = share exp(-d^2 / (2 length_m^2))`` off the diagonal, 1 on
it: the squared-exponential kernel is positive definite, so the joint covariance is too; it is the shape the demo
maps' residuals show, flat to ~40 m, then falling). A corner joining the set
gets its cross-covariance with the vehicle from the held ones it correlates with (the vehicle's error depends on
the map only through them: ``P_x,new = P_xM C_MM^-1 C_M,new``).
Pure numpy, new arrays out.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from stages.common.geometry import wrap_angle_rad
from stages.evaluate.ekf import EkfState, map_corner_jacobian, predict_range_bearing


@dataclass(frozen=True)
class MapCorrelation:
    """Correlation of two map corners' errors at distance d: ``share * exp(-d^2 / (2 length_m^2))`` (share 0:
    none)."""

    share: float = 0.0
    length_m: float = 50.0

    def kernel(self, d_m: np.ndarray) -> np.ndarray:
        return self.share * np.exp(-0.5 * (np.asarray(d_m, float) / self.length_m) ** 2)


@dataclass(frozen=True)
class ConsiderSet:
    idx: np.ndarray  # (m,) map-corner rows held
    P_xc: np.ndarray  # (n, 2m) cross-covariance of the vehicle state errors and the corners' (e, n) errors
    C: np.ndarray  # (m, 2, 2) the corners' own covariances (constant)
    Cf: np.ndarray | None = None  # (2m, 2m) their joint covariance (None: block diagonal of C)
    # The marking raster's local offset (x, y, yaw) as a consider parameter (``with_map_offset``; measured through
    # ``update_linear``): the cross-covariance (n, 3) with the vehicle errors and its own covariance (3, 3); None:
    # not held.
    P_xm: np.ndarray | None = None
    Cm: np.ndarray | None = None

    def joint(self) -> np.ndarray:
        if self.Cf is not None:
            return self.Cf
        m = len(self.idx)
        out = np.zeros((2 * m, 2 * m))
        for j, p in enumerate(self.C):
            out[2 * j:2 * j + 2, 2 * j:2 * j + 2] = p
        return out


def empty(n_state: int) -> ConsiderSet:
    return ConsiderSet(np.zeros(0, np.int64), np.zeros((n_state, 0)), np.zeros((0, 2, 2)))


def _sqrt_spd(C: np.ndarray) -> np.ndarray:
    """(m,2,2) symmetric square roots of SPD 2x2 matrices."""
    w, V = np.linalg.eigh(C)
    return np.einsum("mij,mj,mkj->mik", V, np.sqrt(np.clip(w, 0.0, None)), V)


def _cross(S_a: np.ndarray, en_a: np.ndarray, S_b: np.ndarray, en_b: np.ndarray, corr: MapCorrelation,
           same: bool = False) -> np.ndarray:
    """(2a, 2b) covariance between corner sets a and b: k(d_ij) S_i S_j (the own blocks, with ``same``, C_i)."""
    d = np.linalg.norm(en_a[:, None, :] - en_b[None, :, :], axis=2)
    k = corr.kernel(d)
    if same:
        np.fill_diagonal(k, 1.0)
    blocks = k[:, :, None, None] * np.einsum("aij,bjk->abik", S_a, S_b)
    return blocks.transpose(0, 2, 1, 3).reshape(2 * len(en_a), 2 * len(en_b))


def propagate(cs: ConsiderSet, Phi: np.ndarray) -> ConsiderSet:
    """Motion: the corners do not move, the vehicle errors go through their transition ``Phi`` (n, n)."""
    return replace(cs, P_xc=Phi @ cs.P_xc, P_xm=None if cs.P_xm is None else Phi @ cs.P_xm)


def forget(cs: ConsiderSet, xy_m: np.ndarray, corners_en_m: np.ndarray, forget_m: float) -> ConsiderSet:
    """Drop the corners farther than ``forget_m`` from the vehicle position ``xy_m``."""
    if len(cs.idx) == 0:
        return cs
    keep = np.hypot(*(corners_en_m[cs.idx] - np.asarray(xy_m)[:2]).T) <= forget_m
    cols = np.repeat(keep, 2)
    Cf = None if cs.Cf is None else cs.Cf[np.ix_(cols, cols)]
    return replace(cs, idx=cs.idx[keep], P_xc=cs.P_xc[:, cols], C=cs.C[keep], Cf=Cf)


def add(cs: ConsiderSet, idx: np.ndarray, C_blocks: np.ndarray, corners_en_m: np.ndarray | None = None,
        corr: MapCorrelation | None = None) -> tuple[ConsiderSet, np.ndarray]:
    """Add the corners not yet held; returns the set and each given corner's position in it. Without a
    correlation (``corr`` None or share 0) a new corner has no correlation with the vehicle or the held corners;
    with one, ``corners_en_m`` (the whole map's (K,2) positions) places them for the kernel."""
    idx = np.asarray(idx, dtype=np.int64)
    new = ~np.isin(idx, cs.idx)
    held = cs
    if new.any():
        n = cs.P_xc.shape[0]
        C_new = np.asarray(C_blocks, float).reshape(-1, 2, 2)[new]
        if corr is None or corr.share <= 0.0:
            held = replace(cs, idx=np.concatenate([cs.idx, idx[new]]),
                           P_xc=np.hstack([cs.P_xc, np.zeros((n, 2 * int(new.sum())))]),
                           C=np.concatenate([cs.C, C_new]), Cf=None)
        else:
            en = np.asarray(corners_en_m, float)
            S_old, S_new = _sqrt_spd(cs.C), _sqrt_spd(C_new)
            C_on = _cross(S_old, en[cs.idx], S_new, en[idx[new]], corr)
            C_nn = _cross(S_new, en[idx[new]], S_new, en[idx[new]], corr, same=True)
            C_oo = cs.joint()
            if len(cs.idx):  # P_xM C_MM^-1 C_M,new (least squares: strongly correlated corners make C_MM stiff)
                P_xn = np.linalg.lstsq(C_oo, cs.P_xc.T, rcond=None)[0].T @ C_on
            else:
                P_xn = np.zeros((n, C_nn.shape[0]))
            Cf = np.block([[C_oo, C_on], [C_on.T, C_nn]])
            held = replace(cs, idx=np.concatenate([cs.idx, idx[new]]), P_xc=np.hstack([cs.P_xc, P_xn]),
                           C=np.concatenate([cs.C, C_new]), Cf=0.5 * (Cf + Cf.T))
    pos = {int(k): i for i, k in enumerate(held.idx)}
    return held, np.array([pos[int(k)] for k in idx], dtype=np.int64)


def update(state: EkfState, cs: ConsiderSet, z_meas: np.ndarray, corner_idx: np.ndarray, corners_en_m: np.ndarray,
           R_extraction: np.ndarray, yaw_meas_rad: np.ndarray | None = None, yaw_sigma_rad: float | np.ndarray = 0.0
           ) -> tuple[EkfState, ConsiderSet, np.ndarray]:
    """Schmidt-Kalman update with N associated corners (rows ``corner_idx`` of the map, positions
    ``corners_en_m`` (N,2), covariances already in ``cs`` or added here from ``cs``'s caller via ``add``).

    ``R_extraction`` (N,2,2): the extracted corners' range/bearing noise only (the map part is the consider
    states'). Optional direct heading measurements (M,) with std ``yaw_sigma_rad`` (one for all, or (M,) one
    each), as ``ekf.update``.
    Full-matrix Joseph form with the consider rows of the gain at zero. Returns (state, set, innovation).
    """
    z_meas = np.asarray(z_meas, dtype=float).reshape(-1, 2)
    yaw_meas = np.zeros(0) if yaw_meas_rad is None else np.asarray(yaw_meas_rad, dtype=float).reshape(-1)
    n, m_yaw, nx = len(z_meas), len(yaw_meas), len(state.q)
    if n + m_yaw == 0:
        return state, cs, np.zeros(0)
    pos = np.array([int(np.flatnonzero(cs.idx == k)[0]) for k in np.asarray(corner_idx)], dtype=np.int64)
    z_pred, H_rb = predict_range_bearing(state.q, np.asarray(corners_en_m, dtype=float).reshape(-1, 2))
    nu_rb = z_meas - z_pred
    nu_rb[:, 1] = wrap_angle_rad(nu_rb[:, 1])
    nu = np.concatenate([nu_rb.reshape(-1), wrap_angle_rad(yaw_meas - state.q[2])])
    rows = 2 * n + m_yaw
    Hx = np.zeros((rows, nx))
    Hx[:2 * n, :3] = H_rb
    Hx[2 * n:, 2] = 1.0
    nc = 2 * len(cs.idx)
    Hc = np.zeros((rows, nc))
    Jm = map_corner_jacobian(H_rb)
    Cf = cs.joint()
    for j, p in enumerate(pos):
        Hc[2 * j:2 * j + 2, 2 * p:2 * p + 2] = Jm[j]
    R = np.zeros((rows, rows))
    for j in range(n):
        R[2 * j:2 * j + 2, 2 * j:2 * j + 2] = R_extraction[j]
    R[np.arange(2 * n, rows), np.arange(2 * n, rows)] = yaw_sigma_rad**2
    P, Pxc = state.P, cs.P_xc
    PHt = P @ Hx.T + Pxc @ Hc.T  # cov(x, innovation)
    HcCf = Hc @ Cf
    S = Hx @ PHt + Hc @ Pxc.T @ Hx.T + HcCf @ Hc.T + R
    S = 0.5 * (S + S.T)
    K = np.linalg.solve(S, PHt.T).T
    q = state.q + K @ nu
    q[2] = wrap_angle_rad(q[2])
    A = np.eye(nx) - K @ Hx
    B = K @ Hc
    P_new = A @ P @ A.T - A @ Pxc @ B.T - B @ Pxc.T @ A.T + B @ Cf @ B.T + K @ R @ K.T
    Pxc_new = A @ Pxc - K @ HcCf
    P_xm = None if cs.P_xm is None else A @ cs.P_xm  # the raster offset is independent of the corners
    return EkfState(q, 0.5 * (P_new + P_new.T)), replace(cs, P_xc=Pxc_new, P_xm=P_xm), nu


def with_map_offset(cs: ConsiderSet, n_state: int, Cm: np.ndarray) -> ConsiderSet:
    """Hold the marking raster's local offset (x, y, yaw) with covariance ``Cm`` (3,3), uncorrelated so far."""
    return replace(cs, P_xm=np.zeros((n_state, 3)), Cm=np.asarray(Cm, dtype=float))


def decay_map_offset(cs: ConsiderSet, rho: float) -> ConsiderSet:
    """The raster offset as a first-order Gauss-Markov process along the road, ``m' = rho m + w`` with ``Cm``
    stationary: its cross-covariance with the vehicle errors decays by ``rho`` (``exp(-travel / length)``)."""
    return cs if cs.P_xm is None else replace(cs, P_xm=rho * cs.P_xm)


def update_linear(state: EkfState, cs: ConsiderSet, H_pose: np.ndarray, innovation: np.ndarray,
                  variance: np.ndarray, gate_chi2: float = np.inf) -> tuple[EkfState, ConsiderSet, float]:
    """Schmidt-Kalman update with r independent linear measurements of the pose that do not involve the map
    corners (``H_pose`` (r,3) on x, y, yaw; e.g. ``ekf_markings``): the corners' errors stay as they are, the
    cross-covariance goes through ``I - K H``. When ``cs`` holds the raster offset (``with_map_offset``) the
    measurement is of the pose plus that offset (``z = H (pose + m) + v``): an offset shared by consecutive
    scans is not averaged away. Joseph form. Returns the state, the set and the innovation's Mahalanobis distance
    under its full covariance (raster offset included); above ``gate_chi2`` nothing is updated."""
    H_pose = np.asarray(H_pose, dtype=float).reshape(-1, 3)
    if len(H_pose) == 0:
        return state, cs, 0.0
    nx = len(state.q)
    H = np.zeros((len(H_pose), nx))
    H[:, :3] = H_pose
    R = np.diag(np.asarray(variance, dtype=float))
    if cs.P_xm is None:
        Pxm, Cm, Hm = np.zeros((nx, 3)), np.zeros((3, 3)), np.zeros_like(H_pose)
    else:
        Pxm, Cm, Hm = cs.P_xm, cs.Cm, H_pose
    P = state.P
    PHt = P @ H.T + Pxm @ Hm.T  # cov(x, innovation)
    S = H @ PHt + Hm @ Pxm.T @ H.T + Hm @ Cm @ Hm.T + R
    S = 0.5 * (S + S.T)
    nu = np.asarray(innovation, dtype=float)
    chi2 = float(nu @ np.linalg.solve(S, nu))
    if chi2 > gate_chi2:
        return state, cs, chi2
    K = np.linalg.solve(S, PHt.T).T
    q = state.q + K @ nu
    q[2] = wrap_angle_rad(q[2])
    A = np.eye(nx) - K @ H
    B = K @ Hm
    P_new = A @ P @ A.T - A @ Pxm @ B.T - B @ Pxm.T @ A.T + B @ Cm @ B.T + K @ R @ K.T
    P_xm = None if cs.P_xm is None else A @ Pxm - K @ Hm @ Cm
    return EkfState(q, 0.5 * (P_new + P_new.T)), replace(cs, P_xc=A @ cs.P_xc, P_xm=P_xm), chi2
