"""The wide loop search: where nothing absolute has held a drive for a while (no GNSS fix, no ENU prior, no survey
anchor), its two passes of a street may sit tens of metres apart in the estimate; the fixed ``loops.radius_m`` misses
them. Here the search region of a query pose is the estimate's uncertainty of the relative position
(``uncertainty.ChainCovariance``): a target is a candidate when its estimated offset, less the fixed radius (the
scans' overlap), lies within ``wide_sigmas`` Mahalanobis of zero, and only where that uncertainty's std exceeds
``wide_min_sigma_m`` (below it the fixed radius covers ``wide_sigmas`` sigma, so drives with GNSS are searched as
before). Such a candidate's relative pose is not known to metres: it is verified from a global registration (FPFH +
RANSAC on the structure above the road, ``stages.common.registration_global``) whose result must itself lie within
the gate, then by the usual GICP verification from there (fitness, RMSE, two starts; ``verify.verify_loop``).
Accepted loops of the loosely held drives must then agree pairwise (``pcm.consistent_set``, Mangelson et al. 2018):
the largest set whose cycles through the odometry close within their covariance is kept, the others rejected; a
loop no other loop nearby confirms is not enough (``wide_min_consistent``). The map is solved with them, and the
search runs again on the tighter estimate (rounds): the relative uncertainty is now capped through the accepted
loops, so the gate narrows to the fixed radius near them, and the fixed-radius search on the solved estimate (with
the ordinary verification) takes the candidates there.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from stages.common.geometry import se3_inverse
from stages.posegraph.config import LoopConfig
from stages.posegraph.loops.candidates import Candidate, find_candidates, keyframes_by_travel, travel_m
from stages.posegraph.loops.pcm import consistent_set
from stages.posegraph.loops.uncertainty import ChainCovariance, chain_covariance
from stages.posegraph.loops.verify import LoopRecord, verify_from_store

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class WideCandidate:
    i: int
    j: int
    prior_distance_m: float
    cov_en_m2: np.ndarray  # (2,2) the relative position's covariance (map east/north)
    yaw_var_rad2: float


def loose_drives(problem, drives) -> np.ndarray:
    """Per drive: True when nothing absolute holds it along its way (no GNSS fix, no ENU prior trajectory, no survey
    anchor), only a start pose and its odometry (and a local prior's shape)."""
    offsets = np.cumsum([0] + [d.n for d in drives])
    held = np.array([bool(d.gnss_valid.any()) for d in drives])
    for p in problem.pose_priors:
        if p.kind in ("prior", "survey", "fixed"):
            held[np.searchsorted(offsets, p.i, side="right") - 1] = True
    return ~held


def capped_relative(chain: ChainCovariance, q: int, targets: np.ndarray, loops: list[LoopRecord]) -> np.ndarray:
    """``chain.relative`` capped through each accepted loop (a, b): the chain q -> a plus b -> target, either way
    round, when its trace is smaller (the tighter estimate after a round)."""
    cov = chain.relative(q, targets)
    tr = np.trace(cov, axis1=1, axis2=2)
    for r in loops:
        for a, b in ((r.i, r.j), (r.j, r.i)):
            if chain.group[a] != chain.group[q]:
                continue
            via = chain.same_drive(q, np.array([a]))[0] + chain.relative(b, targets)
            t = np.trace(via, axis1=1, axis2=2)
            better = t < tr
            cov[better], tr[better] = via[better], t[better]
    return cov


def find_wide_candidates(chain: ChainCovariance, stamps_s: np.ndarray, query: np.ndarray, travel: np.ndarray,
                         cfg: LoopConfig, loops: list[LoopRecord] = (), tried: set = frozenset()
                         ) -> list[WideCandidate]:
    """Per query pose of a loosely held drive, up to ``cfg.wide.max_per_scan`` targets of other passes inside the
    Mahalanobis gate (module docstring) where the relative std exceeds ``cfg.wide.min_sigma_m`` (within the fixed
    radius too: the estimate is metres off there, the ordinary verification's correction envelope would refuse the
    true loop), nearest in Mahalanobis distance first, at least ``cfg.wide.target_spacing_m`` of travel apart on
    their pass; pairs in ``tried`` are skipped."""
    pos = chain.positions_en
    n = len(pos)
    out: list[WideCandidate] = []
    seen: set = set()
    accepted = [r for r in loops if r.accepted]
    for q in np.asarray(query, np.int64):
        if chain.absolute[q]:
            continue
        t = np.arange(n)
        other = (chain.group != chain.group[q]) | (np.abs(stamps_s - stamps_s[q]) >= cfg.min_separation_s)
        t = t[other]
        v = pos[t] - pos[q]
        d = np.linalg.norm(v, axis=1)
        if len(t) == 0:
            continue
        cov = capped_relative(chain, int(q), t, accepted)
        a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
        big = 0.5 * (a + c) + np.sqrt(0.25 * (a - c) ** 2 + b * b)
        wide = big >= cfg.wide.min_sigma_m ** 2
        shrunk = v * np.maximum(0.0, 1.0 - cfg.radius_m / np.maximum(d, 1e-9))[:, None]
        det = a * c - b * b
        det = np.where(det > 1e-12, det, 1e-12)
        m2 = (c * shrunk[:, 0] ** 2 - 2 * b * shrunk[:, 0] * shrunk[:, 1] + a * shrunk[:, 1] ** 2) / det
        keep = wide & (m2 <= cfg.wide.sigmas ** 2)
        if not keep.any():
            continue
        order = np.argsort(m2[keep], kind="stable")
        t_k, d_k, cov_k = t[keep][order], d[keep][order], cov[keep][order]
        chosen: list[int] = []
        for tt, dd, cc in zip(t_k, d_k, cov_k):
            if any(chain.group[tt] == chain.group[x] and abs(travel[tt] - travel[x]) < cfg.wide.target_spacing_m
                   for x in chosen):
                continue
            chosen.append(int(tt))
            pair = (min(int(q), int(tt)), max(int(q), int(tt)))
            if pair not in tried and pair not in seen:
                seen.add(pair)
                yaw_var = float(chain.s0[pair[1]] - chain.s0[pair[0]]) if chain.group[q] == chain.group[tt] \
                    else float(chain.s0[q] - chain.s0[chain.start[q]] + chain.s0[tt] - chain.s0[chain.start[tt]]
                               + chain.start_var_rad2[q] + chain.start_var_rad2[tt])
                out.append(WideCandidate(pair[0], pair[1], float(dd), cc, yaw_var))
            if len(chosen) >= cfg.wide.max_per_scan:
                break
    return out


def _verify_wide_block(item) -> list:
    """A block of wide candidates: their clouds loaded in this process, each verified by ``verify_wide``."""
    from stages.posegraph.loops.clouds import _clouds_item

    chunk, voxel_m, pairs, cfg = item
    clouds = _clouds_item((chunk, voxel_m))
    return [verify_wide(clouds[i], clouds[j], prior, cov_i, yaw_var, cfg) for i, j, prior, cov_i, yaw_var in pairs]


def verify_wide(points_i: np.ndarray, points_j: np.ndarray, T_i_j_prior: np.ndarray, cov_i_m2: np.ndarray,
                yaw_var_rad2: float, cfg: LoopConfig):
    """One wide candidate: FPFH + RANSAC of the structure clouds (scan j onto scan i), gated by the prior's
    uncertainty (``cov_i_m2``: the relative position's covariance in scan i's frame; ``yaw_var_rad2``), then the
    GICP verification from that start. Returns a ``verify.Verdict``."""
    from stages.common.ground_plane import split_road
    from stages.common.registration_global import register_global
    from stages.posegraph.loops.verify import Verdict, verify_loop

    v = cfg.verify
    structure = [split_road(np.asarray(p, np.float64), np.eye(4), v.ground_tolerance_m).structure_m
                 for p in (points_j, points_i)]
    voxel = cfg.wide.global_voxel_m
    gm = register_global(structure[0], structure[1], voxel_m=voxel, normal_radius_m=2 * voxel,
                         feature_radius_m=5 * voxel, max_corr_m=1.5 * voxel, seed=0)
    if gm.n_correspondences < 3:
        return Verdict(False, "global registration found no match", gm.T_target_source, 0.0, float("inf"),
                       np.eye(6))
    diff = gm.T_target_source[:2, 3] - T_i_j_prior[:2, 3]
    cov = cov_i_m2 + np.eye(2) * cfg.radius_m ** 2 / 4  # the overlap's own slack: half the fixed radius, 1 sigma
    m2 = float(diff @ np.linalg.solve(cov, diff))
    dyaw = np.arctan2(gm.T_target_source[1, 0], gm.T_target_source[0, 0]) - \
        np.arctan2(T_i_j_prior[1, 0], T_i_j_prior[0, 0])
    dyaw = float((dyaw + np.pi) % (2 * np.pi) - np.pi)
    yaw_lim = cfg.wide.sigmas * np.sqrt(yaw_var_rad2 + np.radians(cfg.wide.yaw_slack_deg) ** 2)
    if m2 > cfg.wide.sigmas ** 2 or abs(dyaw) > yaw_lim:
        return Verdict(False, f"global match outside the gate ({np.sqrt(m2):.1f} sigma, "
                              f"{np.degrees(dyaw):.1f} deg)", gm.T_target_source, gm.fitness, float("inf"), np.eye(6))
    return verify_loop(points_i, points_j, gm.T_target_source, v)


def verify_wide_from_store(cands: list[WideCandidate], poses: np.ndarray, drives, offsets: np.ndarray, load,
                           cfg: LoopConfig) -> list[LoopRecord]:
    """``verify_wide`` of every candidate, in blocks through ``parallel_map`` (each worker loads its block's clouds,
    as ``verify.verify_from_store``)."""
    from pipeline.parallel import default_workers, parallel_map
    from stages.posegraph.loops.clouds import _use_drives, cloud_requests
    from stages.posegraph.loops.verify import block_size

    n = len(cands)
    if n == 0:
        return []
    block = block_size(n, default_workers())
    order = sorted(range(n), key=lambda m: (cands[m].i, cands[m].j))
    items, members = [], []
    for start in range(0, n, block):
        sel = order[start:start + block]
        chunk = cloud_requests(offsets, np.unique([cands[m].i for m in sel] + [cands[m].j for m in sel]))
        pairs = []
        for m in sel:
            c = cands[m]
            Ri = poses[c.i, :2, :2]
            pairs.append((c.i, c.j, se3_inverse(poses[c.i]) @ poses[c.j], Ri.T @ c.cov_en_m2 @ Ri, c.yaw_var_rad2))
        items.append((chunk, cfg.verify.voxel_m, pairs, cfg))
        members.append(sel)
    blocks = parallel_map(_verify_wide_block, items, workers=cfg.workers(n), initializer=_use_drives,
                          initargs=(drives, load))
    verdicts: list = [None] * n
    for sel, got in zip(members, blocks):
        for m, v in zip(sel, got):
            verdicts[m] = v
    return [LoopRecord(c.i, c.j, c.prior_distance_m, v.fitness, v.inlier_rmse_m, v.T_i_j, v.accepted,
                       v.reason if v.accepted else f"wide: {v.reason}", v.information)
            for c, v in zip(cands, verdicts)]


def close_wide_loops(problem, poses: np.ndarray, drives, load, cfg: LoopConfig, loops: list[LoopRecord],
                     solve, verify_wide_fn=None, verify_fn=None, say=None) -> tuple[list[LoopRecord], np.ndarray, dict]:
    """The rounds of the wide search (module docstring) after the fixed-radius loops ``loops`` of the pass-1
    estimate ``poses``: returns every loop record (the fixed ones first), the last solved estimate and a summary.
    ``solve(loops, initial) -> poses`` solves the graph with loops; ``verify_wide_fn(cands, poses)`` and
    ``verify_fn(cands, poses)`` verify wide and fixed-radius candidates (default: from the drives' scans; tests
    give oracles). Without a loosely held drive nothing changes (the loops and ``poses`` come back as given)."""
    say = say or (lambda *a, **k: None)
    loose = loose_drives(problem, drives)
    summary = {"rounds": 0, "wide_candidates": 0, "wide_accepted": 0, "fixed_candidates": 0, "pcm_rejected": 0}
    if not cfg.wide.enabled or not loose.any():
        return loops, poses, summary
    offsets = np.cumsum([0] + [d.n for d in drives])
    if verify_wide_fn is None:
        verify_wide_fn = lambda c, p: verify_wide_from_store(c, p, drives, offsets, load, cfg)  # noqa: E731
    if verify_fn is None:
        verify_fn = lambda c, p: verify_from_store(c, p, drives, offsets, load, cfg) if c else []  # noqa: E731
    group = np.repeat(np.arange(len(drives)), [d.n for d in drives])
    stamps_s = np.concatenate([d.stamps_ns for d in drives]) * 1e-9
    pass1 = poses
    chain1 = chain_covariance(problem, pass1, offsets, ~loose)
    loops = list(loops)
    tried = {(r.i, r.j) for r in loops}
    summary["pcm_rejected"] += apply_pcm(loops, pass1, chain1, loose[group], cfg)
    for rnd in range(cfg.wide.rounds):
        if any(r.accepted for r in loops):  # search from the estimate that holds the loops found so far
            base = list(problem.betweens)
            poses = solve(loops, poses)
            problem.betweens = base  # the solve leaves its loop factors in the problem: the caller adds them again
        chain = chain_covariance(problem, poses, offsets, ~loose)
        travel = travel_m(poses[:, :3, 3], group)
        query = keyframes_by_travel(poses[:, :3, 3], group, cfg.wide.stride_m)
        query = query[loose[group[query]]]
        say(f"wide loop search, round {rnd + 1}")
        wide = find_wide_candidates(chain, stamps_s, query, travel, cfg, loops, tried)
        q2 = keyframes_by_travel(poses[:, :3, 3], group, cfg.stride_m)
        fixed = [c for c in find_candidates(poses[:, :3, 3], stamps_s, group, q2[loose[group[q2]]],
                                            radius_m=cfg.radius_m, min_separation_s=cfg.min_separation_s,
                                            max_per_scan=cfg.max_per_scan)
                 if (c.i, c.j) not in tried and _held_pair(chain, c, loops, cfg.wide.min_sigma_m)]
        tried |= {(c.i, c.j) for c in wide} | {(c.i, c.j) for c in fixed}
        new = verify_wide_fn(wide, poses) + (verify_fn(fixed, poses) if fixed else [])
        summary["rounds"] += 1
        summary["wide_candidates"] += len(wide)
        summary["fixed_candidates"] += len(fixed)
        summary["wide_accepted"] += sum(r.accepted for r in new[:len(wide)])
        loops += new
        summary["pcm_rejected"] += apply_pcm(loops, pass1, chain1, loose[group], cfg)
        log.info("wide loop search round %d: %d wide and %d fixed-radius candidates, %d accepted before the "
                 "consistency check; %d loops accepted in all", rnd + 1, len(wide), len(fixed),
                 sum(r.accepted for r in new), sum(r.accepted for r in loops))
        if not any(r.accepted for r in new):
            break
    return loops, poses, summary


def _held_pair(chain: ChainCovariance, c: Candidate, loops: list[LoopRecord], min_sigma_m: float) -> bool:
    """Whether the estimate holds the pair's relative position to less than ``min_sigma_m`` (the ordinary
    verification from the estimate applies; else the pair is the wide search's)."""
    cov = capped_relative(chain, c.i, np.array([c.j]), [r for r in loops if r.accepted])[0]
    return float(np.linalg.eigvalsh(cov)[-1]) < min_sigma_m ** 2


def apply_pcm(loops: list[LoopRecord], pass1: np.ndarray, chain: ChainCovariance, loose_pose: np.ndarray,
              cfg: LoopConfig) -> int:
    """The pairwise consistency check over the accepted loops that touch a loosely held pose: those outside the
    largest consistent set, or confirmed there by fewer than ``cfg.wide.min_consistent`` - 1 other loops within
    ``cfg.pcm_window_m``, are rejected. Returns how many were rejected now."""
    idx = [k for k, r in enumerate(loops) if (r.accepted or r.reason.startswith("inconsistent with the other"))
           and (loose_pose[r.i] or loose_pose[r.j])]
    if not idx:
        return 0
    travel = travel_m(np.column_stack([chain.positions_en, np.zeros(len(pass1))]), chain.group)
    keep = consistent_set([loops[k] for k in idx], pass1, chain, cfg.pcm_probability, travel, cfg.pcm_window_m,
                          min_support=cfg.wide.min_consistent - 1)
    rejected = 0
    for m, k in enumerate(idx):
        r = loops[k]
        if m in keep:
            if not r.accepted:
                r.accepted, r.reason = True, "accepted (consistent with the other loops)"
        elif r.accepted:
            r.accepted, r.reason = False, "inconsistent with the other loops (pairwise consistency, PCM)"
            rejected += 1
    return rejected
