"""How the optimized poses' errors correlate with distance, from the pose graph's own joint marginals.

A map corner is placed with the poses of the stretch of drive that saw it, so corners a few tens of metres apart
share that stretch's error: their errors are correlated, and a localizer that treats them as independent averages
away an error it carries (docs/evaluation.md, "Correlated map-corner errors"). The pose graph knows this
correlation: the joint marginal covariance of two poses i, j (gtsam ``Marginals.jointMarginalCovariance``) gives
the correlation of their horizontal position errors,

    rho_ij = tr(C_ij) / sqrt(tr(C_ii) tr(C_jj))      (2x2 horizontal blocks, ENU axes),

and a squared-exponential kernel ``share * exp(-d^2 / (2 length^2))`` fitted to rho against the distance d between
the poses is the map's statement of how its local error is shared. No truth is involved: the kernel is as honest
as the graph's factors (measured against the simulator's truth in docs/posegraph.md).

Pairs are drawn with a fixed seed, an equal number per distance bin, so the figure repeats. Arrays in, a small
result out; gtsam's Cholesky marginals only (a graph that needs the QR fallback of ``graph.pose_marginals`` gets
no kernel: ``None``).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

DISTANCE_BINS_M = ((0.0, 15.0), (15.0, 40.0), (40.0, 80.0), (80.0, 150.0))


@dataclass(frozen=True)
class ErrorKernel:
    share: float  # correlation of two poses' horizontal errors at distance 0 (the kernel's amplitude)
    length_m: float  # the squared-exponential kernel's length
    bins_m: tuple[tuple[float, float], ...]
    bin_mean_rho: tuple[float, ...]  # the mean sampled correlation per bin (nan: no pair)
    n_pairs: int

    def as_dict(self) -> dict:
        return {"share": self.share, "length_m": self.length_m, "n_pairs": self.n_pairs,
                "bins_m": [list(b) for b in self.bins_m],
                "bin_mean_rho": [None if not np.isfinite(r) else r for r in self.bin_mean_rho],
                "method": "pose graph joint marginals, squared-exponential fit"}


def sample_pairs(xy_m: np.ndarray, bins_m=DISTANCE_BINS_M, per_bin: int = 60, seed: int = 0,
                 max_draws: int = 200_000) -> tuple[np.ndarray, np.ndarray]:
    """Pose index pairs (i < j), up to ``per_bin`` whose distance falls in each bin, drawn with ``seed``."""
    xy_m = np.asarray(xy_m, dtype=float).reshape(-1, 2)
    n = len(xy_m)
    if n < 2 or per_bin <= 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    rng = np.random.default_rng(seed)
    i = rng.integers(0, n, max_draws)
    j = rng.integers(0, n, max_draws)
    keep = i != j
    i, j = np.minimum(i[keep], j[keep]), np.maximum(i[keep], j[keep])
    d = np.linalg.norm(xy_m[i] - xy_m[j], axis=1)
    out_i, out_j = [], []
    for lo, hi in bins_m:
        sel = np.flatnonzero((d >= lo) & (d < hi))[:per_bin]
        out_i.append(i[sel])
        out_j.append(j[sel])
    return np.concatenate(out_i), np.concatenate(out_j)


def horizontal_correlation(C_ii: np.ndarray, C_jj: np.ndarray, C_ij: np.ndarray) -> float:
    """Correlation of two positions' horizontal errors from their (3x3 or 2x2, same axes) covariance blocks."""
    a, b = np.trace(C_ii[:2, :2]), np.trace(C_jj[:2, :2])
    return float(np.trace(C_ij[:2, :2]) / np.sqrt(a * b)) if a > 0 and b > 0 else float("nan")


def fit_kernel(d_m: np.ndarray, rho: np.ndarray, max_length_m: float = 500.0) -> tuple[float, float]:
    """Least-squares ``(share, length_m)`` of ``share * exp(-d^2 / (2 length^2))`` to the sampled correlations
    (share in [0, 0.99]; the kernel must stay below 1 off the diagonal)."""
    from scipy.optimize import least_squares

    d_m, rho = np.asarray(d_m, float), np.asarray(rho, float)
    ok = np.isfinite(d_m) & np.isfinite(rho)
    if ok.sum() < 3:
        return 0.0, 1.0
    d_m, rho = d_m[ok], rho[ok]
    fit = least_squares(lambda p: p[0] * np.exp(-0.5 * (d_m / p[1]) ** 2) - rho, [0.5, 30.0],
                        bounds=([0.0, 1.0], [0.99, max_length_m]))
    return float(fit.x[0]), float(fit.x[1])


def _enu_block(cov6: np.ndarray, Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """(3,3) (east, north, yaw) block of a 6x6 joint-marginal block in gtsam's body-frame (rotation, translation)
    tangents of poses a and b (rotations R_map_vehicle)."""
    Ba, Bb = np.zeros((3, 6)), np.zeros((3, 6))
    Ba[:2, 3:], Ba[2, :3] = Ra[:2], Ra[2]
    Bb[:2, 3:], Bb[2, :3] = Rb[:2], Rb[2]
    return Ba @ cov6 @ Bb.T


def pose_error_kernel(graph, values, poses: np.ndarray, n_poses: int, per_bin: int = 60, seed: int = 0,
                      split=None) -> ErrorKernel | None:
    """The kernel of poses ``0..n_poses-1`` of the graph (``T_map_vehicle`` ``poses`` give their positions and the
    rotations into ENU of gtsam's body-frame marginals); None when gtsam's Cholesky marginals give up. With
    ``split`` (``map_frame.FrameSplit`` of these poses) the errors are those relative to the map frame."""
    import gtsam

    from stages.posegraph.factors.graph import _key, _variable_named
    from stages.posegraph.map_frame import frame_basis

    i_idx, j_idx = sample_pairs(poses[:n_poses, :2, 3], per_bin=per_bin, seed=seed)
    if not len(i_idx):
        return None
    try:
        marginals = gtsam.Marginals(graph, values)
    except RuntimeError as err:
        log.warning("pose graph: the map states no error correlation (gtsam's Cholesky marginals gave up near %s)",
                    _variable_named(err))
        return None
    G = None if split is None else frame_basis(poses[:n_poses, :2, 3], split.reference_en_m)
    rho = np.empty(len(i_idx))
    for n, (i, j) in enumerate(zip(i_idx.tolist(), j_idx.tolist())):
        keys = gtsam.KeyVector()
        keys.append(_key(i))
        keys.append(_key(j))
        joint = marginals.jointMarginalCovariance(keys)  # 6x6 blocks, body frames, rotation then translation
        blocks = [_enu_block(joint.at(keys[a], keys[b]), poses[(i, j)[a], :3, :3], poses[(i, j)[b], :3, :3])
                  for a, b in ((0, 0), (1, 1), (0, 1))]
        if G is not None:
            blocks = [split.relative_cross(a, b, c, G) for (a, b), c in zip(((i, i), (j, j), (i, j)), blocks)]
        rho[n] = horizontal_correlation(*blocks)
    d = np.linalg.norm(poses[i_idx, :2, 3] - poses[j_idx, :2, 3], axis=1)
    share, length = fit_kernel(d, rho)
    means = []
    for lo, hi in DISTANCE_BINS_M:
        sel = (d >= lo) & (d < hi) & np.isfinite(rho)
        means.append(float(rho[sel].mean()) if sel.any() else float("nan"))
    return ErrorKernel(share, length, DISTANCE_BINS_M, tuple(means), int(len(rho)))
