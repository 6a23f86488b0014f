"""The pose-graph passes: (1) odometry + GNSS, (2) verified loops under a robust kernel (or GNC), (3) loops
inconsistent with the result removed; optional survey anchors; reference drives localised in a fixed map.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from stages.common.geometry import se3_inverse
from stages.common.registration import crop_range
from stages.posegraph.factors.drive import DriveInput, base_problem, deskew_scan_lidar, increments
from stages.posegraph.factors.graph import Between, PosePrior, Problem, between_residuals, optimize
from stages.posegraph.loops.verify import find_candidates, keyframes_by_travel, verify_loop

log = logging.getLogger(__name__)
# (drive, scan_id) list -> {(drive, scan_id): (points_lidar_m (N,3), time_offset_s (N,) or None)}
ScanLoader = Callable[[list[tuple[str, int]]], dict[tuple[str, int], tuple[np.ndarray, np.ndarray | None]]]


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


@dataclass
class Solution:
    poses: np.ndarray  # (N,4,4)
    problem: Problem
    loops: list[LoopRecord] = field(default_factory=list)
    timings_s: dict[str, float] = field(default_factory=dict)


def vehicle_clouds(drives: list[DriveInput], offsets: np.ndarray, wanted: np.ndarray, load: ScanLoader,
                   voxel_m: float, batch: int = 64, workers: int | None = 1) -> dict[int, np.ndarray]:
    """Deskewed, voxel-downsampled vehicle-frame points of the wanted pose indices, loaded in batches; the
    batches run through ``parallel_map`` (each worker reads its scans from the store) when ``workers`` != 1."""
    from pipeline.parallel import parallel_map

    owner = np.searchsorted(offsets, wanted, side="right") - 1
    items = []
    for start in range(0, len(wanted), batch):
        chunk = [(int(g), int(o), int(g - offsets[o])) for g, o in zip(wanted[start:start + batch],
                                                                         owner[start:start + batch])]
        items.append((chunk, voxel_m))
    out: dict[int, np.ndarray] = {}
    for part in parallel_map(_clouds_item, items, workers=workers if len(items) > 1 else 1,
                             initializer=_use_drives, initargs=(drives, load)):
        out.update(part)
    return out


def _use_drives(drives: list[DriveInput], load: ScanLoader) -> None:
    from pipeline.parallel import set_worker_state

    set_worker_state(drives=drives, load=load, increments={})


def _clouds_item(item) -> dict[int, np.ndarray]:
    """One batch of ``vehicle_clouds`` (module level: a pool process or a cluster worker runs it)."""
    import open3d as o3d

    from pipeline.parallel import worker_state

    chunk, voxel_m = item
    state = worker_state()
    drives, incs = state["drives"], state["increments"]
    got = state["load"]([(drives[o].name, int(drives[o].scan_ids[k])) for _, o, k in chunk])
    out = {}
    for g, o, k in chunk:
        d = drives[o]
        pts, toff = got[(d.name, int(d.scan_ids[k]))][:2]
        keep = crop_range(pts, 2.0, 80.0)
        pts = np.asarray(pts, float)[keep]
        if toff is not None and o not in incs:
            incs[o] = increments(d)
        pts = deskew_scan_lidar(d, incs.get(o), k, pts, None if toff is None else np.asarray(toff, float)[keep])
        pts = pts @ d.T_vehicle_lidar[:3, :3].T + d.T_vehicle_lidar[:3, 3]
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)).voxel_down_sample(voxel_m)
        out[g] = np.asarray(cloud.points)
    return out


def _workers(n_items: int, p) -> int | None:
    """All the machine's processes (None) from ``p.parallel_min_items`` independent items on, else this one."""
    return None if n_items >= p.parallel_min_items else 1


def _verify_kwargs(p) -> dict:
    return dict(voxel_m=p.loop_voxel_m, max_corr_m=p.loop_max_corr_m, min_fitness=p.loop_min_fitness,
                max_rmse_m=p.loop_max_rmse_m, max_correction_m=p.loop_max_correction_m,
                max_correction_rad=p.loop_max_correction_rad, consistency_m=p.loop_consistency_m,
                min_sigma_m=p.loop_min_sigma_m, min_sigma_rad=p.loop_min_sigma_rad,
                coarse_voxel_m=p.loop_coarse_voxel_m, coarse_corr_m=p.loop_coarse_corr_m,
                inlier_m=p.loop_inlier_m, plane_tol_m=p.loop_plane_tol_m)


def _verify_item(item) -> object:
    """One candidate's ICP verification (module level: runs in a pool process or on a cluster worker)."""
    cloud_i, cloud_j, prior, kwargs = item
    return verify_loop(cloud_i, cloud_j, prior, **kwargs)


def verify_candidates(candidates, poses: np.ndarray, clouds: dict[int, np.ndarray], p,
                      fixed: dict[int, np.ndarray] | None = None, progress=None) -> list[LoopRecord]:
    """ICP-verify each candidate from the current estimate's relative pose (``fixed`` poses override). The
    candidates are independent: they run through ``pipeline.parallel.parallel_map`` (processes here, tasks on
    a cluster) when there are at least ``p.parallel_min_items`` of them; the verdicts do not depend on it."""
    from pipeline.parallel import parallel_map

    fixed = fixed or {}
    kwargs = _verify_kwargs(p)
    items = []
    for c in candidates:
        Ti = fixed.get(c.i, poses[c.i] if c.i < len(poses) else None)
        Tj = fixed.get(c.j, poses[c.j] if c.j < len(poses) else None)
        items.append((clouds[c.i], clouds[c.j], se3_inverse(Ti) @ Tj, kwargs))
    verdicts = parallel_map(_verify_item, items, workers=_workers(len(items), p), progress=progress)
    return [LoopRecord(c.i, c.j, c.prior_distance_m, v.fitness, v.inlier_rmse_m, v.T_i_j, v.accepted, v.reason,
                       v.information) for c, v in zip(candidates, verdicts)]


def loop_betweens(loops: list[LoopRecord], p) -> list[Between]:
    robust = "none" if p.loop_kernel == "gnc" else p.loop_kernel
    return [Between(r.i, r.j, r.T_i_j, r.information, "loop", robust, p.loop_kernel_k) for r in loops if r.accepted]


def _lm(p) -> dict:
    """Levenberg-Marquardt settings of the parameters, as keyword arguments of ``optimize``."""
    return {"max_iterations": p.max_iterations, "relative_error_tol": p.lm_relative_error_tol}


def optimize_with_loops(problem: Problem, loops: list[LoopRecord], p, max_rounds: int = 8,
                        solve_times_s: list[float] | None = None, initial: np.ndarray | None = None) -> np.ndarray:
    """Pass 2 with the accepted loops under the robust kernel; pass 3 removes, worst first, the loops the
    result cannot explain (whitened residual above ``loop_max_whitened_residual``), re-optimising each round,
    then re-admits removed loops that the final graph does explain. The first solve starts from ``initial``
    (the pass-1 estimate; default ``problem.initial``), each later one from the previous result.
    ``solve_times_s`` collects the wall time of each complete solve (all poses, GNSS, loops)."""
    base = list(problem.betweens)
    gnc = p.loop_kernel == "gnc"
    last = initial  # where the next solve starts

    def solve() -> np.ndarray:
        nonlocal last
        t0 = time.perf_counter()
        out = last = _solve()
        if solve_times_s is not None:
            solve_times_s.append(time.perf_counter() - t0)
        return out

    def _solve() -> np.ndarray:
        problem.betweens = base + loop_betweens(loops, p)
        if gnc:
            return optimize(problem, **_lm(p), gnc_loops=True, initial=last)
        # A redescending kernel (Cauchy) started where a true loop is 1-2 m (50-100 sigma) off gives it
        # almost no weight: the GNSS bias wins and pass 3 then drops every loop. A convex Huber pass first
        # (bounded influence, so one false loop cannot bend the map far) brings the true loops into the
        # kernel's basin; the configured kernel then refines from there.
        warm = [Between(b.i, b.j, b.T_i_j, b.information, b.kind, "huber", p.loop_kernel_k)
                if b.kind == "loop" else b for b in problem.betweens]
        full = problem.betweens
        problem.betweens = warm
        start = optimize(problem, **_lm(p), initial=last)
        problem.betweens = full
        return optimize(problem, **_lm(p), initial=start)

    poses = solve()
    removed: list[LoopRecord] = []
    for _ in range(max_rounds):
        accepted = [r for r in loops if r.accepted]
        if not accepted:
            break
        res = between_residuals(loop_betweens(accepted, p), poses)
        worst = float(res.max())
        if worst <= p.loop_max_whitened_residual:
            break
        for r, x in zip(accepted, res):
            if x > max(p.loop_max_whitened_residual, 0.5 * worst):
                r.accepted, r.reason = False, f"inconsistent with the optimised graph (whitened residual {x:.1f})"
                removed.append(r)
        poses = solve()
    if removed:
        res = between_residuals(loop_betweens([_as_accepted(r) for r in removed], p), poses)
        back = [r for r, x in zip(removed, res) if x <= p.loop_max_whitened_residual]
        for r in back:
            r.accepted, r.reason = True, "accepted (re-admitted after pass 3)"
        log.info("pass 3: %d loops removed as inconsistent, %d re-admitted", len(removed), len(back))
        if back:
            poses = solve()
    return poses


def _as_accepted(r: LoopRecord) -> LoopRecord:
    return LoopRecord(r.i, r.j, r.prior_distance_m, r.fitness, r.inlier_rmse_m, r.T_i_j, True, r.reason,
                      r.information)


def solve_map(drives: list[DriveInput], load: ScanLoader, p, *, extra_loops: list[LoopRecord] = (),
              survey_priors: Callable[[np.ndarray, np.ndarray], list[PosePrior]] | None = None,
              report_step: Callable[[str, int, int], None] | None = None) -> Solution:
    """All map drives in one graph. ``extra_loops`` enter as accepted (tests/bench plant false loops here);
    ``survey_priors(poses, offsets)`` returns absolute anchors computed on the pass-2 estimate."""
    import time

    t0 = time.perf_counter()
    problem, offsets = base_problem(drives, p)
    poses = optimize(problem, **_lm(p))
    t1 = time.perf_counter()
    group = np.repeat(np.arange(len(drives)), [d.n for d in drives])
    stamps_s = np.concatenate([d.stamps_ns for d in drives]) * 1e-9
    query = keyframes_by_travel(poses[:, :3, 3], group, p.loop_stride_m)
    cands = find_candidates(poses[:, :3, 3], stamps_s, group, query, radius_m=p.loop_radius_m,
                            min_separation_s=p.loop_min_separation_s, max_per_scan=p.loop_max_per_scan)
    wanted = np.unique([c.i for c in cands] + [c.j for c in cands]).astype(np.int64)
    clouds = vehicle_clouds(drives, offsets, wanted, load, p.loop_voxel_m, workers=_workers(len(wanted), p))
    step = (lambda done, total: report_step("loops verified", done, total)) if report_step else None
    loops = verify_candidates(cands, poses, clouds, p, progress=step) + list(extra_loops)
    t2 = time.perf_counter()
    solve_times: list[float] = []
    poses = optimize_with_loops(problem, loops, p, solve_times_s=solve_times, initial=poses)
    t3 = time.perf_counter()
    if survey_priors is not None:
        anchors = survey_priors(poses, offsets)
        if anchors:
            problem.pose_priors += anchors
            poses = optimize(problem, **_lm(p), gnc_loops=p.loop_kernel == "gnc",
                             initial=poses)
    t4 = time.perf_counter()
    log.info("posegraph: %d poses, %d candidates, %d loops accepted", len(poses), len(cands),
             sum(r.accepted for r in loops))
    return Solution(poses, problem, loops, {"pass1_s": t1 - t0, "loops_s": t2 - t1, "pass23_s": t3 - t2,
                                            "survey_s": t4 - t3, "n_loop_solves": len(solve_times),
                                            "loop_solve_max_s": max(solve_times, default=0.0)})


def solve_reference(drive: DriveInput, map_drives: list[DriveInput], map_poses: np.ndarray, load: ScanLoader,
                    p) -> Solution:
    """One eval drive in the map's frame: its odometry + GNSS, plus loops onto map scans held fixed."""
    problem, _ = base_problem([drive], p)
    poses = optimize(problem, **_lm(p))
    n = drive.n
    stamps = np.concatenate([drive.stamps_ns] + [d.stamps_ns for d in map_drives]) * 1e-9
    positions = np.concatenate([poses[:, :3, 3], map_poses[:, :3, 3]])
    group = np.concatenate([np.zeros(n, int), np.ones(len(map_poses), int)])
    query = keyframes_by_travel(positions[:n], group[:n], p.loop_stride_m)
    cands = find_candidates(positions, stamps, group, query, radius_m=p.loop_radius_m,
                            min_separation_s=p.loop_min_separation_s, max_per_scan=p.loop_max_per_scan,
                            allowed_targets=group == 1)
    all_drives = [drive] + list(map_drives)
    offsets = np.cumsum([0] + [d.n for d in all_drives])
    wanted = np.unique([c.i for c in cands] + [c.j for c in cands]).astype(np.int64)
    clouds = vehicle_clouds(all_drives, offsets, wanted, load, p.loop_voxel_m, workers=_workers(len(wanted), p))
    fixed = {g: map_poses[g - n] for g in wanted if g >= n}
    loops = verify_candidates(cands, poses, clouds, p, fixed=fixed)
    # map poses in loops become extra variables held by tight priors
    extra = sorted({g for r in loops if r.accepted for g in (r.i, r.j) if g >= n})
    remap = {g: n + m for m, g in enumerate(extra)}
    problem.n_poses = n + len(extra)
    problem.initial = np.concatenate([poses] + [fixed[g][None] for g in extra])
    tight = np.diag([(p.fixed_prior_sigma_m / 10.0) ** -2] * 3 + [p.fixed_prior_sigma_m ** -2] * 3)
    problem.pose_priors += [PosePrior(remap[g], fixed[g], tight, "fixed") for g in extra]
    local = [LoopRecord(remap.get(r.i, r.i), remap.get(r.j, r.j), r.prior_distance_m, r.fitness, r.inlier_rmse_m,
                        r.T_i_j, r.accepted, r.reason, r.information) for r in loops]
    poses = optimize_with_loops(problem, local, p)[:n]
    for r_local, r in zip(local, loops):  # decisions of pass 3 back onto the global indices
        r.accepted, r.reason = r_local.accepted, r_local.reason
    return Solution(poses, problem, loops)
