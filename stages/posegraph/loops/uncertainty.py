"""How far apart two poses of the current estimate may really be: the horizontal covariance of their relative
position accumulated along the odometry since the last absolute constraint, the gate of the wide loop search
(``wide.py``).

The odometry chain of a drive is linearised at the estimate: the increment into pose k (between factors k-1 -> k:
ICP edges, bridges, wheel; their informations summed) has a translation covariance (turned into the map frame by
pose k-1's heading) and a heading variance s_k, whose error turns everything after pose k about p_k. The
relative position p_b - p_a of two poses a < b of one drive then has the covariance

    sum_{a<k<=b} R C_k R^T + J (sum s_k (p_b - p_k)(p_b - p_k)^T) J^T,   J = 90 deg turn,

which prefix sums of s_k, s_k p_k and s_k p_k p_k^T give in O(1) per pair (the chain's marginal with
nothing else in the graph; Olson et al. 2006 and LIO-SAM's loop search draw their radius from the same quantity).
What caps it: a drive with GNSS fixes or an ENU prior trajectory is held absolutely (``absolute`` poses: the
relative covariance of two of its poses is ~0 after the last fix; those drives keep the fixed radius), and a local
prior trajectory's shape factors bound two of its poses' relative position by twice the stated covariance. Poses of
two different drives: each one's covariance from its start pose (its stated heading std turning the whole drive).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_J = np.array([[0.0, -1.0], [1.0, 0.0]])
CHAIN_KINDS = ("odometry", "bridge", "wheel", "wheel_fused")


@dataclass(frozen=True)
class ChainCovariance:
    """Prefix sums of the odometry chain (module docstring), per global pose index."""

    positions_en: np.ndarray  # (N,2) the estimate's positions
    group: np.ndarray  # (N,) drive index
    absolute: np.ndarray  # (N,) bool: the pose's drive is held by GNSS fixes or an ENU prior
    trans: np.ndarray  # (N,2,2) cumulative translation covariance (map frame) of the increments into 1..k
    s0: np.ndarray  # (N,) cumulative heading variance
    s1: np.ndarray  # (N,2) cumulative s_k p_k
    s2: np.ndarray  # (N,2,2) cumulative s_k p_k p_k^T
    start: np.ndarray  # (N,) the first global index of the pose's drive
    start_var_rad2: np.ndarray  # (N,) the drive's start heading variance (0: none stated)
    start_pos_m2: np.ndarray  # (N,) the drive's start position variance per axis
    prior_cap_m2: np.ndarray  # (N,) a local prior's bound on a relative position's variance per axis (inf: none)

    def same_drive(self, a: int, b: np.ndarray) -> np.ndarray:
        """(len(b),2,2) covariance of p_b - p_a for poses ``b`` of ``a``'s drive (either order)."""
        b = np.asarray(b, np.int64)
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        return self._segment(lo, hi, hi)

    def from_start(self, b: np.ndarray) -> np.ndarray:
        """(len(b),2,2) covariance of pose b's position from its drive's start pose (the start's own stated heading
        and position errors included)."""
        b = np.asarray(b, np.int64)
        st = self.start[b]
        cov = self._segment(st, b, b)
        lever = self.positions_en[b] - self.positions_en[st]
        turned = lever @ _J.T
        cov += self.start_var_rad2[b][:, None, None] * turned[:, :, None] * turned[:, None, :]
        cov += self.start_pos_m2[b][:, None, None] * np.eye(2)
        return cov

    def _segment(self, lo: np.ndarray, hi: np.ndarray, end: np.ndarray) -> np.ndarray:
        p = self.positions_en[end]
        s0 = self.s0[hi] - self.s0[lo]
        s1 = self.s1[hi] - self.s1[lo]
        s2 = self.s2[hi] - self.s2[lo]
        m = s0[:, None, None] * p[:, :, None] * p[:, None, :] - p[:, :, None] * s1[:, None, :] \
            - s1[:, :, None] * p[:, None, :] + s2
        return self.trans[hi] - self.trans[lo] + _J @ m @ _J.T

    def relative(self, q: int, targets: np.ndarray) -> np.ndarray:
        """(len(targets),2,2) covariance of p_target - p_q: the chain between them on one drive (capped by a local
        prior), the two drives' covariances from their starts otherwise; 0 where both are held absolutely."""
        targets = np.asarray(targets, np.int64)
        out = np.zeros((len(targets), 2, 2))
        same = self.group[targets] == self.group[q]
        if same.any():
            cov = self.same_drive(q, targets[same])
            cap = self.prior_cap_m2[q]
            if np.isfinite(cap):
                over = np.trace(cov, axis1=1, axis2=2) > 2 * cap
                cov[over] = cap * np.eye(2)
            out[same] = cov
        other = ~same
        if other.any():
            t = targets[other]
            cov_q = np.zeros((2, 2)) if self.absolute[q] else self.from_start(np.array([q]))[0]
            cov_t = self.from_start(t)
            cov_t[self.absolute[t]] = 0.0
            out[other] = cov_q + cov_t
        out[self.absolute[targets] & self.absolute[q]] = 0.0
        return out


def chain_covariance(problem, poses: np.ndarray, offsets: np.ndarray, absolute_drives: np.ndarray
                     ) -> ChainCovariance:
    """The prefix sums of every drive's chain from the problem's between factors of ``CHAIN_KINDS`` between
    consecutive poses and its start priors (kind ``start``); ``absolute_drives`` (bool per drive): held by GNSS or an
    ENU prior; a local prior's shape factors (kind ``prior``) give its cap."""
    n = len(poses)
    offsets = np.asarray(offsets, np.int64)
    group = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
    info = np.zeros((n, 6, 6))
    cap = np.full(n, np.inf)
    for b in problem.betweens:
        if b.kind in CHAIN_KINDS and b.j == b.i + 1 and group[b.i] == group[b.j]:
            info[b.j] += b.information
        elif b.kind == "prior" and group[b.i] == group[b.j]:
            cov_t = np.linalg.inv(b.information[3:, 3:])[:2, :2]
            g = group[b.i]
            var = float(np.max(np.linalg.eigvalsh(cov_t)))
            sl = slice(offsets[g], offsets[g + 1])
            cap[sl] = np.where(np.isfinite(cap[sl]), np.maximum(cap[sl], var), var)
    start_var = np.zeros(n)
    start_pos = np.zeros(n)
    for p in problem.pose_priors:
        if p.kind == "start":
            cov = np.linalg.inv(p.information)
            g = group[p.i]
            sl = slice(offsets[g], offsets[g + 1])
            start_var[sl] = cov[2, 2]
            start_pos[sl] = float(np.max(np.linalg.eigvalsh(cov[3:5, 3:5])))
    pos = poses[:, :2, 3]
    yaw = np.arctan2(poses[:, 1, 0], poses[:, 0, 0])
    trans_k = np.zeros((n, 2, 2))
    s_k = np.zeros(n)
    for k in range(n):
        if k == 0 or group[k] != group[k - 1]:
            continue
        if not info[k].any():
            s_k[k], trans_k[k] = 1.0, np.eye(2) * 1e6  # nothing links them: unbounded
            continue
        cov = np.linalg.pinv(info[k])
        c, s = np.cos(yaw[k - 1]), np.sin(yaw[k - 1])
        R = np.array([[c, -s], [s, c]])
        trans_k[k] = R @ cov[3:5, 3:5] @ R.T
        s_k[k] = cov[2, 2]
    absolute = np.asarray(absolute_drives, bool)[group]
    return ChainCovariance(pos, group, absolute, np.cumsum(trans_k, axis=0), np.cumsum(s_k),
                           np.cumsum(s_k[:, None] * pos, axis=0),
                           np.cumsum(s_k[:, None, None] * pos[:, :, None] * pos[:, None, :], axis=0),
                           offsets[group], start_var, start_pos, cap)
