"""The map's common frame error and each pose's error relative to the map: an S-transformation of the pose graph's
joint covariance.

A pose graph anchored by GNSS (or a survey) states each pose's *absolute* error: without a survey every pose of a
map drive carries the drive's GNSS bias averaged over it, ~0.5 m, while poses tens of metres apart are off by
nearly the same amount (their relative error is centimetres). A localizer matching the map's corners is judged in
the map's frame: what it needs is each corner's error *relative to the map*, and, once, how far the whole map frame
may sit from the true ENU frame (to start from a GNSS fix metres off and converge onto the map).

Let ``e`` be the stacked horizontal errors (east, north, yaw) of the map drives' N poses, ``Sigma`` its joint
covariance (the inverse of the graph's information, linearised at the solution), and ``G`` (3N x k) the
displacement of every pose under a small change ``g`` of the frame about the reference point ``c``:

    rigid (k = 3: shift t_e, t_n, rotation theta):  G_i = [[1, 0, -(n_i - c_n)], [0, 1, e_i - c_e], [0, 0, 1]]
    similarity (k = 4: + scale s):                  column 4 = [e_i - c_e, n_i - c_n, 0]

The frame error is the weighted least-squares fit of a frame change to the pose errors, ``g = A e`` with
``A = (G^T W G)^-1 G^T W`` (W: each pose's east and north weighted by its share of the drive's travel, yaw 0: the
fit of positions that ``truth_in_map`` makes of the corners), and the error relative to the map is what is left,
``e_rel = (I - G A) e``. Both are linear in ``e`` (Baarda's S-transformation: the same network in another datum),
so

    Sigma_frame = A Sigma A^T                        (k x k, stated once per map version)
    Sigma_rel   = (I - G A) Sigma (I - G A)^T        (each pose's 3x3 block; the corners carry it)

With ``M = W G (G^T W G)^-1`` (3N x k) only ``Sigma M`` is needed besides the diagonal blocks: k solves with the
graph's sparse information matrix. Block i of the relative covariance is
``Sigma_ii - G_i (Sigma M)_i^T - (Sigma M)_i G_i^T + G_i Sigma_frame G_i^T`` and, for two poses (the corners' error
kernel), ``Sigma_ij - G_i (Sigma M)_j^T - (Sigma M)_i G_j^T + G_i Sigma_frame G_j^T``.

The frame error is as honest as the graph's GNSS model: with the Gauss-Markov bias chain (``factors/gnss.py``) the
shift is the drive's bias averaged over it and the rotation the bias's change across the map; with survey anchors
it is what the anchors leave. Arrays in, arrays out; the information matrix is built from the linearised graph's
sparse Jacobian (gtsam) and factored by scipy (SuperLU), the diagonal blocks are the caller's (gtsam marginals).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

RIGID_DOF = ("shift_east_m", "shift_north_m", "rotation_rad")
SIMILARITY_DOF = RIGID_DOF + ("scale",)


@dataclass(frozen=True)
class FrameSplit:
    """The frame error of a set of poses and their errors relative to the frame."""

    reference_en_m: np.ndarray  # (2,) the point the frame's shift is stated at (travel-weighted centroid)
    cov_frame: np.ndarray  # (3,3) covariance of (shift east m, shift north m, rotation rad)
    scale_std: float  # std of the frame's scale (a 4-dof similarity fit), 1
    cov_relative: np.ndarray  # (N,3,3) each pose's (east, north, yaw) covariance relative to the frame
    sigma_m: np.ndarray  # (N,3,k=3) Sigma M: the poses' covariance with the rigid frame fit, (e, n, yaw) x g

    def relative_cross(self, i: int, j: int, cov_ij: np.ndarray, G: np.ndarray) -> np.ndarray:
        """(3,3) relative cross-covariance of poses i and j from their absolute one ``cov_ij`` (ENU e, n, yaw)."""
        Gi, Gj = G[i], G[j]
        return (cov_ij - Gi @ self.sigma_m[j].T - self.sigma_m[i] @ Gj.T + Gi @ self.cov_frame @ Gj.T)

    def as_dict(self) -> dict:
        """The manifest's ``map_frame`` entry: the frame's covariance at its reference point, its stds, and the
        poses' error relative to the frame (RMS over the map drives' poses of the per-axis and heading stds: what a
        layer painted from those poses, such as a marking raster, is locally off by)."""
        c, r = self.cov_frame, self.cov_relative
        rel_m = float(np.sqrt(np.mean(r[:, 0, 0] + r[:, 1, 1]) / 2.0)) if len(r) else 0.0
        rel_deg = float(np.degrees(np.sqrt(np.mean(r[:, 2, 2])))) if len(r) else 0.0
        return {"reference_en_m": [float(v) for v in self.reference_en_m],
                "cov_shift_rotation": [[float(v) for v in row] for row in c],
                "std_east_m": float(np.sqrt(c[0, 0])), "std_north_m": float(np.sqrt(c[1, 1])),
                "std_rotation_deg": float(np.degrees(np.sqrt(c[2, 2]))), "std_scale": float(self.scale_std),
                "relative_std_m": rel_m, "relative_std_deg": rel_deg,
                "method": "pose graph joint covariance, S-transformation onto a travel-weighted rigid fit of the map "
                          "drives' positions (stages/posegraph/map_frame.py)"}


def frame_basis(en_m: np.ndarray, reference_en_m: np.ndarray, scale: bool = False) -> np.ndarray:
    """(N,3,k) displacement of each pose's (east, north, yaw) under a frame change (shift e, shift n, rotation
    [, scale]) about ``reference_en_m``."""
    d = np.asarray(en_m, float).reshape(-1, 2) - np.asarray(reference_en_m, float)
    G = np.zeros((len(d), 3, 4 if scale else 3))
    G[:, 0, 0] = G[:, 1, 1] = G[:, 2, 2] = 1.0
    G[:, 0, 2], G[:, 1, 2] = -d[:, 1], d[:, 0]
    if scale:
        G[:, 0, 3], G[:, 1, 3] = d[:, 0], d[:, 1]
    return G


def travel_weights(en_m: np.ndarray, group: np.ndarray | None = None) -> np.ndarray:
    """(N,) each pose's share of its drive's travel (half the steps to its neighbours), so that a stop's many poses
    weigh what its metres do; a drive that does not move weighs each pose alike."""
    en_m = np.asarray(en_m, float).reshape(-1, 2)
    group = np.zeros(len(en_m), int) if group is None else np.asarray(group)
    w = np.zeros(len(en_m))
    for g in np.unique(group):
        idx = np.flatnonzero(group == g)
        step = np.linalg.norm(np.diff(en_m[idx], axis=0), axis=1)
        wg = np.zeros(len(idx))
        wg[:-1] += 0.5 * step
        wg[1:] += 0.5 * step
        w[idx] = wg if wg.sum() > 0 else 1.0
    return w / w.sum() if w.sum() > 0 else np.full(len(w), 1.0 / max(len(w), 1))


def _fit_operator(G: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(N,3,k) M = W G (G^T W G)^-1, W = diag(w_i, w_i, 0) per pose (positions fit the frame, headings do not)."""
    Wd = np.stack([weights, weights, np.zeros_like(weights)], axis=1)  # (N,3)
    WG = Wd[:, :, None] * G
    N = np.einsum("nak,nal->kl", G, WG)
    return WG @ np.linalg.inv(N)


def split_frame(solve_sigma, marginals_enu: np.ndarray, en_m: np.ndarray, weights: np.ndarray,
                reference_en_m: np.ndarray | None = None) -> FrameSplit:
    """The frame error and the relative covariances of N poses.

    ``solve_sigma(V)``: (N,3,k) -> (N,3,k), the joint covariance of the poses' (e, n, yaw) errors applied to V
    (``sparse_covariance_operator``); ``marginals_enu`` (N,3,3) their diagonal blocks; ``en_m`` (N,2) positions;
    ``weights`` (N,) the fit's weights (``travel_weights``)."""
    en_m = np.asarray(en_m, float).reshape(-1, 2)
    w = np.asarray(weights, float)
    ref = np.average(en_m, axis=0, weights=w) if reference_en_m is None else np.asarray(reference_en_m, float)
    G4 = frame_basis(en_m, ref, scale=True)
    M4 = _fit_operator(G4, w)
    SM4 = solve_sigma(M4)  # (N,3,4)
    cov4 = np.einsum("nak,nal->kl", M4, SM4)
    G, M = G4[..., :3], _fit_operator(G4[..., :3], w)
    SM = solve_sigma(M)
    cov_frame = np.einsum("nak,nal->kl", M, SM)
    cov_frame = 0.5 * (cov_frame + cov_frame.T)
    GSM = np.einsum("nak,nbk->nab", G, SM)  # G_i (Sigma M)_i^T
    rel = (marginals_enu - GSM - GSM.transpose(0, 2, 1) + np.einsum("nak,kl,nbl->nab", G, cov_frame, G))
    rel = 0.5 * (rel + rel.transpose(0, 2, 1))
    return FrameSplit(ref, cov_frame, float(np.sqrt(max(cov4[3, 3], 0.0))), rel, SM)


def sparse_covariance_operator(graph, values, pose_keys: list[int], rotations: np.ndarray):
    """``V -> Sigma V`` for the (e, n, yaw) errors of the poses ``pose_keys`` (gtsam keys, rotations (N,3,3)
    R_map_vehicle): the graph linearised at ``values``, its information ``J^T J`` from gtsam's sparse Jacobian,
    equilibrated and factored once by SuperLU. gtsam's Pose3 tangent is (rotation, translation) in the body frame:
    an ENU position error is ``R dt``, a heading error ``(R dw)_z``."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    lin = graph.linearize(values)
    ijs = lin.sparseJacobian_()
    dim_of = values.dims()  # gtsam numbers the sparse Jacobian's columns by keys in ascending order
    keys = sorted(int(k) for k in dim_of)
    dims = np.array([int(dim_of[k]) for k in keys])
    offsets = np.concatenate([[0], np.cumsum(dims)])
    n_cols = int(offsets[-1])
    rows, cols, vals = ijs[0].astype(np.int64) - 1, ijs[1].astype(np.int64) - 1, ijs[2]
    keep = cols < n_cols  # the augmented right-hand side (the last column) is not part of the information
    J = sp.csc_matrix((vals[keep], (rows[keep], cols[keep])), shape=(int(rows.max()) + 1, n_cols))
    H = (J.T @ J).tocsc()
    d = np.sqrt(np.maximum(H.diagonal(), 1e-300))
    Dinv = sp.diags(1.0 / d)
    lu = splu((Dinv @ H @ Dinv).tocsc())
    where = {k: int(offsets[n]) for n, k in enumerate(keys)}
    col0 = np.array([where[int(k)] for k in pose_keys])
    R = np.asarray(rotations, float)

    def embed(V: np.ndarray) -> np.ndarray:
        """(N,3,k) ENU directions -> (n_cols,k) tangent-space right-hand sides (E^T V)."""
        out = np.zeros((n_cols, V.shape[2]))
        rot = np.einsum("nij,nk->njk", R[:, 2:3, :], V[:, 2, :])  # yaw row of R^T ... as E^T
        trans = np.einsum("nij,nik->njk", R[:, :2, :], V[:, :2, :])
        for a in range(3):
            out[col0 + a] = rot[:, a, :]
            out[col0 + 3 + a] = trans[:, a, :]
        return out

    def select(X: np.ndarray) -> np.ndarray:
        """(n_cols,k) tangent vectors -> (N,3,k) their (e, n, yaw) at the poses (E X)."""
        rot = np.stack([X[col0 + a] for a in range(3)], axis=1)  # (N,3,k)
        trans = np.stack([X[col0 + 3 + a] for a in range(3)], axis=1)
        out = np.empty((len(col0), 3, X.shape[1]))
        out[:, :2] = np.einsum("nij,njk->nik", R[:, :2, :], trans)
        out[:, 2] = np.einsum("nj,njk->nk", R[:, 2, :], rot)
        return out

    def apply(V: np.ndarray) -> np.ndarray:
        B = embed(np.asarray(V, float))
        X = lu.solve(B / d[:, None]) / d[:, None]
        return select(X)

    return apply



def split_map_frame(problem, poses: np.ndarray, group: np.ndarray, marginals_enu: np.ndarray) -> FrameSplit:
    """``split_frame`` of the first ``len(group)`` poses of a solved ``Problem`` (the map drives; ``group`` their
    drive per pose) from their (N,3,3) ENU marginals, weighted by travel."""
    from stages.posegraph.factors.graph import _key, build_graph

    n = len(group)
    graph, values, _ = build_graph(problem, poses)
    op = sparse_covariance_operator(graph, values, [_key(i) for i in range(n)], poses[:n, :3, :3])
    en = poses[:n, :2, 3]
    return split_frame(op, marginals_enu[:n], en, travel_weights(en, group))
