"""The pose-graph stage's committed output against the simulator's truth (the figures of docs/posegraph.md).

Reads ``poses_optimized`` and ``poses_gnss`` of the workflow's plan (the fingerprints the plan picks; run the stage
first: ``cornermap run WF --only posegraph`` or the whole workflow) and the simulator's truth trajectories, then
prints per drive the RTK/INS-only and optimised figures of ``stages.common.trajectory_metrics.summarize`` and the
map-vs-reference agreement (revisit pairs across the drives, within ``--pair-radius-m`` in truth), and per drive
whether the covariances the poses carry hold their errors relative to the map frame (the truth rigidly fitted onto
the first drive's poses; stated vs true RMS, NEES of the horizontal position:
``trajectory_metrics.horizontal_covariance_consistency``; the map's corner covariance carries them) and the map
frame's stated error (the poses' ``map_frame`` metadata) beside the true one.

    .venv/bin/python -m bench.bench_posegraph_eval -w workflows/gangnam.yaml [--root runs/gangnam] [--params P.yaml]
    .venv/bin/python -m bench.bench_posegraph_eval -w BUILD/bench_build.yaml --sim SIM   # a bench_build --keep root

``--params`` is the file the run was made with (``cornermap run tiny --root R --params P.yaml``): without it the plan
is the workflow's own and finds nothing committed. The benches are not installed with the product: run them from
the checkout, or with ``PYTHONPATH=CHECKOUT`` from elsewhere.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

KEYS = ["abs_horizontal_rms_m", "abs_horizontal_max_m", "self_consistency_rms_m", "self_consistency_heading_rms_deg",
        "relative_10m_rms_m", "heading_rms_deg", "vertical_rms_m", "drift_100m_percent"]


def committed(plan, stage: str, key: str, dataset: str):
    """A reader of one committed output of ``stage`` in ``plan`` (arg ``key``)."""
    from pipeline.errors import DatasetIOError
    from pipeline.reader import StoreInputReader

    sp = plan.stages[stage]
    if not sp.committed:
        raise DatasetIOError(f"{plan.root}: stage {stage!r} has no committed output for this plan; run it first")
    return StoreInputReader(plan.root, {key: (dataset, sp.fingerprint)}, {key: None})


def marginals_xy(table, drive: str) -> np.ndarray:
    """(N,2,2) horizontal block of ``cov_xy_yaw`` of ``drive``'s rows, in scan order (``Trajectory.from_table``'s)."""
    import pyarrow.compute as pc

    rows = table.filter(pc.equal(table["drive"], drive)).sort_by("scan_id")
    cov = np.asarray(rows["cov_xy_yaw"].combine_chunks().flatten().to_numpy(), dtype=float).reshape(-1, 3, 3)
    return cov[:, :2, :2]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-w", "--workflow", type=Path, required=True)
    ap.add_argument("--root", type=Path, default=None, help="default: the workflow's root")
    ap.add_argument("--params", type=Path, default=None, help="the --params file the run was made with")
    ap.add_argument("--pair-radius-m", type=float, default=8.0)
    ap.add_argument("--sim", type=Path, default=None, help="the simulated folder (with truth/) when the workflow "
                    "reads drives simulated apart, e.g. bench_build's (keep its root with --keep)")
    args = ap.parse_args()

    from bench.bench_posegraph import truth_poses
    from pipeline.api import load_param_file
    from pipeline.plan import make_plan
    from pipeline.store import dataset_dir
    from pipeline.workflow import load_workflow
    from stages.common import trajectory_metrics as M
    from stages.common.geometry import fit_rigid_2d
    from stages.common.records import Trajectory

    wf = load_workflow(args.workflow, param_overrides=load_param_file(args.params))
    plan = make_plan(wf, wf.root_dir(args.root))
    if args.sim is not None:
        sim = args.sim
    elif "simulate" in plan.stages:
        sim = dataset_dir(plan.root, "raw_drives", plan.stages["simulate"].fingerprint) / "artifacts" / "all"
    else:
        raise SystemExit("the workflow has no simulate stage: name the simulated folder with --sim DIR")
    optimized = committed(plan, "posegraph", "poses", "poses_optimized").read("poses")
    gnss = committed(plan, "ingest", "gnss", "poses_gnss").read("gnss")
    drives = sorted(set(optimized["drive"].to_pylist()))
    print(f"root {plan.root}; drives {drives}")
    print("| drive | trajectory | " + " | ".join(KEYS) + " |")
    print("|---" * (len(KEYS) + 2) + "|")
    est_all, true_all, t_all, frames, stated = [], [], [], [], []
    for n, drive in enumerate(drives):
        opt = Trajectory.from_table(optimized, drive)
        T_true = truth_poses(sim, drive, opt.stamp_ns)
        g = Trajectory.from_table(gnss, drive)
        on_opt = np.isin(g.scan_id, opt.scan_id)
        stamps_s = opt.stamp_ns * 1e-9
        for name, T in (("RTK/INS only", g.T[on_opt]), ("optimised", opt.T)):
            s = M.summarize(T, T_true, stamps_s)
            print(f"| {drive} | {name} | " + " | ".join("-" if np.isnan(s[k]) else f"{s[k]:.3f}" for k in KEYS) + " |")
        if n == 0:  # the map frame: the truth fitted onto the first (map) drive, as truth_in_map fits the corners
            R_map, t_map = fit_rigid_2d(T_true[:, :2, 3], opt.T[:, :2, 3])
        T_in_map = T_true.copy()
        T_in_map[:, :2, 3] = T_true[:, :2, 3] @ R_map.T + t_map
        c = M.horizontal_covariance_consistency(opt.T, T_in_map, marginals_xy(optimized, drive))
        stated.append(f"{drive}: stated vs true relative to the map frame (the pose graph's covariances, which the "
                      f"map's corner covariance carries, against the truth fitted onto {drives[0]}): stated "
                      f"{c['stated_rms_m']:.4f} m RMS, true {c['true_rms_m']:.4f} m; NEES (2 dof) "
                      f"mean {c['nees_mean']:.2f} (2 when honest), {c['nees_share_q95']:.2f} under its 95 % "
                      f"quantile")
        R, t = fit_rigid_2d(opt.T[:, :2, 3], T_true[:, :2, 3])
        centroid = opt.T[:, :2, 3].mean(axis=0)
        frames.append(f"{drive}: map frame vs the truth's: rotation {np.degrees(np.arctan2(R[1, 0], R[0, 0])):+.3f} "
                      f"deg, offset at the drive's centroid {np.linalg.norm(R @ centroid + t - centroid):.3f} m "
                      f"(rigid 2-D fit of the optimised positions onto the truth)")
        est_all.append(opt.T)
        true_all.append(T_true)
        t_all.append(stamps_s + 1e6 * n)  # drives apart in time: every pair across drives is a revisit
    frame = committed(plan, "posegraph", "poses", "poses_optimized").metadata("poses").get("map_frame")
    if frame:
        from bench.bench_map_frame import frame_error
        from stages.common.geometry import wrap_angle_rad
        from stages.posegraph.map_frame import travel_weights

        est, tru = est_all[0], true_all[0]  # the map drive (one map drive: the workflows' layout)
        yaw = lambda T: np.arctan2(T[:, 1, 0], T[:, 0, 0])  # noqa: E731
        g, _ = frame_error(est[:, :2, 3], tru[:, :2, 3], wrap_angle_rad(yaw(est) - yaw(tru)),
                           travel_weights(est[:, :2, 3]), np.asarray(frame["reference_en_m"], float))
        cov = np.asarray(frame["cov_shift_rotation"], float)
        frames.append(f"stated map frame ({frame.get('source')}): std {frame['std_east_m']:.3f} / "
                      f"{frame['std_north_m']:.3f} m at {np.round(frame['reference_en_m'], 1).tolist()}, "
                      f"{frame['std_rotation_deg']:.3f} deg; true ({g[0]:+.3f}, {g[1]:+.3f}) m, "
                      f"{np.degrees(g[2]):+.3f} deg; NEES (3 dof) {g @ np.linalg.solve(cov, g):.2f}")
    print("\n".join(frames + stated))
    if len(drives) > 1:
        pairs = M.revisit_pairs(np.concatenate(true_all), np.concatenate(t_all), radius_m=args.pair_radius_m)
        first = len(est_all[0])
        across = pairs[(pairs[:, 0] < first) != (pairs[:, 1] < first)]
        err = M.self_consistency_errors_m(np.concatenate(est_all), np.concatenate(true_all), across)
        print(f"map ({drives[0]}) vs the other drives: {M.rms(err):.3f} m RMS over {len(across)} pairs within "
              f"{args.pair_radius_m:g} m")


if __name__ == "__main__":
    main()
