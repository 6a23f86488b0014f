"""Where a vehicle will localize well on a map, and where not: the predicted position uncertainty of the corner EKF
and of the marking MCL per cell of the driven roads, from the landmarks the sensor sees there.

Model (a covariance analysis: the filters' own Riccati recursion, run without measurements' values):
1. Road. Each map drive's path, resampled every ``step_m`` (one scan at the drive's moving speed, at least the
   filters' decorrelation travel, so every sample is one full look).
2. What is seen. At each sample the corners in view (``corner_visibility.visible``: range, the walls' seen side,
   the rebuilt walls of other buildings) and the markings' information (``marking_information``).
3. The EKF (``method = ekf``): state (east, north, heading); ICP increments with the EKF's motion noise; each corner
   in view measures range, bearing and its two walls' headings with the EKF's noise floors, scaled by
   ``detection_rate`` (the share of corners in view the EKF associates, set on calibration seeds); the markings
   measure the pose with their information. Map errors are Schmidt consider states as in the EKF
   (``stages/evaluate/consider.py``): each corner's error (its 2x2 covariance, correlated ``share exp(-d^2/2L^2)``
   with the others) and the marking raster's offset (a Gauss-Markov offset along the road) are never averaged away.
4. The MCL (``method = mcl``): the same on the markings alone, with the MCL's wheel/gyro motion noise.
5. Cells. A cell (``cell_m`` squares of the ENU grid) holds the samples in it (a pass's first ``burn_in_m`` only
   when nothing else covers the cell); its covariance is their mean: ``sigma_2d_m = sqrt(cov_ee + cov_nn)``, the
   predicted RMS of the 2-D error; along and across are about the cell's road axis.
Pure numpy, arrays in, arrays out. Results and their honesty on validation drives: docs/map-format.md.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from stages.common.localizer_defaults import (
    CORNER_EKF,
    CornerEkfNoise,
    MarkingNoise,
    MclMotionNoise,
)


@dataclass(frozen=True)
class Corners:
    en_m: np.ndarray  # (K,2)
    cov_m2: np.ndarray  # (K,2,2)
    theta_rad: np.ndarray  # (K,2) wall directions from the corner
    convex: np.ndarray  # (K,) bool


@dataclass(frozen=True)
class LocalizabilityConfig:
    cell_m: float = 10.0
    detection_rate: float = 0.58  # share of the corners in view an EKF look associates (tiles param)
    min_incidence_deg: float = 10.0  # a wall seen more obliquely gives no line
    wall_stub_m: float = 5.0  # an unpaired wall's length when rebuilding walls
    burn_in_m: float = 50.0  # a pass's start-up, used only where nothing else covers a cell
    corr_share: float = CORNER_EKF.map_corr_share  # the map's corner error correlation (the manifest's, if stated)
    corr_length_m: float = CORNER_EKF.map_corr_length_m
    forget_m: float = 120.0  # a held corner farther than this leaves the consider set (the EKF's)
    weak_sigma_m: float = 0.10  # a cell predicted above this is 'weak'
    fail_sigma_m: float = 0.40  # ... above this 'fail'
    ekf: CornerEkfNoise = field(default_factory=CornerEkfNoise)
    markings: MarkingNoise = field(default_factory=MarkingNoise)
    mcl: MclMotionNoise = field(default_factory=MclMotionNoise)


def resample_path(en_m: np.ndarray, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """A path (N,2) every ``step_m`` along it -> ((M,2) points, (M,) headings of travel)."""
    en = np.asarray(en_m, float).reshape(-1, 2)
    seg = np.linalg.norm(np.diff(en, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-6])
    en = en[keep]
    if len(en) < 2:
        return np.zeros((0, 2)), np.zeros(0)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(en, axis=0), axis=1))])
    t = np.arange(0.0, s[-1], step_m)
    pts = np.column_stack([np.interp(t, s, en[:, 0]), np.interp(t, s, en[:, 1])])
    ahead = np.column_stack([np.interp(t + 1.0, s, en[:, 0]), np.interp(t + 1.0, s, en[:, 1])])
    behind = np.column_stack([np.interp(t - 1.0, s, en[:, 0]), np.interp(t - 1.0, s, en[:, 1])])
    d = ahead - behind
    return pts, np.arctan2(d[:, 1], d[:, 0])


def _kernel_cov(S_a, en_a, S_b, en_b, share, length_m, same=False) -> np.ndarray:
    """(2a, 2b) covariance of two corner sets' errors: share exp(-d^2/2L^2) S_i S_j (own blocks C_i with ``same``)."""
    d = np.linalg.norm(en_a[:, None, :] - en_b[None, :, :], axis=2)
    k = share * np.exp(-0.5 * (d / length_m) ** 2) if share > 0 else np.zeros_like(d)
    if same:
        np.fill_diagonal(k, 1.0)
    blocks = k[:, :, None, None] * np.einsum("aij,bjk->abik", S_a, S_b)
    return blocks.transpose(0, 2, 1, 3).reshape(2 * len(en_a), 2 * len(en_b))


def _sqrt_spd(C: np.ndarray) -> np.ndarray:
    w, V = np.linalg.eigh(C)
    return np.einsum("mij,mj,mkj->mik", V, np.sqrt(np.clip(w, 0.0, None)), V)


class _Schmidt:
    """Covariance of (east, north, heading) errors with consider states: held corners and the raster offset."""

    def __init__(self, P0: np.ndarray, Cm: np.ndarray, corners: Corners, S: np.ndarray, cfg: LocalizabilityConfig):
        self.P, self.Cm, self.Pxm = P0.copy(), Cm, np.zeros((3, 3))
        self.corners, self.S, self.cfg = corners, S, cfg
        self.idx = np.zeros(0, np.int64)
        self.Pxc, self.Ccc = np.zeros((3, 0)), np.zeros((0, 0))

    def predict(self, yaw: float, step_m: float, Q_vehicle: np.ndarray, decay: float) -> None:
        c, s = np.cos(yaw), np.sin(yaw)
        F = np.array([[1.0, 0.0, -s * step_m], [0.0, 1.0, c * step_m], [0.0, 0.0, 1.0]])
        G = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        self.P = F @ self.P @ F.T + G @ Q_vehicle @ G.T
        self.Pxm = F @ self.Pxm * decay
        self.Pxc = F @ self.Pxc

    def hold(self, new: np.ndarray, here: np.ndarray) -> None:
        """Add corners ``new`` to the consider set (their cross-covariance with the state through the correlated
        held ones) and drop held corners farther than forget_m from ``here``."""
        en, cfg = self.corners.en_m, self.cfg
        keep = np.linalg.norm(en[self.idx] - here, axis=1) <= cfg.forget_m
        if not keep.all():
            cols = np.repeat(keep, 2)
            self.idx, self.Pxc, self.Ccc = self.idx[keep], self.Pxc[:, cols], self.Ccc[np.ix_(cols, cols)]
        new = np.setdiff1d(new, self.idx)
        if len(new) == 0:
            return
        C_nn = _kernel_cov(self.S[new], en[new], self.S[new], en[new], cfg.corr_share, cfg.corr_length_m, True)
        if len(self.idx):
            C_mn = _kernel_cov(self.S[self.idx], en[self.idx], self.S[new], en[new], cfg.corr_share, cfg.corr_length_m)
            P_xn = self.Pxc @ np.linalg.lstsq(self.Ccc, C_mn, rcond=None)[0] if cfg.corr_share > 0 \
                else np.zeros((3, 2 * len(new)))
            self.Ccc = np.block([[self.Ccc, C_mn], [C_mn.T, C_nn]])
        else:
            P_xn = np.zeros((3, 2 * len(new)))
            self.Ccc = C_nn
        self.idx = np.concatenate([self.idx, new])
        self.Pxc = np.hstack([self.Pxc, P_xn])

    def update(self, Hx: np.ndarray, R: np.ndarray, Hc: np.ndarray | None = None, Hm: np.ndarray | None = None
               ) -> None:
        """Schmidt update with rows ``Hx`` on the state, ``Hc`` on the held corners, ``Hm`` on the raster offset."""
        PHt = self.P @ Hx.T
        S = Hx @ PHt + R
        cross_c = self.Pxc @ Hc.T if Hc is not None else 0.0
        cross_m = self.Pxm @ Hm.T if Hm is not None else 0.0
        if Hc is not None:
            S = S + Hx @ cross_c + (Hx @ cross_c).T + Hc @ self.Ccc @ Hc.T
        if Hm is not None:
            S = S + Hx @ cross_m + (Hx @ cross_m).T + Hm @ self.Cm @ Hm.T
        K = np.linalg.solve(S, (PHt + cross_c + cross_m).T).T
        HPxc = Hx @ self.Pxc + (Hc @ self.Ccc if Hc is not None else 0.0)
        HPxm = Hx @ self.Pxm + (Hm @ self.Cm if Hm is not None else 0.0)
        self.P = self.P - K @ S @ K.T
        self.P = 0.5 * (self.P + self.P.T)
        self.Pxc = self.Pxc - K @ HPxc
        self.Pxm = self.Pxm - K @ HPxm


def _corner_rows(q: np.ndarray, idx: np.ndarray, held: np.ndarray, corners: Corners, noise: CornerEkfNoise,
                 rate: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Range, bearing and two wall headings per corner in view: (Hx, R, Hc) on the state and the held corners."""
    d = corners.en_m[idx] - q[:2]
    r2 = np.maximum(np.einsum("ij,ij->i", d, d), 1e-6)
    r = np.sqrt(r2)
    n = len(idx)
    Hx = np.zeros((4 * n, 3))
    Hx[0::4, 0], Hx[0::4, 1] = -d[:, 0] / r, -d[:, 1] / r
    Hx[1::4, 0], Hx[1::4, 1], Hx[1::4, 2] = d[:, 1] / r2, -d[:, 0] / r2, -1.0
    Hx[2::4, 2] = Hx[3::4, 2] = 1.0
    col = {int(k): j for j, k in enumerate(held)}
    Hc = np.zeros((4 * n, 2 * len(held)))
    for j, k in enumerate(idx):
        c = 2 * col[int(k)]
        Hc[4 * j:4 * j + 2, c:c + 2] = -Hx[4 * j:4 * j + 2, :2]
    var = np.tile([noise.range_sigma_floor_m ** 2, np.deg2rad(noise.bearing_sigma_floor_deg) ** 2,
                   np.deg2rad(noise.wall_heading_sigma_deg) ** 2, np.deg2rad(noise.wall_heading_sigma_deg) ** 2], n)
    return Hx, np.diag(var / rate), Hc


def _marking_rows(info: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    w, V = np.linalg.eigh(0.5 * (info + info.T))
    keep = w > 1e-9 * max(1.0, float(w.max(initial=0.0)))
    if not keep.any():
        return None
    return V[:, keep].T, np.diag(1.0 / w[keep])


def predict_pass(en_m: np.ndarray, yaw_rad: np.ndarray, step_m: float, method: str, corners: Corners,
                 in_view: list[np.ndarray], marking_info: np.ndarray, cfg: LocalizabilityConfig) -> np.ndarray:
    """(M,3,3) predicted covariance of (east, north, heading) at each sample of one pass (see the module doc).
    ``in_view[k]``: corner rows seen at sample k; ``marking_info`` (M,3,3) one scan's markings' information."""
    ekf = method == "ekf"
    mk = cfg.markings
    if ekf:
        sig0, yaw0 = cfg.ekf.init_sigma_xy_m, np.deg2rad(cfg.ekf.init_sigma_yaw_deg)
        s_xy = cfg.ekf.icp_sigma_frac * step_m + cfg.ekf.icp_sigma_xy_m
        Q = np.diag([s_xy ** 2, s_xy ** 2, np.deg2rad(cfg.ekf.icp_sigma_yaw_deg) ** 2])
    else:
        m = cfg.mcl
        sig0, yaw0 = m.init_sigma_xy_m, np.deg2rad(m.init_sigma_yaw_deg)
        Q = np.diag([(m.sigma_frac * step_m + m.sigma_xy_m) ** 2, (m.sigma_lateral_frac * step_m + m.sigma_xy_m) ** 2,
                     np.deg2rad(m.sigma_yaw_deg) ** 2])
    Cm = np.diag([mk.map_sigma_m ** 2, mk.map_sigma_m ** 2, np.deg2rad(mk.map_sigma_deg) ** 2])
    S = _sqrt_spd(corners.cov_m2) if len(corners.en_m) else np.zeros((0, 2, 2))
    f = _Schmidt(np.diag([sig0 ** 2, sig0 ** 2, yaw0 ** 2]), Cm, corners, S, cfg)
    decay = float(np.exp(-step_m / mk.map_length_m))
    out = np.zeros((len(en_m), 3, 3))
    for k in range(len(en_m)):
        q = np.array([en_m[k, 0], en_m[k, 1], yaw_rad[k]])
        if k:
            f.predict(float(yaw_rad[k - 1]), step_m, Q, decay)
        if ekf and len(in_view[k]):
            f.hold(in_view[k], q[:2])
            Hx, R, Hc = _corner_rows(q, in_view[k], f.idx, corners, cfg.ekf, cfg.detection_rate)
            f.update(Hx, R, Hc=Hc)
        rows = _marking_rows(marking_info[k])
        if rows is not None:
            f.update(rows[0], rows[1], Hm=-rows[0])
        out[k] = f.P
    return out
