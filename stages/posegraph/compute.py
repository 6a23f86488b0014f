"""Adapter of the posegraph stage: reads edges, GNSS poses, scans (only loop/anchor candidates), survey;
solves the map drives jointly, then each reference (eval) drive against the fixed map; writes tables,
TUM/KITTI trajectories and the report into the ``report`` artifact directory.
"""
from __future__ import annotations

import logging

import numpy as np
import pyarrow as pa

from pipeline.declare import PartitionKey, StageContext
from pipeline.errors import ConfigError, DataQualityError
from stages.common.geometry import write_kitti, write_tum
from stages.common.records import decode_scans_raw
from stages.posegraph.factors.drive import DriveInput, dead_reckoning
from stages.posegraph.factors.graph import marginal_cov_xy_yaw
from stages.posegraph.params import PosegraphParams
from stages.posegraph.report import write_report
from stages.posegraph.solve import solve_map, solve_reference
from stages.posegraph.tables import drive_input, loops_table, poses_table

log = logging.getLogger(__name__)


def _marginals(problem, poses: np.ndarray, what: str) -> np.ndarray:
    """``marginal_cov_xy_yaw``, its undetermined graph a data-quality error naming the drives."""
    try:
        return marginal_cov_xy_yaw(problem, poses)
    except ValueError as err:
        raise DataQualityError(f"posegraph, {what}: {err}; hint: a stretch without ICP edges, GNSS fixes or "
                               "loops leaves poses free (see the posegraph report's edge counts)") from err


class ScanLoader:
    """Reads only the requested scans (the row groups that hold them): (xyz, time offsets or None,
    *extra columns) per scan. Picklable: worker processes of the stage read the store themselves."""

    def __init__(self, inputs, extra_columns: tuple[str, ...] = ()):
        self.inputs, self.extra_columns = inputs, tuple(extra_columns)

    def __call__(self, requests: list[tuple[str, int]]):
        out = {}
        extra = self.extra_columns
        for drive in sorted({d for d, _ in requests}):
            ids = sorted({s for d, s in requests if d == drive})
            tab = self.inputs.read_in("scans", "scan_id", ids, partition=PartitionKey(drive=drive),
                                      columns=["scan_id", "x_m", "y_m", "z_m", "time_offset_s", *extra])
            rows = decode_scans_raw(tab)  # the store's row groups come in scan order; sorted once otherwise
            del tab
            for s, r in zip(ids, rows.rows_of(ids)):
                xyz = rows.xyz_lidar_m[r].astype(np.float64)  # each scan's own arrays, float64
                t = rows.time_offset_s[r].astype(np.float64)
                out[(drive, s)] = (xyz, t if np.any(t != 0) else None, *(getattr(rows, c)[r].copy() for c in extra))
        return out


def scan_loader(ctx: StageContext, extra_columns: tuple[str, ...] = ()) -> ScanLoader:
    return ScanLoader(ctx.inputs, extra_columns)


def _loop_rows(loops, names: list[tuple[str, int]]) -> list[dict]:
    rows = []
    for r in loops:
        (da, sa), (db, sb) = names[r.i], names[r.j]
        dx, dy, dyaw = float(r.T_i_j[0, 3]), float(r.T_i_j[1, 3]), float(np.arctan2(r.T_i_j[1, 0], r.T_i_j[0, 0]))
        rows.append({"drive_a": da, "scan_a": sa, "drive_b": db, "scan_b": sb, "prior_distance_m": r.prior_distance_m,
                     "fitness": r.fitness, "inlier_rmse_m": r.inlier_rmse_m if np.isfinite(r.inlier_rmse_m) else 0.0,
                     "dx_m": dx, "dy_m": dy, "dyaw_rad": dyaw, "accepted": r.accepted, "reason": r.reason})
    return rows


def read_drive_inputs(ctx: StageContext) -> tuple[list[DriveInput], list[DriveInput]]:
    """The workflow's map drives and reference (eval) drives, from the stage's inputs (wheel odometry only when
    a wheel parameter uses it)."""
    p = ctx.params
    gnss = ctx.inputs.read("poses_gnss")
    edges = ctx.inputs.read("edges")
    info = ctx.inputs.read("drive_info")
    wheel = ctx.inputs.read("odometry", columns=["drive", "stamp_ns", "speed_mps", "yaw_rate_radps"]) \
        if ctx.inputs.has("odometry") and p.factors.uses_wheel else None
    all_drives = sorted(set(gnss["drive"].to_pylist()))
    map_names = list(ctx.settings.get("map_drives") or all_drives)
    eval_names = [d for d in (ctx.settings.get("eval_drives") or []) if d not in map_names]
    missing = [d for d in map_names + eval_names if d not in all_drives]
    if missing:
        raise ConfigError("posegraph settings", [f"drive {d!r} has no poses_gnss rows; have {all_drives}"
                                                 for d in missing])
    spans = ctx.inputs.read("span_edges") if p.factors.span_edges and ctx.inputs.has("span_edges") else None
    prior = ctx.inputs.read("prior") if ctx.inputs.has("prior") else None
    return ([drive_input(d, gnss, edges, info, wheel, spans, prior) for d in map_names],
            [drive_input(d, gnss, edges, info, wheel, spans, prior) for d in eval_names])


class SurveySource:
    """The survey cloud of the stage's inputs, read where it is needed. Picklable (it holds the input reader, not
    the points): the anchor workers read the survey themselves, so the stage's process never holds the raw cloud
    while the loops and anchors run, nor pickles it once per worker (gangnam: 8.3 M points, 230 MB a copy)."""

    has_intensity = True

    def __init__(self, inputs, cache_dir=None):
        import uuid

        self.inputs = inputs
        self.key = uuid.uuid4().hex  # the same in every process it is sent to (``worker_cache`` keys)
        # where the processes that use it share what they derive from it once (``pipeline.parallel.build_once``:
        # the downsampled survey, its normals, its marking tiles); None: each process derives its own
        self.cache_dir = cache_dir

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        """(N,3) ENU points and (N,) intensity, each distinct cloud once (drives that name the same survey file each
        ingest it; stages/common/survey_parts.py)."""
        from pipeline.memory import release_memory
        from stages.common.survey_parts import distinct_survey_partitions

        pts, intensity = [], []
        for key in distinct_survey_partitions(self.inputs):
            t = self.inputs.read("survey", partition=key, columns=["east_m", "north_m", "up_m", "intensity"])
            pts.append(np.column_stack([t[c].to_numpy() for c in ("east_m", "north_m", "up_m")]))
            intensity.append(t["intensity"].to_numpy())
            del t
        if not pts:
            return np.zeros((0, 3)), np.zeros(0, np.float32)
        out = (pts[0], intensity[0]) if len(pts) == 1 else (np.concatenate(pts), np.concatenate(intensity))
        del pts, intensity
        release_memory()  # the Arrow tables' pages (gangnam's 8.3 M points: 730 -> 435 MB resident)
        return out


def read_survey(ctx: StageContext) -> tuple[np.ndarray, np.ndarray]:
    """The survey cloud's (N,3) ENU points and (N,) intensity (``SurveySource.read``)."""
    return SurveySource(ctx.inputs).read()


def compute(ctx: StageContext) -> dict[str, pa.Table]:
    """The stage: its independent inner work (loop verification, anchors) runs on one process pool for the whole
    run (``pipeline.parallel.shared_pool``): its processes start once, and keep the survey's indices between the
    anchoring rounds."""
    from pipeline.parallel import shared_pool
    from stages.posegraph.regions import RegionParams, partitioned, solves_summary

    r = ctx.params.regions
    with shared_pool(), partitioned(RegionParams(**dict(r))) as solves:
        out = _compute(ctx)
    if solves:  # solved region by region (``maps reoptimize``): its figures in the dataset's metadata
        out["_extra"]["region_solve"] = solves_summary(solves)
    return out


def _compute(ctx: StageContext) -> dict[str, pa.Table]:
    cfg: PosegraphParams = ctx.params
    ctx.report_step("reading the drives")
    drives, ref_drives = read_drive_inputs(ctx)
    load = scan_loader(ctx)
    held = read_held_solution(ctx, drives)
    if held is not None:
        return _compute_increment(ctx, cfg, drives, ref_drives, load, held)
    survey_cb, survey_matches = None, []
    if ctx.inputs.has("survey"):
        from stages.posegraph.anchors.survey_anchor import survey_anchor_callback

        survey_cb = survey_anchor_callback(drives, load, SurveySource(ctx.inputs, ctx.scratch_dir / "survey"),
                                           cfg.anchors, survey_matches,
                                           feature_load=scan_loader(ctx, ("intensity", "ring")),
                                           report_step=ctx.report_step)
    sol = solve_map(drives, load, cfg, survey_priors=survey_cb, report_step=ctx.report_step)
    names = [(d.name, int(s)) for d in drives for s in d.scan_ids]
    if cfg.solve.compute_marginals:
        ctx.report_step("marginal covariances")
    cov = _marginals(sol.problem, sol.poses, "the map drives") if cfg.solve.compute_marginals \
        else np.zeros((len(names), 9))
    split = frame_of_map(sol, drives, cov.reshape(-1, 3, 3)) \
        if cfg.solve.compute_marginals else None
    cov_map = split.cov_relative.reshape(-1, 9) if split is not None else cov
    offsets = np.cumsum([0] + [d.n for d in drives])
    optimized = [poses_table("poses_optimized", d, sol.poses[a:b], cov_map[a:b])
                 for d, a, b in zip(drives, offsets[:-1], offsets[1:])]
    odometry = [poses_table("poses_odometry", d, dead_reckoning(d)) for d in drives]
    loop_rows = _loop_rows(sol.loops, names)
    refs = {}
    for k, d in enumerate(ref_drives):
        ctx.report_step(f"reference drive {d.name}", k, len(ref_drives))
        ref = solve_reference(d, drives, sol.poses, load, cfg)
        rcov = _marginals(ref.problem, np.concatenate([ref.poses, ref.problem.initial[d.n:]]), f"drive {d.name!r}"
                          )[:d.n] if cfg.solve.compute_marginals else np.zeros((d.n, 9))
        # solved on the map's poses held fixed: its covariance is relative to the map already
        optimized.append(poses_table("poses_optimized", d, ref.poses, rcov))
        odometry.append(poses_table("poses_odometry", d, dead_reckoning(d)))
        loop_rows += _loop_rows(ref.loops, [(d.name, int(s)) for s in d.scan_ids] + names)
        refs[d.name] = (d, ref)
    out_dir = ctx.artifact_dir("report")
    for d, a, b in zip(drives, offsets[:-1], offsets[1:]):
        write_tum(out_dir / f"{d.name}_optimized_tum.txt", d.stamps_ns * 1e-9, sol.poses[a:b])
        write_kitti(out_dir / f"{d.name}_optimized_kitti.txt", sol.poses[a:b])
        write_tum(out_dir / f"{d.name}_odometry_tum.txt", d.stamps_ns * 1e-9, dead_reckoning(d))
    for name, (d, ref) in refs.items():
        write_tum(out_dir / f"{name}_optimized_tum.txt", d.stamps_ns * 1e-9, ref.poses)
        write_kitti(out_dir / f"{name}_optimized_kitti.txt", ref.poses)
    ctx.report_step("the report")
    kernel = _error_kernel(sol, cfg.solve.error_kernel_pairs_per_bin, split) if cfg.solve.compute_marginals \
        else None
    frame = split.as_dict() | {"source": frame_source_of(sol, drives)} if split is not None else None
    write_report(out_dir, drives, sol, refs, loop_rows, survey_matches, kernel, frame)
    return {"poses_odometry": pa.concat_tables(odometry), "poses_optimized": pa.concat_tables(optimized),
            "loop_closures": loops_table(loop_rows),
            "_extra": {"pose_error_correlation": kernel, "map_frame": frame}}


def read_held_solution(ctx: StageContext, drives: list[DriveInput]):
    """The published solution the workflow's ``held_poses`` setting names (``cornermap rebuild``'s incremental
    default: ``{fingerprint, version}`` of the LATEST version's ``poses_optimized`` dataset), as a ``HeldSolution``;
    None without the setting, or when none of the map drives is in it (a first build solves jointly)."""
    from stages.posegraph.held import read_held

    spec = ctx.settings.get("held_poses")
    if not spec:
        return None
    held = read_held(ctx.settings["root"], spec, drives)
    return held if held.drives else None


def _compute_increment(ctx: StageContext, cfg: PosegraphParams, drives, ref_drives, load, held):
    """The map drives of ``held`` keep their published rows (bit for bit); the others are solved against them
    (``incremental.solve_increment``); reference drives as in the joint solve."""
    from stages.posegraph.incremental import solve_increment

    new = [d for d in drives if d.name not in held.drives]
    old = [d for d in drives if d.name in held.drives]
    held_T = np.concatenate([held.poses_T(d.name) for d in old])
    survey_cb, survey_matches = None, []
    if ctx.inputs.has("survey") and new:
        from stages.posegraph.anchors.survey_anchor import survey_anchor_callback

        survey_cb = survey_anchor_callback(new, load, SurveySource(ctx.inputs, ctx.scratch_dir / "survey"),
                                           cfg.anchors, survey_matches,
                                           feature_load=scan_loader(ctx, ("intensity", "ring")),
                                           report_step=ctx.report_step)
    frame_prior, held_cov, drive_of_row = None, None, None
    if cfg.solve.compute_marginals:  # the window needs the held map's frame covariance (window.py)
        from stages.posegraph.window import frame_prior_of

        frame_prior = frame_prior_of(held.metadata)
        held_cov = np.concatenate([_held_cov(held.rows(d.name)) for d in old])
        drive_of_row = np.repeat(np.arange(len(old)), [d.n for d in old])
    sol = solve_increment(new, old, held_T, load, cfg, max_per_scan=cfg.loops.incremental_max_per_scan,
                          survey_priors=survey_cb, report_step=ctx.report_step, frame=frame_prior, held_cov=held_cov,
                          held_drive_of_row=drive_of_row)
    n = sum(d.n for d in new)
    window = sol.extra.get("window")
    drift = increment_drift(sol, n, held_T)
    if window is not None:
        drift = (drift or {}) | {"frame": window["record"]}
        if window["record"]["advised"]:
            drift["advised"] = list(drift.get("advised", [])) + ["frame"]
    if cfg.solve.compute_marginals and new:
        ctx.report_step("marginal covariances of the new drives")
        # the map poses the loops reach (and the window's frame) held: the covariance is relative to the map
        if window is None:
            cov = _marginals(sol.problem, np.concatenate([sol.poses, sol.problem.initial[n:]]), "the new drives")[:n]
        else:
            cov = _marginals(window["problem_frame_held"], window["solved"], "the new drives")[:n]
    else:
        cov = np.zeros((n, 9))
    offsets = np.cumsum([0] + [d.n for d in new])
    solved = {d.name: (sol.poses[a:b], cov[a:b]) for d, a, b in zip(new, offsets[:-1], offsets[1:])}
    moved: set[str] = set()
    if window is not None:  # the window's held poses moved by the frame correction; the others kept bit for bit
        corrected = window["held_T"]
        moved = {d.name for d, a, b in zip(old, *_bounds(old)) if not np.array_equal(corrected[a:b], held_T[a:b])}
        held_T = corrected
    all_T = {d.name: held_T[a:b] for d, a, b in zip(old, *_bounds(old))} | {k: v[0] for k, v in solved.items()}
    optimized = [held.rows(d.name) if d.name in held.drives and d.name not in moved
                 else poses_table("poses_optimized", d, all_T[d.name], _held_cov(held.rows(d.name)))
                 if d.name in held.drives else poses_table("poses_optimized", d, *solved[d.name]) for d in drives]
    odometry = [poses_table("poses_odometry", d, dead_reckoning(d)) for d in drives]
    names_new = [(d.name, int(s)) for d in new for s in d.scan_ids] + \
        [(d.name, int(s)) for d in old for s in d.scan_ids]
    loop_rows = held.loop_rows() + _loop_rows(sol.loops, names_new)
    map_T = np.concatenate([all_T[d.name] for d in drives])
    refs = {}
    for k, d in enumerate(ref_drives):
        ctx.report_step(f"reference drive {d.name}", k, len(ref_drives))
        ref = solve_reference(d, drives, map_T, load, cfg)
        rcov = _marginals(ref.problem, np.concatenate([ref.poses, ref.problem.initial[d.n:]]), f"drive {d.name!r}"
                          )[:d.n] if cfg.solve.compute_marginals else np.zeros((d.n, 9))
        optimized.append(poses_table("poses_optimized", d, ref.poses, rcov))
        odometry.append(poses_table("poses_odometry", d, dead_reckoning(d)))
        loop_rows += _loop_rows(ref.loops, [(d.name, int(s)) for s in d.scan_ids] +
                                [(m.name, int(s)) for m in drives for s in m.scan_ids])
        refs[d.name] = (d, ref)
    out_dir = ctx.artifact_dir("report")
    for d in drives:
        kept = d.name in held.drives and d.name not in moved
        if kept and held.copy_report_file(f"{d.name}_optimized_tum.txt", out_dir) \
                and held.copy_report_file(f"{d.name}_optimized_kitti.txt", out_dir):
            pass
        else:
            write_tum(out_dir / f"{d.name}_optimized_tum.txt", d.stamps_ns * 1e-9, all_T[d.name])
            write_kitti(out_dir / f"{d.name}_optimized_kitti.txt", all_T[d.name])
        write_tum(out_dir / f"{d.name}_odometry_tum.txt", d.stamps_ns * 1e-9, dead_reckoning(d))
    for name, (d, ref) in refs.items():
        write_tum(out_dir / f"{name}_optimized_tum.txt", d.stamps_ns * 1e-9, ref.poses)
        write_kitti(out_dir / f"{name}_optimized_kitti.txt", ref.poses)
    ctx.report_step("the report")
    from stages.posegraph.solve import Solution

    # the frame covariance the next night starts from: this night's window's record, else the held one's
    frame_rec = window["record"] if window is not None else (held.metadata.get("incremental") or {}).get("frame")
    report_problem = sol.problem
    if window is not None:  # the report's residuals are the new drives' factors: without the window's frame ties
        from dataclasses import replace

        report_problem = replace(sol.problem, betweens=[b for b in sol.problem.betweens if b.kind != "frame"])
    new_sol = Solution(sol.poses, report_problem, sol.loops, sol.timings_s, sol.survey_rounds)
    frame, kernel = held.metadata.get("map_frame"), held.metadata.get("pose_error_correlation")
    write_report(out_dir, new, new_sol, refs, loop_rows, survey_matches, kernel, frame,
                 incremental={"held_version": held.version, "held_drives": [d.name for d in old],
                              "new_drives": [d.name for d in new], **sol.timings_s, "drift": drift,
                              "moved_drives": sorted(moved)})
    return {"poses_odometry": pa.concat_tables(odometry), "poses_optimized": pa.concat_tables(optimized),
            "loop_closures": loops_table(loop_rows),
            "_extra": {"pose_error_correlation": kernel, "map_frame": frame,
                       "incremental": {"held_version": held.version, "new_drives": [d.name for d in new],
                                       "drift": drift, "moved_drives": sorted(moved),
                                       **({"frame": frame_rec} if frame_rec else {})}}}


def _held_cov(rows: pa.Table) -> np.ndarray:
    """(N,9) published ``cov_xy_yaw`` of held rows (zeros where the column is absent or null)."""
    if "cov_xy_yaw" not in rows.column_names or rows["cov_xy_yaw"].null_count:
        return np.zeros((rows.num_rows, 9))
    return np.asarray(rows["cov_xy_yaw"].combine_chunks().flatten().to_numpy(zero_copy_only=False),
                      float).reshape(-1, 9)


def increment_drift(sol, n: int, held_T: np.ndarray, **drift_kw) -> dict | None:
    """``drift.loop_drift`` of an incremental solution: the map poses its loops reach are the graph's poses n.. (held
    by ``fixed`` priors at their published values), found back among ``held_T`` by position."""
    from stages.posegraph.drift import loop_drift

    if n == 0 or not len(held_T):
        return None
    if "held_of" in sol.extra:  # solve_increment's: graph pose -> held row
        held_rows = dict(sol.extra["held_of"])
    else:  # a solution without it: its held poses are the ``fixed`` priors, found back among held_T by position
        row_of = {tuple(np.round(T[:3, 3], 9)): k for k, T in enumerate(held_T)}
        held_rows = {p.i: row_of[tuple(np.round(p.T_map_vehicle[:3, 3], 9))] for p in sol.problem.pose_priors
                     if p.kind == "fixed" and p.i >= n}
    window = sol.extra.get("window")
    poses = window["solved"] if window is not None else np.concatenate([sol.poses, sol.problem.initial[n:]])
    return loop_drift(sol.problem, poses, n, held_rows, held_T[:, :2, 3], **drift_kw)


def _bounds(drives):
    offsets = np.cumsum([0] + [d.n for d in drives])
    return offsets[:-1], offsets[1:]


def frame_of_map(sol, drives: list[DriveInput], marginals_enu: np.ndarray):
    """The map drives' frame error and relative covariances (``map_frame.split_map_frame``), logged."""
    from stages.posegraph.map_frame import split_map_frame

    group = np.repeat(np.arange(len(drives)), [d.n for d in drives])
    split = split_map_frame(sol.problem, sol.poses, group, marginals_enu)
    c = split.cov_frame
    log.info("posegraph: map frame against ENU (%s): std (%.3f, %.3f) m at (%.1f, %.1f), %.3f deg, scale %.1e; "
             "poses relative to it %.3f m RMS (absolute %.3f m)",
             frame_source_of(sol, drives),
             np.sqrt(c[0, 0]), np.sqrt(c[1, 1]), *split.reference_en_m, np.degrees(np.sqrt(c[2, 2])), split.scale_std,
             np.sqrt(np.mean(np.trace(split.cov_relative[:, :2, :2], axis1=1, axis2=2))),
             np.sqrt(np.mean(marginals_enu[:, 0, 0] + marginals_enu[:, 1, 1])))
    return split


def frame_source_of(sol, drives: list[DriveInput]) -> str:
    """What fixes the map's frame: survey anchors, else the drives' GNSS/INS, prior trajectories (ENU or local with
    a start pose) and start poses, named in that order."""
    if any(r.get("anchors") for r in sol.survey_rounds):
        return "survey anchors"
    kinds = {p.kind for p in sol.problem.pose_priors} | {b.kind for b in sol.problem.betweens}
    parts = ["GNSS/INS"] if any(d.gnss_valid.any() for d in drives) else []
    parts += [name for kind, name in (("prior", "prior trajectory"), ("start", "start pose")) if kind in kinds]
    return " + ".join(parts) or "the first pose held"


def _error_kernel(sol, per_bin: int, split=None) -> dict | None:
    """The map drives' pose-error correlation kernel (``error_correlation``) for the map's metadata; None when
    off (``per_bin`` 0) or when gtsam's Cholesky marginals give up."""
    from stages.posegraph.error_correlation import pose_error_kernel
    from stages.posegraph.factors.graph import build_graph

    if per_bin <= 0:
        return None
    graph, values, _ = build_graph(sol.problem, sol.poses)
    kernel = pose_error_kernel(graph, values, sol.poses, sol.problem.n_poses, per_bin=per_bin, split=split)
    if kernel is None:
        return None
    log.info("posegraph: pose errors correlate %.2f exp(-d^2 / 2 (%.0f m)^2) (%d pose pairs of the map drives)",
             kernel.share, kernel.length_m, kernel.n_pairs)
    return kernel.as_dict()
