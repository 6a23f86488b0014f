"""The window of an incremental solve: the held map's poses near the new drives' path, corrected through one rigid
correction of the held map's frame whose prior is the held solution's frame covariance.

Model. The held map's absolute error is mostly common: every pose of a map solved from GNSS carries the bias of the
drives that fixed its frame, averaged over them (``map_frame.py``: ~0.15 m on tiny for one drive, while poses tens
of metres apart agree to millimetres). Independent per-pose priors would let a window bend to meet the new drive
pose by pose; one correction of the frame cannot. A held pose ``k`` of the window is

    T_k = A (A_pub^-1 T_k,pub) d_k

``A``: the frame's anchor, a pose at the window's reference point ``r`` (the centroid of the window's positions, level,
north-aligned); ``A_pub`` its published value; its prior ``N(A_pub, Sigma_frame)``, the held solution's frame
covariance moved to ``r`` (``frame_prior_at``). ``d_k``: the pose's error relative to the frame, its published
``cov_xy_yaw`` (relative to the map frame, floored at 1 mm / 0.1 mrad; up, roll and pitch 1 cm / 1 mrad). In the graph
``A`` is one more pose variable with that prior; a window pose a loop of a new drive reaches is a variable tied to
it by a between factor ``A_pub^-1 T_k,pub`` of information ``d_k``'s (kind ``frame``). The other window poses are
not variables: they follow ``A``. The new drives' absolute evidence (GNSS, survey anchors) reaches ``A`` through the
loops, against their own GNSS bias states: the solve shares a common offset between the held map and the new drives
by their stated covariances, the linearised joint solve's answer for a map whose error is its frame's.

Window. The held poses within ``loops.radius_m`` of a new pose (the reach of a loop), nearest first, at most
``window_cap(n_new)`` = ``WINDOW_POSES_PER_NEW_POSE`` x the new drives' poses. After the solve each window pose moves
by the correction ``D = A A_pub^-1``, applied whole except within ``TAPER_M`` of travel of a run's end that borders a
pose of the same drive outside the window (a linear ramp of the correction's logarithm: no step in a trajectory).
Poses outside the window keep their published values bit for bit; the solve's variables are the new drives' poses,
the window poses loops reach and ``A``: its cost is the new drives', whatever the map's history.

The frame covariance an incremental night records for the next (``frame_record``): ``A``'s marginal when the window
held every pose of the map (then every pose took the correction), else the prior it started from (conservative:
poses outside the window kept the older error). A first (joint) build's is ``map_frame``'s ``cov_shift_rotation``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.posegraph.factors.graph import Between, PosePrior, Problem

WINDOW_POSES_PER_NEW_POSE = 8  # the window's cap: held poses per new pose (tiny: 250 new, 1000 held on night 5)
TAPER_M = 20.0  # m of travel over which the correction ramps in where a window run meets held poses outside it
FRAME_QUANTILE = 0.999  # the frame test's chi-square quantile (``frame_test``)
FRAME_MIN_GAIN = 0.05  # directions in which the loops removed less than this share of the prior variance: untested
_UP_M, _TILT_RAD = 0.01, 1e-3  # relative std of a held pose's up and roll/pitch (not in its cov_xy_yaw)
_FLOOR_M, _FLOOR_RAD = 1e-3, 1e-4


@dataclass(frozen=True)
class FramePrior:
    """The held map's frame covariance: (east m, north m, rotation rad) at ``reference_en_m``, and the up std."""

    reference_en_m: np.ndarray  # (2,)
    cov_en_rot: np.ndarray  # (3,3)
    std_up_m: float
    source: str  # "map_frame" (a joint build's) | "incremental" (a previous night's record)


def frame_prior_of(metadata: dict) -> FramePrior | None:
    """The frame prior the held solution's metadata states: the last incremental night's ``incremental.frame``
    record, else the joint build's ``map_frame``; None when neither (marginals off)."""
    rec = ((metadata or {}).get("incremental") or {}).get("frame")
    if isinstance(rec, dict) and rec.get("next_cov_en_rot") is not None:
        cov = np.asarray(rec["next_cov_en_rot"], float)
        return FramePrior(np.asarray(rec["reference_en_m"], float), cov, float(rec["next_std_up_m"]), "incremental")
    mf = (metadata or {}).get("map_frame")
    if isinstance(mf, dict) and mf.get("cov_shift_rotation") is not None:
        cov = np.asarray(mf["cov_shift_rotation"], float)
        return FramePrior(np.asarray(mf["reference_en_m"], float), cov, float(np.sqrt(0.5 * (cov[0, 0] + cov[1, 1]))),
                          "map_frame")
    return None


def frame_prior_at(prior: FramePrior, point_en_m: np.ndarray) -> np.ndarray:
    """(6,6) covariance of the frame anchor at ``point_en_m`` in gtsam's order (roll, pitch, yaw, east, north, up):
    a rotation theta about the reference moves the point by theta x (p - r)."""
    d = np.asarray(point_en_m, float) - prior.reference_en_m
    J = np.array([[1.0, 0.0, -d[1]], [0.0, 1.0, d[0]], [0.0, 0.0, 1.0]])
    c = J @ prior.cov_en_rot @ J.T  # (east, north, rotation) at the point
    out = np.zeros((6, 6))
    idx = [3, 4, 2]
    out[np.ix_(idx, idx)] = c
    out[0, 0] = out[1, 1] = _TILT_RAD ** 2
    out[5, 5] = prior.std_up_m ** 2
    out = 0.5 * (out + out.T)
    if np.linalg.eigvalsh(out).min() <= 0.0:  # a degenerate statement (a frame fixed exactly): floor it
        out += np.diag([_FLOOR_RAD ** 2] * 3 + [_FLOOR_M ** 2] * 3)
    return out


def window_cap(n_new: int) -> int:
    return WINDOW_POSES_PER_NEW_POSE * int(n_new)


def select_window(held_xy: np.ndarray, new_xy: np.ndarray, radius_m: float, cap: int) -> tuple[np.ndarray, int]:
    """Rows of ``held_xy`` within ``radius_m`` of a new pose, nearest first up to ``cap``, sorted; and how many
    within reach the cap left out."""
    from scipy.spatial import cKDTree

    if not len(held_xy) or not len(new_xy):
        return np.zeros(0, np.int64), 0
    dist, _ = cKDTree(np.asarray(new_xy, float)).query(np.asarray(held_xy, float), distance_upper_bound=radius_m)
    near = np.flatnonzero(np.isfinite(dist))
    if len(near) > cap:
        keep = near[np.argsort(dist[near], kind="stable")[:cap]]
        return np.sort(keep), int(len(near) - cap)
    return near.astype(np.int64), 0


def anchor_pose(window_T: np.ndarray) -> np.ndarray:
    """The frame anchor's published value: level, north-aligned, at the window positions' centroid."""
    A = np.eye(4)
    A[:3, 3] = window_T[:, :3, 3].mean(axis=0)
    return A


def relative_information(cov_xy_yaw: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(6,6) information of a held pose relative to the frame in its body frame (gtsam order: rotation,
    translation) from its published ENU (east, north, yaw) covariance (9 values)."""
    c = np.asarray(cov_xy_yaw, float).reshape(3, 3)
    cov = np.zeros((6, 6))
    cov[np.ix_([3, 4, 2], [3, 4, 2])] = 0.5 * (c + c.T)
    cov[0, 0] = cov[1, 1] = _TILT_RAD ** 2
    cov[5, 5] = _UP_M ** 2
    cov[3, 3] += _FLOOR_M ** 2
    cov[4, 4] += _FLOOR_M ** 2
    cov[2, 2] += _FLOOR_RAD ** 2
    R = T[:3, :3]
    B = np.zeros((6, 6))
    B[:3, :3] = R
    B[3:, 3:] = R
    body = B.T @ cov @ B
    return np.linalg.inv(0.5 * (body + body.T))


@dataclass
class WindowGraph:
    """What ``add_window`` put into a problem: the anchor's index and published value, its prior covariance, the
    window's held rows and how many within reach the cap left out."""

    anchor: int
    A_pub: np.ndarray
    cov_prior: np.ndarray  # (6,6) gtsam order at the anchor
    rows: np.ndarray  # held rows of the window (sorted)
    left_out: int


def add_window(problem: Problem, held_of: dict[int, int], held_T: np.ndarray, held_cov: np.ndarray,
               rows: np.ndarray, left_out: int, prior: FramePrior) -> WindowGraph:
    """Append the frame anchor to ``problem`` and tie to it the graph poses ``held_of`` maps to window rows (graph
    index -> held row; those poses are already variables of ``problem`` at their published values, without
    priors); the held poses a loop reaches outside the window get a ``fixed`` prior at their published value."""
    rows = np.asarray(rows, np.int64)
    in_window = set(rows.tolist())
    A_pub = anchor_pose(held_T[rows])
    cov = frame_prior_at(prior, A_pub[:2, 3])
    a = problem.n_poses
    problem.n_poses += 1
    problem.initial = np.concatenate([problem.initial, A_pub[None]])
    problem.pose_priors.append(PosePrior(a, A_pub, np.linalg.inv(cov), "frame"))
    A_inv = np.linalg.inv(A_pub)
    tight = np.diag([(_FLOOR_M / 10.0) ** -2] * 3 + [_FLOOR_M ** -2] * 3)
    for g, row in held_of.items():
        if row in in_window:
            problem.betweens.append(Between(a, g, A_inv @ held_T[row], relative_information(held_cov[row],
                                                                                           held_T[row]), "frame"))
        else:
            problem.pose_priors.append(PosePrior(g, held_T[row], tight, "fixed"))
    return WindowGraph(a, A_pub, cov, rows, left_out)


def log_pose(T: np.ndarray) -> np.ndarray:
    import gtsam

    return np.asarray(gtsam.Pose3.Logmap(gtsam.Pose3(T)))


def exp_pose(xi: np.ndarray) -> np.ndarray:
    import gtsam

    return gtsam.Pose3.Expmap(np.asarray(xi, float)).matrix()


def taper_weights(held_T: np.ndarray, rows: np.ndarray, drive_of_row: np.ndarray, taper_m: float = TAPER_M
                  ) -> np.ndarray:
    """Weight of the correction at each window row: 1, ramping to 0 over ``taper_m`` of travel towards an end of a
    run of window rows that borders a pose of the same drive outside the window."""
    rows = np.asarray(rows, np.int64)
    w = np.ones(len(rows))
    if not len(rows):
        return w
    in_window = np.zeros(len(held_T), bool)
    in_window[rows] = True
    pos = held_T[:, :3, 3]
    breaks = np.flatnonzero((np.diff(rows) != 1) | (drive_of_row[rows[1:]] != drive_of_row[rows[:-1]])) + 1
    for run in np.split(np.arange(len(rows)), breaks):
        r = rows[run]
        step = np.r_[0.0, np.linalg.norm(np.diff(pos[r], axis=0), axis=1)]
        travel = np.cumsum(step)
        first, last = r[0], r[-1]
        dist = np.full(len(r), np.inf)
        if first > 0 and drive_of_row[first - 1] == drive_of_row[first] and not in_window[first - 1]:
            dist = np.minimum(dist, travel + np.linalg.norm(pos[first] - pos[first - 1]))
        if last + 1 < len(held_T) and drive_of_row[last + 1] == drive_of_row[last] and not in_window[last + 1]:
            dist = np.minimum(dist, travel[-1] - travel + np.linalg.norm(pos[last + 1] - pos[last]))
        w[run] = np.clip(dist / taper_m, 0.0, 1.0) if taper_m > 0 else 1.0
    return w


def correct_window(held_T: np.ndarray, win: WindowGraph, A_sol: np.ndarray, drive_of_row: np.ndarray,
                   taper_m: float = TAPER_M) -> np.ndarray:
    """The held poses with the window's rows moved by the frame correction (``taper_weights``); the other rows
    are the same array values."""
    out = held_T.copy()
    xi = log_pose(np.linalg.inv(win.A_pub) @ A_sol)  # the correction in the anchor's frame
    for row, w in zip(win.rows, taper_weights(held_T, win.rows, drive_of_row, taper_m)):
        D = win.A_pub @ exp_pose(w * xi) @ np.linalg.inv(win.A_pub)
        out[row] = D @ held_T[row]
    return out


def anchor_marginal(problem: Problem, poses: np.ndarray, anchor: int) -> np.ndarray:
    """(6,6) marginal covariance of the anchor at ``poses`` (gtsam's body frame = ENU: the anchor is level)."""
    import gtsam

    from stages.posegraph.factors.graph import _key, build_graph

    graph, values, _ = build_graph(problem, poses)
    try:
        return np.asarray(gtsam.Marginals(graph, values).marginalCovariance(_key(anchor)))
    except RuntimeError:
        tree = graph.linearize(values).eliminateMultifrontal(gtsam.Ordering.OrderingType.COLAMD, gtsam.EliminateQR)
        return np.asarray(tree.marginalCovariance(_key(anchor)))


def frame_held(problem: Problem, win: WindowGraph, A_sol: np.ndarray) -> Problem:
    """A copy of ``problem`` whose anchor is held at ``A_sol`` (tight prior): its marginals are relative to the map
    frame, as the held map's published covariances are."""
    tight = np.diag([(_FLOOR_M / 10.0) ** -2] * 3 + [_FLOOR_M ** -2] * 3)
    priors = [PosePrior(p.i, A_sol, tight, "fixed") if p.kind == "frame" else p for p in problem.pose_priors]
    return Problem(problem.n_poses, problem.initial, list(problem.betweens), list(problem.positions),
                   list(problem.attitudes), priors, problem.n_biases, list(problem.bias_links),
                   list(problem.bias_priors))


def frame_test(delta: np.ndarray, cov_prior: np.ndarray, cov_post: np.ndarray, *, quantile: float = FRAME_QUANTILE,
               min_gain: float = FRAME_MIN_GAIN) -> dict:
    """Is the held map's frame where it says it is? ``delta``: the anchor's correction (gtsam order, 6), prior and
    posterior covariances (6,6). Horizontal part (east, north, yaw): under a consistent map the correction is
    N(0, Sigma_prior - Sigma_post) (the innovation a Kalman update makes); whitened by the prior, the directions in
    which the new drives removed at least ``min_gain`` of its variance are tested,

        T = sum_i (u_i^T L^-1 delta)^2 / lambda_i   (lambda_i, u_i: eigenpairs of I - L^-1 Sigma_post L^-T)

    against ``chi2.ppf(quantile, dof)``. Large: the held map is off by more than its frame covariance states; the
    window moved the poses it holds, but the map's poses outside it keep that error (reoptimize)."""
    from scipy.stats import chi2

    idx = [3, 4, 2]
    d = np.asarray(delta, float)[idx]
    P = np.asarray(cov_prior, float)[np.ix_(idx, idx)]
    Q = np.asarray(cov_post, float)[np.ix_(idx, idx)]
    L = np.linalg.cholesky(0.5 * (P + P.T))
    Li = np.linalg.inv(L)
    gain = np.eye(3) - Li @ (0.5 * (Q + Q.T)) @ Li.T
    lam, U = np.linalg.eigh(0.5 * (gain + gain.T))
    keep = lam >= min_gain
    z = U.T @ (Li @ d)
    t = float(np.sum(z[keep] ** 2 / lam[keep]))
    dof = int(keep.sum())
    threshold = float(chi2.ppf(quantile, dof)) if dof else None
    return {"shift_en_m": [round(float(d[0]), 4), round(float(d[1]), 4)], "rotation_deg": round(float(np.degrees(
        d[2])), 4), "chi2": round(t, 2), "dof": dof, "threshold": None if threshold is None else round(threshold, 2),
        "advised": bool(dof and t > threshold)}


def frame_record(win: WindowGraph, A_sol: np.ndarray, cov_post: np.ndarray, n_held: int, prior: FramePrior,
                 drift: dict) -> dict:
    """The ``incremental.frame`` record: the window, the correction and its test (``frame_test``), and the frame
    covariance the next night starts from (module docstring)."""
    idx = [3, 4, 2]
    whole = len(win.rows) == n_held and win.left_out == 0
    cov_next = cov_post if whole else win.cov_prior
    moved = np.linalg.norm(A_sol[:2, 3] - win.A_pub[:2, 3])
    return {**drift, "window_poses": int(len(win.rows)), "held_poses": int(n_held), "left_out": int(win.left_out),
            "anchor_moved_m": round(float(moved), 4), "prior_source": prior.source,
            "prior_std_en_m": [round(float(np.sqrt(win.cov_prior[i, i])), 4) for i in (3, 4)],
            "posterior_std_en_m": [round(float(np.sqrt(cov_post[i, i])), 4) for i in (3, 4)],
            "reference_en_m": [float(v) for v in A_sol[:2, 3]],
            "next_cov_en_rot": [[float(v) for v in row] for row in cov_next[np.ix_(idx, idx)]],
            "next_std_up_m": float(np.sqrt(cov_next[5, 5]))}
