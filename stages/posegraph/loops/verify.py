"""Loop-closure verification by ICP with fitness, residual, correction and two-start consistency gates, of one
candidate (``verify_loop``) or of many in parallel (``verify_candidates``); accepted loops as graph factors.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.common.geometry import se3_inverse
from stages.common.ground_plane import on_road_planes, split_road
from stages.common.registration import (
    floor_information,
    plane_hessian,
    prepare_cloud,
    register_coarse_to_fine,
    score_alignment,
)
from stages.posegraph.config import LoopConfig, LoopVerifyConfig
from stages.posegraph.factors.graph import Between


@dataclass(frozen=True)
class Verdict:
    accepted: bool
    reason: str
    T_i_j: np.ndarray
    fitness: float
    inlier_rmse_m: float
    information: np.ndarray


@dataclass
class LoopRecord:
    i: int
    j: int
    prior_distance_m: float
    fitness: float
    inlier_rmse_m: float
    T_i_j: np.ndarray
    accepted: bool
    reason: str
    information: np.ndarray | None = None  # 6x6 gtsam order, body frame of T_i_j


POINT_SIGMA_M = 0.05  # per-point residual std of a loop's information (``register_coarse_to_fine``'s default)
VERIFY_BLOCK = 32  # at most this many candidates per task of verify_from_store (one block's clouds are resident)


def block_size(n_candidates: int, workers: int) -> int:
    """Candidates per block: about four blocks per worker, so that the last block to finish leaves the others idle
    for an eighth of the work or less (demo's 193 reference-drive candidates went in 7 blocks of 32 to 2 workers:
    the last one ran alone), between 4 and ``VERIFY_BLOCK``."""
    return int(min(VERIFY_BLOCK, max(4, -(-n_candidates // (4 * max(1, workers))))))


def _verify_item(item) -> object:
    """One candidate's ICP verification (module level: runs in a pool process or on a cluster worker)."""
    cloud_i, cloud_j, prior, cfg = item
    return verify_loop(cloud_i, cloud_j, prior, cfg)


def _verify_block(item) -> list[Verdict]:
    """A block of candidates: this process loads the clouds they use (``clouds._clouds_item``, from the drives and
    loader ``clouds._use_drives`` left in its state) and verifies each; the clouds are dropped with the block."""
    from stages.posegraph.loops.clouds import _clouds_item

    chunk, voxel_m, pairs, cfg = item
    clouds = _clouds_item((chunk, voxel_m))
    prepared: dict = {}  # a scan in several candidates of the block is prepared once per voxel size
    splits: dict = {}  # and split into road and structure once
    return [verify_loop(clouds[i], clouds[j], prior, cfg, prepared=prepared, keys=(j, i), splits=splits)
            for i, j, prior in pairs]


def verify_from_store(candidates, poses: np.ndarray, drives, offsets: np.ndarray, load, cfg: LoopConfig,
                      fixed: dict[int, np.ndarray] | None = None, progress=None,
                      block: int | None = None) -> list[LoopRecord]:
    """``verify_candidates`` without the clouds in this process: the candidates, ordered by their first pose, go in
    blocks of ``block`` (default ``block_size``) to the workers (``pipeline.parallel.parallel_map``), each of which
    reads and prepares the clouds of its block itself. Memory is one block's clouds per worker, not every candidate's
    cloud at once (on gangnam 889 candidates: the clouds of ~1,500 scans were held by the stage's process through the
    whole solve). The verdicts equal ``verify_candidates``' on ``vehicle_clouds``' clouds (each cloud is computed
    alone)."""
    from pipeline.parallel import default_workers, parallel_map
    from stages.posegraph.loops.clouds import _use_drives, cloud_requests

    fixed = fixed or {}
    n = len(candidates)
    block = block or block_size(n, default_workers())
    order = sorted(range(n), key=lambda m: (min(candidates[m].i, candidates[m].j), max(candidates[m].i,
                                                                                        candidates[m].j), m))
    items, members = [], []
    for start in range(0, n, block):
        sel = order[start:start + block]
        chunk = cloud_requests(offsets, np.unique([candidates[m].i for m in sel] + [candidates[m].j for m in sel]))
        pairs = []
        for m in sel:
            c = candidates[m]
            Ti = fixed.get(c.i, poses[c.i] if c.i < len(poses) else None)
            Tj = fixed.get(c.j, poses[c.j] if c.j < len(poses) else None)
            pairs.append((c.i, c.j, se3_inverse(Ti) @ Tj))
        items.append((chunk, cfg.verify.voxel_m, pairs, cfg.verify))
        members.append(sel)
    step = (lambda done, total: progress(min(done * block, n), n)) if progress else None
    blocks = parallel_map(_verify_block, items, workers=cfg.workers(n), initializer=_use_drives,
                          initargs=(drives, load), progress=step)
    verdicts: list = [None] * n
    for sel, got in zip(members, blocks):
        for m, v in zip(sel, got):
            verdicts[m] = v
    return [LoopRecord(c.i, c.j, c.prior_distance_m, v.fitness, v.inlier_rmse_m, v.T_i_j, v.accepted, v.reason,
                       v.information) for c, v in zip(candidates, verdicts)]


def verify_candidates(candidates, poses: np.ndarray, clouds: dict[int, np.ndarray], cfg: LoopConfig,
                      fixed: dict[int, np.ndarray] | None = None, progress=None) -> list[LoopRecord]:
    """ICP-verify each candidate from the current estimate's relative pose (``fixed`` poses override). The
    candidates are independent: they run through ``pipeline.parallel.parallel_map`` (processes here, tasks on
    a cluster) when there are at least ``cfg.parallel_min_items`` of them; the verdicts do not depend on it."""
    from pipeline.parallel import parallel_map

    fixed = fixed or {}
    items = []
    for c in candidates:
        Ti = fixed.get(c.i, poses[c.i] if c.i < len(poses) else None)
        Tj = fixed.get(c.j, poses[c.j] if c.j < len(poses) else None)
        items.append((clouds[c.i], clouds[c.j], se3_inverse(Ti) @ Tj, cfg.verify))
    verdicts = parallel_map(_verify_item, items, workers=cfg.workers(len(items)), progress=progress)
    return [LoopRecord(c.i, c.j, c.prior_distance_m, v.fitness, v.inlier_rmse_m, v.T_i_j, v.accepted, v.reason,
                       v.information) for c, v in zip(candidates, verdicts)]


def loop_betweens(loops: list[LoopRecord], cfg: LoopConfig) -> list[Between]:
    """The accepted loops as between factors under the loop kernel (none under GNC, which weighs them itself)."""
    robust = "none" if cfg.kernel == "gnc" else cfg.kernel
    return [Between(r.i, r.j, r.T_i_j, r.information, "loop", robust, cfg.kernel_k) for r in loops if r.accepted]


def verify_loop(points_i_vehicle: np.ndarray, points_j_vehicle: np.ndarray, T_i_j_prior: np.ndarray,
                cfg: LoopVerifyConfig, prepared: dict | None = None, keys: tuple = ("j", "i"),
                splits: dict | None = None) -> Verdict:
    """``verify_once`` of the whole clouds; with ``cfg.ground_split`` an accepted loop is verified again on the
    structure above the road planes, started from the first result, and that result replaces it when it is accepted
    and moves the loop less than ``cfg.ground_split_max_shift_m`` (the road pulls close scans towards zero offset by
    centimetres; in a street without cross structure the structure alone slides metres, and the whole clouds' result
    stands)."""
    prepared = {} if prepared is None else prepared  # the whole clouds, prepared once for both verifications
    whole = verify_once(points_i_vehicle, points_j_vehicle, T_i_j_prior, cfg, False, prepared, keys, splits)
    if not (cfg.ground_split and whole.accepted):
        return whole
    split = verify_once(points_i_vehicle, points_j_vehicle, whole.T_i_j, cfg, True, prepared, keys, splits)
    if split.accepted and np.linalg.norm(split.T_i_j[:3, 3] - whole.T_i_j[:3, 3]) < cfg.ground_split_max_shift_m:
        return split
    return whole


def verify_once(points_i_vehicle: np.ndarray, points_j_vehicle: np.ndarray, T_i_j_prior: np.ndarray,
                cfg: LoopVerifyConfig, ground_split: bool = False, prepared: dict | None = None,
                keys: tuple = ("j", "i"), splits: dict | None = None) -> Verdict:
    """Coarse-to-fine GICP of scan j onto scan i from the prior relative pose (1-2 m off between passes), and
    again from a start shifted by 1 m along and 0.7 m across; accepted only when both agree, at least
    ``min_fitness`` of the scan lies on the other scan's surfaces (``score_alignment``) with a point-to-plane
    RMS below ``max_rmse_m``, and the correction stays inside the prior's envelope. ``Verdict.fitness`` and
    ``inlier_rmse_m`` are that inlier share and plane RMS. Both starts use the same prepared clouds (``prepared``, keyed
    by ``keys`` = (scan j's key, scan i's key); a caller's dict shares them across candidates).

    The second start runs its coarse stage first: when that lands within ``consistency_m`` of the first start's
    coarse result, the two agree (the fine stages go on from the same place), and its fine stages are not run; else
    they are, and the two final results are compared as before. The fine stages are four fifths of a start's
    GICP time (demo seed 1: 33 of 40 ms).

    With ``ground_split`` (``loops.verify.ground_split``, off by default: docs/posegraph.md) the GICP
    registers the structure above each scan's road plane only, and the two road planes give height, roll and pitch
    (``ground_plane.align_ground_planes``, as the odometry's edges). The road's noise is centred on each sensor (a
    divergent beam spreads its range along the ray on oblique ground), and it pulled a registration of two scans a
    few metres apart towards zero offset (demo seed 2: the drive's end onto its start, 0.15 m apart in truth,
    measured 0.035 m; 2.64 m measured 2.50 m; from the truth's relative pose as from the estimate's). The score is
    taken on the whole clouds at the result, so the gates keep their meaning; the information adds the ground's on
    the target's road plane. ``splits`` keeps each scan's split under its key, as ``prepared`` keeps its clouds."""
    voxel_m, max_corr_m, min_sigma_m, min_sigma_rad = cfg.voxel_m, cfg.max_corr_m, cfg.min_sigma_m, cfg.min_sigma_rad
    min_fitness, max_rmse_m = cfg.min_fitness, cfg.max_rmse_m
    coarse = ((cfg.coarse_voxel_m, cfg.coarse_corr_m),)
    fine = ((voxel_m, max_corr_m), (voxel_m, max_corr_m / 2))
    src_m, tgt_m, road = points_j_vehicle, points_i_vehicle, None
    if ground_split:
        cache = {} if splits is None else splits
        for key, pts in zip(keys, (points_j_vehicle, points_i_vehicle)):
            if key not in cache:
                cache[key] = split_road(np.asarray(pts, np.float64), np.eye(4), cfg.ground_tolerance_m)
        sj, si = cache[keys[0]], cache[keys[1]]
        if sj.plane is not None and si.plane is not None and min(len(sj.structure_m), len(si.structure_m)) >= 100:
            src_m, tgt_m, road = sj.structure_m, si.structure_m, (sj, si)
    reg = dict(max_iterations=40, point_sigma_m=POINT_SIGMA_M, min_sigma_m=min_sigma_m, min_sigma_rad=min_sigma_rad,
               relative_tolerance=cfg.relative_tolerance, prepared={} if prepared is None else prepared,
               keys=keys if road is None else tuple(("structure", k) for k in keys))
    res_coarse, source, target = register_coarse_to_fine(src_m, tgt_m, T_i_j_prior, stages=coarse, **reg)
    res = res_coarse
    if res_coarse.converged:
        res, source, target = register_coarse_to_fine(src_m, tgt_m, res_coarse.T_target_source, stages=fine, **reg)
    T = res.T_target_source if road is None else on_road_planes(res.T_target_source, res.converged, road[0].plane,
                                                                  road[1].plane)
    if road is not None:  # scored on the whole clouds (the gates' meaning), prepared once per scan as the others
        cache = reg["prepared"]
        for key, pts in zip(keys, (points_j_vehicle, points_i_vehicle)):
            if (key, voxel_m) not in cache:
                cache[(key, voxel_m)] = prepare_cloud(pts, voxel_m)
        source, target = cache[(keys[0], voxel_m)], cache[(keys[1], voxel_m)]
    score = score_alignment(source, target, T, cfg.inlier_m, cfg.plane_tol_m)
    correction = se3_inverse(T_i_j_prior) @ T
    corr_m = float(np.linalg.norm(correction[:3, 3]))
    corr_rad = float(np.arccos(np.clip((np.trace(correction[:3, :3]) - 1) / 2, -1, 1)))
    if road is not None and res.converged:
        H = res.hessian + plane_hessian(road[0].ground_m, road[1].ground_m, road[1].plane.normal, T, max_corr_m,
                                        POINT_SIGMA_M)
        # floored twice, as the whole clouds' (``register_clouds`` floors its Hessian, and the line below again)
        info = floor_information(floor_information(H, min_sigma_m, min_sigma_rad), min_sigma_m, min_sigma_rad)
    else:
        info = floor_information(res.information, min_sigma_m, min_sigma_rad)
    reason = "accepted"
    if not res.converged or score.inlier_share < min_fitness:
        reason = f"inlier share {score.inlier_share:.2f} < {min_fitness:.2f}"
    elif score.plane_rmse_m > max_rmse_m:
        reason = f"point-to-plane rmse {score.plane_rmse_m:.3f} m > {max_rmse_m:.3f} m"
    elif corr_m > cfg.max_correction_m or corr_rad > cfg.max_correction_rad:
        reason = f"correction {corr_m:.2f} m / {np.rad2deg(corr_rad):.1f} deg beyond the prior's envelope"
    else:
        shifted = T_i_j_prior.copy()
        shifted[:3, 3] += T_i_j_prior[:3, :3] @ np.array([1.0, -0.7, 0.0])
        res2, _, _ = register_coarse_to_fine(src_m, tgt_m, shifted, stages=coarse, **reg)
        gap_m = _gap_m(res2, res_coarse)
        if gap_m > cfg.consistency_m and res2.converged:
            res2, _, _ = register_coarse_to_fine(src_m, tgt_m, res2.T_target_source, stages=fine, **reg)
            gap_m = _gap_m(res2, res)
        if gap_m > cfg.consistency_m:
            reason = f"ambiguous: two ICP starts disagree by {gap_m:.2f} m"
    return Verdict(reason == "accepted", reason, T, score.inlier_share, score.plane_rmse_m, info)


def _gap_m(a, b) -> float:
    """Distance between two registrations' translations (inf when either did not converge)."""
    if not (a.converged and b.converged):
        return float("inf")
    return float(np.linalg.norm(a.T_target_source[:3, 3] - b.T_target_source[:3, 3]))
