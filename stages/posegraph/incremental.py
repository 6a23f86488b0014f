"""Incremental pose graph: new drives solved against a published map whose poses are held, but for a window.

The graph is the new drives' own (odometry, GNSS, prior trajectory or start pose, survey anchors) plus verified loops
from their keyframes onto the map's scans and onto each other. With the held solution's frame covariance
(``frame``), the map poses within reach of the new drives' path form a window that moves with one rigid correction
of the map's frame (``window.py``): a map pose a loop reaches is a variable tied to the frame anchor; the window's
poses are written back moved by the correction, every other map pose keeps its published value bit for bit.
Without it, a map pose a loop reaches is held by a tight prior at its published value (``fixed_prior_sigma_m``), as
for a reference drive (``solve.solve_reference``), and never written back. The cost is the new drives' (their pass
1, anchors, loop candidates within ``loops.radius_m`` of their path, the solves over their poses, one more variable
and its marginal), not the map's history.

A full joint re-solve of every drive (``solve.solve_map``) stays what ``cornermap rebuild --full`` and a first
build run; a later ``maps reoptimize`` (issue 59) is that solve, scheduled.
"""
from __future__ import annotations

import logging
import time
from typing import Callable

import numpy as np

from stages.posegraph.factors.base import base_problem
from stages.posegraph.factors.drive import DriveInput
from stages.posegraph.factors.graph import PosePrior, Problem, optimize
from stages.posegraph.loops.candidates import find_candidates
from stages.posegraph.loops.verify import LoopRecord, verify_from_store
from stages.posegraph.params import PosegraphParams
from stages.posegraph.solve import Solution, anchored_query, optimize_with_loops
from stages.posegraph.window import (
    FramePrior,
    add_window,
    anchor_marginal,
    correct_window,
    frame_held,
    frame_record,
    frame_test,
    log_pose,
    select_window,
    window_cap,
)

log = logging.getLogger(__name__)


def solve_increment(new: list[DriveInput], held: list[DriveInput], held_poses: np.ndarray, load, cfg: PosegraphParams,
                    *, max_per_scan: int | None = None, survey_priors: Callable | None = None,
                    report_step: Callable[..., None] | None = None, frame: FramePrior | None = None,
                    held_cov: np.ndarray | None = None, held_drive_of_row: np.ndarray | None = None) -> Solution:
    """The ``new`` drives' poses (one row per scan, drives in order) with the ``held`` drives' poses
    (``held_poses``, (M,4,4), the held drives' rows in order) held: fixed, or with ``frame`` (the held solution's
    frame covariance), ``held_cov`` ((M,9) their published ``cov_xy_yaw``) and ``held_drive_of_row`` ((M,) the held
    drive of each row; default from ``held``) moved in the window (``window.py``; the result in ``extra["window"]``).
    ``survey_priors(poses, offsets)``: the survey
    anchors of the new drives (``anchors.survey_anchor.survey_anchor_callback`` built on ``new``). ``max_per_scan``:
    loop targets per query scan (default the joint solve's ``loops.max_per_scan``): the nearest other passes, map
    or new, so the loops a new drive verifies do not grow with the passes the map holds.

    Returns a ``Solution`` whose ``poses`` are the new drives' (N,4,4) and whose ``problem`` holds N variables
    followed by the map poses its loops reach (tightly held); loop indices: 0..N-1 the new drives' scans, N.. the
    held drives' scans (N + row of ``held_poses``)."""
    say = report_step or (lambda step, done=None, total=None: None)
    n = int(sum(d.n for d in new))
    if len(held_poses) != sum(d.n for d in held):
        raise ValueError(f"held poses: {len(held_poses)} rows for {sum(d.n for d in held)} scans of the held drives")
    if n == 0:  # every map drive held: nothing to solve
        return Solution(np.zeros((0, 4, 4)), Problem(0, np.zeros((0, 4, 4))), [])
    t0 = time.perf_counter()
    say("pass 1: odometry and GNSS of the new drives")
    problem, offsets = base_problem(new, cfg.factors, cfg.gnss, cfg.prior)
    lc, lm = cfg.loops, cfg.solve.lm_kwargs()
    poses = optimize(problem, **lm)
    t1 = time.perf_counter()
    rounds: list[dict] = []
    group_new = np.repeat(np.arange(len(new)), [d.n for d in new])
    poses, query = anchored_query(problem, poses, offsets, group_new, survey_priors, cfg, rounds)
    t2 = time.perf_counter()
    say("loop candidates against the map")
    all_drives = list(new) + list(held)
    group = np.repeat(np.arange(len(all_drives)), [d.n for d in all_drives])
    positions = np.concatenate([poses[:, :3, 3], held_poses[:, :3, 3]]) if len(held_poses) else poses[:, :3, 3]
    stamps_s = np.concatenate([d.stamps_ns for d in all_drives]) * 1e-9
    cands = find_candidates(positions, stamps_s, group, query, radius_m=lc.radius_m,
                            min_separation_s=lc.min_separation_s, max_per_scan=max_per_scan or lc.max_per_scan)
    all_offsets = np.cumsum([0] + [d.n for d in all_drives])
    wanted = np.unique([c.i for c in cands] + [c.j for c in cands]).astype(np.int64)
    fixed = {int(g): held_poses[g - n] for g in wanted if g >= n}
    step = (lambda done, total: report_step("loops verified", done, total)) if report_step else None
    loops = verify_from_store(cands, poses, all_drives, all_offsets, load, lc, fixed=fixed, progress=step) \
        if cands else []
    t3 = time.perf_counter()
    # the map poses a loop reaches: variables at their published values, held by tight priors or, with a frame
    # prior, tied to the window's frame anchor (window.py)
    extra = sorted({g for r in loops if r.accepted for g in (r.i, r.j) if g >= n})
    remap = {g: n + m for m, g in enumerate(extra)}
    problem.n_poses = n + len(extra)
    problem.initial = np.concatenate([problem.initial] + [held_poses[g - n][None] for g in extra])
    win = None
    if frame is not None and len(held_poses):
        rows, left_out = select_window(held_poses[:, :2, 3], poses[:, :2, 3], lc.radius_m, window_cap(n))
        if set(rows.tolist()) & {g - n for g in extra}:  # a loop reaches the window: the frame can move
            win = add_window(problem, {remap[g]: g - n for g in extra}, held_poses, held_cov, rows, left_out, frame)
    if win is None:
        sigma_m = cfg.solve.fixed_prior_sigma_m
        tight = np.diag([(sigma_m / 10.0) ** -2] * 3 + [sigma_m ** -2] * 3)
        problem.pose_priors += [PosePrior(remap[g], held_poses[g - n], tight, "fixed") for g in extra]
    local = [LoopRecord(remap.get(r.i, r.i), remap.get(r.j, r.j), r.prior_distance_m, r.fitness, r.inlier_rmse_m,
                        r.T_i_j, r.accepted, r.reason, r.information) for r in loops]
    solve_times: list[float] = []
    start = problem.initial.copy()
    start[:n] = poses
    solved = start
    if local or survey_priors is None:
        say(f"passes 2-3: solving the new drives with {sum(r.accepted for r in loops)} loops")
        solved = optimize_with_loops(problem, local, lc, cfg.solve, solve_times_s=solve_times, initial=start)
        poses = solved[:n]
    for r_local, r in zip(local, loops):  # pass 3's decisions back onto the global indices
        r.accepted, r.reason = r_local.accepted, r_local.reason
    window = None
    if win is not None:
        say("the window: the held map's frame correction")
        A_sol = solved[win.anchor]
        cov_post = anchor_marginal(problem, solved, win.anchor)
        drive_of_row = np.repeat(np.arange(len(held)), [d.n for d in held]) if held_drive_of_row is None \
            else held_drive_of_row
        corrected = correct_window(held_poses, win, A_sol, drive_of_row)
        test = frame_test(log_pose(np.linalg.inv(win.A_pub) @ A_sol), win.cov_prior, cov_post)
        window = {"graph": win, "A_sol": A_sol, "cov_post": cov_post, "held_T": corrected,
                  "record": frame_record(win, A_sol, cov_post, len(held_poses), frame, test),
                  "problem_frame_held": frame_held(problem, win, A_sol), "solved": solved}
        log.info("posegraph (incremental): window of %d held poses (%d left out by the cap); the held map's frame "
                 "moved %.3f m (prior std %s m, posterior %s m); frame test %.1f of %s", len(win.rows), win.left_out,
                 window["record"]["anchor_moved_m"], window["record"]["prior_std_en_m"],
                 window["record"]["posterior_std_en_m"], test["chi2"], test["threshold"])
    t4 = time.perf_counter()
    log.info("posegraph (incremental): %d new poses against %d held, %d loop query poses, %d candidates, "
             "%d loops accepted, %d map poses reached", n, len(held_poses), len(query), len(cands),
             sum(r.accepted for r in loops), len(extra))
    return Solution(poses, problem, loops, {"pass1_s": t1 - t0, "survey_s": t2 - t1, "loops_s": t3 - t2,
                                            "pass23_s": t4 - t3, "n_loop_solves": len(solve_times),
                                            "loop_solve_max_s": max(solve_times, default=0.0),
                                            "n_held_poses": len(held_poses), "n_map_poses_reached": len(extra),
                                            "n_window_poses": 0 if win is None else len(win.rows)},
                    rounds, {"held_of": {remap[g]: g - n for g in extra}, "window": window})
