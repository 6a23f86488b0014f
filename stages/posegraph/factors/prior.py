"""A drive's prior trajectory and stated start pose (``poses_prior``) in the pose graph: what places a drive without
GNSS in the map's frame.

- A prior in the map's ENU frame (``frame`` map_enu, ``source`` prior_file): an absolute pose prior (kind
  ``prior``) at most one per ``every_s`` seconds, with the stated std per axis (the stated std is the error of each
  pose; a trajectory's errors are correlated along it, so the factors are thinned like the GNSS fixes), under a
  Huber kernel.
- A prior in a local frame (origin and heading unknown): its shape only, as between factors (kind ``prior``) from
  the drive's first valid prior pose to each thinned one, ``T_local_first^-1 T_local_k`` with the stated std
  (rotated into the first pose's frame); the frame then comes from the start pose. The first pose's own error is
  shared by every such factor (not modelled: a prior whose first pose is 0.1 deg off turns the shape by that).
- The start pose (``source`` start): an absolute pose prior (kind ``start``) on the drive's first scan: position
  (std 0 at the map's origin: floored at ``MIN_SIGMA_M``), heading with its stated std; roll and pitch unknown
  (NaN) take ``unknown_roll_pitch_sigma_rad`` (the vehicle roughly level).

An axis whose std is NaN carries ``UNKNOWN_SIGMA_M`` / the unknown roll-pitch sigma (no information, the graph stays
determined). ``prior_in_map`` gives the initial values: the prior's poses moved into the map's frame (a local prior
turned about z and shifted onto the start pose), the start pose alone for a drive with nothing else.
"""
from __future__ import annotations

import numpy as np

from stages.common.geometry import se3_inverse
from stages.common.records import PriorPoses
from stages.posegraph.config import PriorConfig
from stages.posegraph.factors.gnss import select_epochs
from stages.posegraph.factors.graph import Between, PosePrior

MIN_SIGMA_M = 1e-3  # a stated std of 0 (the start at the map's origin): the origin is exact, the factor is not
MIN_SIGMA_RAD = 1e-5
UNKNOWN_SIGMA_M = 1e3  # an axis the prior says nothing about


def information_of(R_frame_vehicle: np.ndarray, std: np.ndarray, unknown_rp_sigma_rad: float) -> np.ndarray:
    """6x6 information (gtsam order rx ry rz tx ty tz, the pose's body frame) of a pose stated with ``std``
    (x y z m in the frame's axes, roll pitch yaw rad). NaN std: no information on that axis."""
    std = np.asarray(std, float)
    pos = np.where(np.isfinite(std[:3]), np.maximum(std[:3], MIN_SIGMA_M), UNKNOWN_SIGMA_M)
    rot = np.where(np.isfinite(std[3:]), np.maximum(std[3:], MIN_SIGMA_RAD), unknown_rp_sigma_rad)
    R = np.asarray(R_frame_vehicle, float)
    cov_t = R.T @ np.diag(pos ** 2) @ R  # the frame's axes into the body's
    info = np.zeros((6, 6))
    info[:3, :3] = np.diag(rot ** -2.0)
    info[3:, 3:] = np.linalg.inv(cov_t)
    return 0.5 * (info + info.T)


def _at_scans(prior: PriorPoses, scan_ids: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(positions into ``scan_ids``, rows of ``prior``) of the rows in ``mask`` whose scan the drive has."""
    rows = np.flatnonzero(mask)
    pos = np.searchsorted(scan_ids, prior.scan_id[rows])
    ok = pos < len(scan_ids)
    ok[ok] &= scan_ids[pos[ok]] == prior.scan_id[rows[ok]]
    return pos[ok], rows[ok]


def prior_factors(prior: PriorPoses | None, scan_ids: np.ndarray, stamps_ns: np.ndarray, offset: int,
                  cfg: PriorConfig) -> tuple[list[PosePrior], list[Between]]:
    """The drive's absolute pose priors (start, ENU prior) and shape factors (local prior), pose indices from
    ``offset`` (module docstring)."""
    if prior is None or not len(prior.scan_id):
        return [], []
    out_p: list[PosePrior] = []
    out_b: list[Between] = []
    unknown = cfg.unknown_roll_pitch_sigma_rad
    k_s, r_s = _at_scans(prior, scan_ids, (prior.source == "start") & prior.valid)
    for k, r in zip(k_s, r_s):
        out_p.append(PosePrior(offset + int(k), prior.T[r], information_of(prior.T[r][:3, :3], prior.std[r], unknown),
                               "start"))
    k_f, r_f = _at_scans(prior, scan_ids, (prior.source == "prior_file") & prior.valid)
    if not len(k_f):
        return out_p, out_b
    order = np.argsort(k_f)
    k_f, r_f = k_f[order], r_f[order]
    keep = select_epochs(stamps_ns[k_f], np.ones(len(k_f), bool), cfg.every_s)
    if prior.frame[r_f[0]] == "map_enu":
        for n in keep:
            T = prior.T[r_f[n]]
            out_p.append(PosePrior(offset + int(k_f[n]), T, information_of(T[:3, :3], prior.std[r_f[n]], unknown),
                                   "prior", cfg.kernel, cfg.kernel_k))
        return out_p, out_b
    T_first_inv = se3_inverse(prior.T[r_f[0]])
    for n in keep:
        if n == 0:
            continue
        T_rel = T_first_inv @ prior.T[r_f[n]]
        info = information_of(T_rel[:3, :3], prior.std[r_f[n]], unknown)
        out_b.append(Between(offset + int(k_f[0]), offset + int(k_f[n]), T_rel, info, "prior", cfg.kernel,
                             cfg.kernel_k))
    return out_p, out_b


def prior_in_map(prior: PriorPoses | None, scan_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(N,4,4) T_map_vehicle at the drive's scans from its prior, and (N,) where known; None without a prior.
    A local prior is turned about z and shifted so that its pose at the start's scan is the start pose (heading
    from the start's yaw); without a start row it places nothing."""
    if prior is None or not len(prior.scan_id):
        return None
    n = len(scan_ids)
    T = np.tile(np.eye(4), (n, 1, 1))
    known = np.zeros(n, bool)
    k_s, r_s = _at_scans(prior, scan_ids, (prior.source == "start") & prior.valid)
    k_f, r_f = _at_scans(prior, scan_ids, (prior.source == "prior_file") & prior.valid)
    if len(k_f) and prior.frame[r_f[0]] == "map_enu":
        T[k_f], known[k_f] = prior.T[r_f], True
    elif len(k_f) and len(k_s):
        at = np.flatnonzero(k_f == k_s[0])
        first = at[0] if len(at) else int(np.argmin(np.abs(k_f - k_s[0])))
        T_local, T_start = prior.T[r_f[first]], prior.T[r_s[0]]
        dyaw = np.arctan2(T_start[1, 0], T_start[0, 0]) - np.arctan2(T_local[1, 0], T_local[0, 0])
        T_map_local = np.eye(4)
        c, s = np.cos(dyaw), np.sin(dyaw)
        T_map_local[:2, :2] = [[c, -s], [s, c]]
        T_map_local[:3, 3] = T_start[:3, 3] - T_map_local[:3, :3] @ T_local[:3, 3]
        T[k_f], known[k_f] = T_map_local @ prior.T[r_f], True
    if len(k_s) and not known[k_s[0]]:
        T[k_s[0]], known[k_s[0]] = prior.T[r_s[0]], True
    return (T, known) if known.any() else None
