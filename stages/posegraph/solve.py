"""The pose-graph passes: (1) odometry + GNSS; optional survey anchors; (2) verified loops under a robust kernel (or
GNC), where the anchors leave a drive free; (3) loops inconsistent with the result removed; reference drives localised
in a fixed map.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from stages.posegraph.config import LoopConfig, SolveConfig
from stages.posegraph.factors.base import base_problem
from stages.posegraph.factors.drive import DriveInput
from stages.posegraph.factors.graph import Between, PosePrior, Problem, between_residuals, optimize
from stages.posegraph.loops.candidates import find_candidates, keyframes_by_travel, loosely_anchored, travel_m
from stages.posegraph.loops.clouds import ScanLoader
from stages.posegraph.loops.verify import LoopRecord, loop_betweens, verify_from_store
from stages.posegraph.params import PosegraphParams

log = logging.getLogger(__name__)


@dataclass
class Solution:
    poses: np.ndarray  # (N,4,4)
    problem: Problem
    loops: list[LoopRecord] = field(default_factory=list)
    timings_s: dict[str, float] = field(default_factory=dict)
    survey_rounds: list[dict] = field(default_factory=list)  # one record per anchoring round (``anchored``)
    extra: dict = field(default_factory=dict)  # the incremental solve's: held rows of its map poses, its window


def optimize_with_loops(problem: Problem, loops: list[LoopRecord], loop_cfg: LoopConfig, solve_cfg: SolveConfig,
                        max_rounds: int = 8, solve_times_s: list[float] | None = None,
                        initial: np.ndarray | None = None) -> np.ndarray:
    """Pass 2 with the accepted loops under the robust kernel; pass 3 removes, worst first, the loops the
    result cannot explain (whitened residual above ``loop_cfg.max_whitened_residual``), re-optimising each round,
    then re-admits removed loops that the final graph does explain. The first solve starts from ``initial``
    (the pass-1 estimate; default ``problem.initial``), each later one from the previous result.
    ``solve_times_s`` collects the wall time of each complete solve (all poses, GNSS, loops)."""
    base = list(problem.betweens)
    gnc = loop_cfg.kernel == "gnc"
    lm = solve_cfg.lm_kwargs()
    max_residual = loop_cfg.max_whitened_residual
    last = initial  # where the next solve starts

    def solve() -> np.ndarray:
        nonlocal last
        t0 = time.perf_counter()
        out = last = _solve()
        if solve_times_s is not None:
            solve_times_s.append(time.perf_counter() - t0)
        return out

    def _solve() -> np.ndarray:
        problem.betweens = base + loop_betweens(loops, loop_cfg)
        if gnc:
            return optimize(problem, **lm, gnc_loops=True, initial=last)
        # A redescending kernel (Cauchy) started where a true loop is 1-2 m (50-100 sigma) off gives it
        # almost no weight: the GNSS bias wins and pass 3 then drops every loop. A convex Huber pass first
        # (bounded influence, so one false loop cannot bend the map far) brings the true loops into the
        # kernel's basin; the configured kernel then refines from there.
        warm = [Between(b.i, b.j, b.T_i_j, b.information, b.kind, "huber", loop_cfg.kernel_k)
                if b.kind == "loop" else b for b in problem.betweens]
        full = problem.betweens
        problem.betweens = warm
        start = optimize(problem, **lm, initial=last)
        problem.betweens = full
        return optimize(problem, **lm, initial=start)

    poses = solve()
    removed: list[LoopRecord] = []
    for _ in range(max_rounds):
        accepted = [r for r in loops if r.accepted]
        if not accepted:
            break
        res = between_residuals(loop_betweens(accepted, loop_cfg), poses)
        worst = float(res.max())
        if worst <= max_residual:
            break
        for r, x in zip(accepted, res):
            if x > max(max_residual, 0.5 * worst):
                r.accepted, r.reason = False, f"inconsistent with the optimised graph (whitened residual {x:.1f})"
                removed.append(r)
        poses = solve()
    if removed:
        res = between_residuals(loop_betweens([_as_accepted(r) for r in removed], loop_cfg), poses)
        back = [r for r, x in zip(removed, res) if x <= max_residual]
        for r in back:
            r.accepted, r.reason = True, "accepted (re-admitted after pass 3)"
        log.info("pass 3: %d loops removed as inconsistent, %d re-admitted", len(removed), len(back))
        if back:
            poses = solve()
    return poses


def _as_accepted(r: LoopRecord) -> LoopRecord:
    return LoopRecord(r.i, r.j, r.prior_distance_m, r.fitness, r.inlier_rmse_m, r.T_i_j, True, r.reason,
                      r.information)


def anchored_query(problem: Problem, poses: np.ndarray, offsets, group: np.ndarray,
                   survey_priors: Callable[[np.ndarray, np.ndarray], list[PosePrior]] | None, cfg: PosegraphParams,
                   rounds: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """The survey anchoring rounds (``anchored``, when ``survey_priors`` is given; ``rounds`` collects them), then
    the scans that look for loops: keyframes every ``cfg.loops.stride_m`` of travel per drive (``group``), with
    anchors only those the anchors leave loose (``loosely_anchored``). Returns (poses, query indices)."""
    lc, lm = cfg.loops, cfg.solve.lm_kwargs()
    if survey_priors is not None:
        poses = anchored(problem, poses, offsets, survey_priors, cfg.anchors, rounds,
                         lambda initial: optimize(problem, **lm, gnc_loops=lc.kernel == "gnc", initial=initial))
    query = keyframes_by_travel(poses[:, :3, 3], group, lc.stride_m)
    if survey_priors is not None:
        held, info_en = horizontal_anchors(problem.pose_priors)
        query = loosely_anchored(query, held, info_en, travel_m(poses[:, :3, 3], group), group,
                                 lc.survey_window_m, lc.survey_sigma_m)
    return poses, query


def solve_map(drives: list[DriveInput], load: ScanLoader, cfg: PosegraphParams, *, extra_loops: list[LoopRecord] = (),
              survey_priors: Callable[[np.ndarray, np.ndarray], list[PosePrior]] | None = None,
              report_step: Callable[..., None] | None = None) -> Solution:
    """All map drives in one graph: pass 1 (odometry + GNSS); with ``survey_priors(poses, offsets)`` (absolute
    anchors of the keyframes, matched on the current estimate) the anchoring rounds (``anchored``); then loops,
    verified and solved (passes 2 and 3) where the anchors leave a drive free: with anchors, only the query poses
    whose drive's anchors within ``cfg.loops.survey_window_m`` of travel hold them to less than
    ``cfg.loops.survey_sigma_m`` in one horizontal direction or none look for loops (``loosely_anchored``; where the
    anchors hold each pass, they tie the passes to each other through the survey). ``extra_loops`` enter as
    accepted (tests/bench plant false loops here)."""
    import time

    say = report_step or (lambda step, done=None, total=None: None)
    t0 = time.perf_counter()
    say("pass 1: odometry and GNSS")
    problem, offsets = base_problem(drives, cfg.factors, cfg.gnss, cfg.prior)
    lc, lm = cfg.loops, cfg.solve.lm_kwargs()
    poses = optimize(problem, **lm)
    t1 = time.perf_counter()
    group = np.repeat(np.arange(len(drives)), [d.n for d in drives])
    stamps_s = np.concatenate([d.stamps_ns for d in drives]) * 1e-9
    rounds: list[dict] = []
    poses, query = anchored_query(problem, poses, offsets, group, survey_priors, cfg, rounds)
    t2 = time.perf_counter()
    say("loop candidates")
    cands = find_candidates(poses[:, :3, 3], stamps_s, group, query, radius_m=lc.radius_m,
                            min_separation_s=lc.min_separation_s, max_per_scan=lc.max_per_scan)
    step = (lambda done, total: report_step("loops verified", done, total)) if report_step else None
    loops = (verify_from_store(cands, poses, drives, offsets, load, lc, progress=step) if cands else []) \
        + list(extra_loops)
    if lc.wide.enabled:  # drives nothing absolute holds: the search widened by their uncertainty (loops/wide.py)
        from stages.posegraph.loops.wide import close_wide_loops

        loops, poses, wide = close_wide_loops(
            problem, poses, drives, load, lc, loops, say=say,
            solve=lambda ls, init: optimize_with_loops(problem, ls, lc, cfg.solve, initial=init))
        if wide["rounds"]:
            log.info("posegraph: wide loop search: %s", wide)
    t3 = time.perf_counter()
    solve_times: list[float] = []
    if loops or survey_priors is None:
        say(f"passes 2-3: solving with {sum(r.accepted for r in loops)} loops")
        poses = optimize_with_loops(problem, loops, lc, cfg.solve, solve_times_s=solve_times, initial=poses)
    t4 = time.perf_counter()
    log.info("posegraph: %d poses, %d loop query poses, %d candidates, %d loops accepted", len(poses), len(query),
             len(cands), sum(r.accepted for r in loops))
    return Solution(poses, problem, loops, {"pass1_s": t1 - t0, "survey_s": t2 - t1, "loops_s": t3 - t2,
                                            "pass23_s": t4 - t3, "n_loop_solves": len(solve_times),
                                            "loop_solve_max_s": max(solve_times, default=0.0)}, rounds)


def horizontal_anchors(priors: list[PosePrior]) -> tuple[np.ndarray, np.ndarray]:
    """The survey priors' poses and their horizontal information in east/north ((K,2,2), 1/m^2: a marking anchor's;
    a vertical-only ground anchor's is ~0)."""
    survey = [p for p in priors if p.kind == "survey"]
    idx = np.asarray([p.i for p in survey], np.int64)
    info = np.zeros((len(survey), 2, 2))
    for k, p in enumerate(survey):
        R = p.T_map_vehicle[:2, :2]  # the body-frame block turned into east/north (the vehicle is near level)
        info[k] = R @ p.information[3:5, 3:5] @ R.T
    return idx, info


def pose_change(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Largest horizontal position change (m) and heading change (deg) between two (N, 4, 4) trajectories."""
    if not len(a):
        return 0.0, 0.0
    moved_m = float(np.max(np.linalg.norm(b[:, :2, 3] - a[:, :2, 3], axis=1)))
    yaw = lambda T: np.arctan2(T[:, 1, 0], T[:, 0, 0])  # noqa: E731
    turned = np.angle(np.exp(1j * (yaw(b) - yaw(a))))
    return moved_m, float(np.rad2deg(np.max(np.abs(turned))))


def anchored(problem, poses: np.ndarray, offsets: np.ndarray,
             survey_priors: Callable[[np.ndarray, np.ndarray], list[PosePrior]], cfg, rounds_out: list[dict],
             solve: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """The survey anchors matched from ``poses``, solved, and matched again from the anchored estimate while a
    round moves a pose more than ``cfg.round_tol_m`` / ``cfg.round_tol_deg`` (at most ``cfg.rounds`` rounds). Each
    round replaces the previous round's anchors; ``rounds_out`` gets one record per round."""
    base = list(problem.pose_priors)
    for r in range(cfg.rounds):
        anchors = survey_priors(poses, offsets)
        if not anchors:
            break
        problem.pose_priors = base + anchors
        new = solve(poses)
        moved_m, turned_deg = pose_change(poses, new)
        poses = new
        rounds_out.append({"round": r + 1, "anchors": len(anchors), "max_moved_m": moved_m,
                           "max_turned_deg": turned_deg})
        log.info("survey anchors, round %d: %d anchors; poses moved up to %.3f m, %.3f deg", r + 1, len(anchors),
                 moved_m, turned_deg)
        if moved_m <= cfg.round_tol_m and turned_deg <= cfg.round_tol_deg:
            break
    return poses


def solve_reference(drive: DriveInput, map_drives: list[DriveInput], map_poses: np.ndarray, load: ScanLoader,
                    cfg: PosegraphParams) -> Solution:
    """One eval drive in the map's frame: its odometry + GNSS, plus loops onto map scans held fixed."""
    problem, _ = base_problem([drive], cfg.factors, cfg.gnss, cfg.prior)
    lc = cfg.loops
    poses = optimize(problem, **cfg.solve.lm_kwargs())
    n = drive.n
    stamps = np.concatenate([drive.stamps_ns] + [d.stamps_ns for d in map_drives]) * 1e-9
    positions = np.concatenate([poses[:, :3, 3], map_poses[:, :3, 3]])
    group = np.concatenate([np.zeros(n, int), np.ones(len(map_poses), int)])
    query = keyframes_by_travel(positions[:n], group[:n], lc.reference_stride_m)
    cands = find_candidates(positions, stamps, group, query, radius_m=lc.radius_m,
                            min_separation_s=lc.min_separation_s, max_per_scan=lc.max_per_scan,
                            allowed_targets=group == 1)
    all_drives = [drive] + list(map_drives)
    offsets = np.cumsum([0] + [d.n for d in all_drives])
    wanted = np.unique([c.i for c in cands] + [c.j for c in cands]).astype(np.int64)
    fixed = {g: map_poses[g - n] for g in wanted if g >= n}
    loops = verify_from_store(cands, poses, all_drives, offsets, load, lc, fixed=fixed)
    # map poses in loops become extra variables held by tight priors
    extra = sorted({g for r in loops if r.accepted for g in (r.i, r.j) if g >= n})
    remap = {g: n + m for m, g in enumerate(extra)}
    problem.n_poses = n + len(extra)
    problem.initial = np.concatenate([poses] + [fixed[g][None] for g in extra])
    sigma_m = cfg.solve.fixed_prior_sigma_m
    tight = np.diag([(sigma_m / 10.0) ** -2] * 3 + [sigma_m ** -2] * 3)
    problem.pose_priors += [PosePrior(remap[g], fixed[g], tight, "fixed") for g in extra]
    local = [LoopRecord(remap.get(r.i, r.i), remap.get(r.j, r.j), r.prior_distance_m, r.fitness, r.inlier_rmse_m,
                        r.T_i_j, r.accepted, r.reason, r.information) for r in loops]
    poses = optimize_with_loops(problem, local, lc, cfg.solve)[:n]
    for r_local, r in zip(local, loops):  # decisions of pass 3 back onto the global indices
        r.accepted, r.reason = r_local.accepted, r_local.reason
    return Solution(poses, problem, loops)
