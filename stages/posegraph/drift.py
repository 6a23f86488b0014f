"""The drift trigger of an incremental solve: does a region of the held map disagree with the new drives' loops?

An incremental rebuild holds the map's poses; a new drive tied to the map by loops and to the world by its own
GNSS, survey anchors and odometry has to bend where the held map is wrong. The statistic, per region of the held map
(``regions.partition_poses`` of the held poses, the regions ``maps reoptimize`` would solve): the loops of the new
drives onto held poses of the region, whitened by their information, at the incremental solution,

    T = sum over those k loops of |e|^2,   e = L^T Log(T_ij^-1 T_i^-1 T_j)   (6 per loop)

against ``scale x chi2.ppf(1 - (1 - quantile) / m, 6 k)``, m the regions the night's loops reach. The test: under a
map that agrees with the loops, T is ``s x chi2(6 k)``, ``s`` the loops' variance factor (their information is
ICP's, optimistic by ``s``; 6 k is an upper bound of the degrees of freedom: the new poses were fitted to the same
loops, which only lowers T); one night tests m regions, so each is tested at ``(1 - quantile) / m`` (Bonferroni) and
``1 - quantile`` bounds the night's false-alarm rate. ``scale`` bounds ``s``: the largest one-sided 99 % upper
confidence bound of ``s`` (``T / chi2.ppf(0.01, 6 k)``) over the clean nights of the calibration seeds
(``bench.bench_incremental drift-threshold``; docs/maintenance.md "The drift trigger's threshold"). ``advised``: the
regions whose T exceeds it. Pure: factor lists and arrays in, a dict out.
"""
from __future__ import annotations

import numpy as np

from stages.posegraph.factors.graph import Problem
from stages.posegraph.regions import partition_poses

DRIFT_QUANTILE = 0.999
DRIFT_SCALE = 1.6  # the loops' variance factor bound, calibration seeds tiny 211, 353 (module docstring)
DRIFT_REGION_MAX_POSES = 600  # = ``maps reoptimize``'s default region size


def whitened_loop_errors(betweens, poses: np.ndarray) -> np.ndarray:
    """(K,6) whitened error of each between factor at ``poses`` (gtsam order: rotation, translation)."""
    import gtsam

    out = np.zeros((len(betweens), 6))
    for n, b in enumerate(betweens):
        est = gtsam.Pose3(poses[b.i]).between(gtsam.Pose3(poses[b.j]))
        err = gtsam.Pose3.Logmap(gtsam.Pose3(b.T_i_j).between(est))
        L = np.linalg.cholesky(0.5 * (b.information + b.information.T))
        out[n] = L.T @ err
    return out


def loop_drift(problem: Problem, poses: np.ndarray, n_new: int, held_rows: dict[int, int], held_xy: np.ndarray,
               *, max_poses: int = DRIFT_REGION_MAX_POSES, quantile: float = DRIFT_QUANTILE,
               scale: float = DRIFT_SCALE) -> dict:
    """The statistic per region (module docstring). ``problem``/``poses``: the incremental graph and its solution
    (poses 0..n_new-1 the new drives', the others held map poses); ``held_rows[g]``: the row in ``held_xy`` (every
    held pose's east/north, m) of graph pose g >= n_new."""
    from scipy.stats import chi2

    labels = partition_poses(held_xy, max_poses)
    loops = [b for b in problem.betweens if b.kind == "loop" and ((b.i < n_new) != (b.j < n_new))]
    region_of = np.array([labels[held_rows[b.j if b.j >= n_new else b.i]] for b in loops], np.int64)
    sq = np.sum(whitened_loop_errors(loops, poses) ** 2, axis=1) if loops else np.zeros(0)
    rows = []
    tested = len(set(region_of.tolist()))  # m: the regions this night's loops reach (Bonferroni)
    for r in range(int(labels.max()) + 1 if len(labels) else 0):
        sel = region_of == r
        k = int(sel.sum())
        centre = held_xy[labels == r].mean(axis=0)
        if k == 0:
            rows.append({"region": r, "center_en_m": [round(float(c), 1) for c in centre], "loops": 0,
                         "chi2": 0.0, "dof": 0, "threshold": None, "advised": False})
            continue
        t, dof = float(sq[sel].sum()), 6 * k
        threshold = float(scale * chi2.ppf(1.0 - (1.0 - quantile) / tested, dof))
        rows.append({"region": r, "center_en_m": [round(float(c), 1) for c in centre], "loops": k,
                     "chi2": round(t, 2), "dof": dof, "threshold": round(threshold, 2), "advised": t > threshold})
    return {"statistic": "chi2 of the new drives' loops onto the held map (whitened, at the incremental solution)",
            "quantile": quantile, "scale": scale, "regions_tested": tested, "region_max_poses": max_poses,
            "regions": rows,
            "advised": [row["region"] for row in rows if row["advised"]]}
