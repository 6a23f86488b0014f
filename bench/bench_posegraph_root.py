"""Pose-graph bench on a committed pipeline root (e.g. gangnam): the posegraph stage's own inputs (the workflow's
plan picks the fingerprints), solved in process without survey anchoring, with and without a planted false loop,
against the simulator's truth. Upstream stages must be committed (`cornermap run WF --only odometry`).

    .venv/bin/python -m bench.bench_posegraph_root -w workflows/gangnam.yaml [--set KEY=VALUE] [--no-plant]

Below the table, what the inputs can carry at best: the true trajectory's shape rigidly fitted to the GNSS fixes
(no odometry can do better than a perfect shape: the residual frame error is the GNSS bias averaged over the
drive), the heading error of GNSS chords over 100-800 m (the bias gradient) and the dead reckoning's heading
drift over the same distances; where the two cross is roughly the heading a graph of the two can reach.

The planted loop declares two scans of the first map drive the same place although they are ~20 m apart in
truth, with the confident information of a good loop (0.02 m, 0.03 deg). Loop verification reads the scans
it needs from the store (row groups by key), as the stage does.
"""
from __future__ import annotations

import argparse
import logging
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.bench_posegraph import _overrides, truth_poses


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-w", "--workflow", type=Path, required=True)
    ap.add_argument("--root", type=Path, default=None, help="default: the workflow's root")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="posegraph param override")
    ap.add_argument("--no-plant", action="store_true", help="skip the planted-false-loop solve")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)

    from pipeline.api import stage_context
    from pipeline.plan import make_plan
    from pipeline.store import dataset_dir
    from pipeline.workflow import load_workflow
    from stages.common import trajectory_metrics as M
    from stages.posegraph.compute import read_drive_inputs, scan_loader
    from stages.posegraph.factors.drive import dead_reckoning
    from stages.posegraph.loops.verify import LoopRecord
    from stages.posegraph.solve import solve_map

    wf = load_workflow(args.workflow, param_overrides={"posegraph": _overrides(args.set)})
    root = wf.root_dir(args.root)
    plan = make_plan(wf, root)
    sp = plan.stages["posegraph"]
    missing = [f"{arg} ({ds})" for arg, (ds, fp) in sp.inputs.items()
               if arg not in sp.decl.optional_inputs and not fp]
    if missing:
        raise SystemExit(f"{root}: no committed input for posegraph: {', '.join(missing)}; run the upstream stages")
    ctx = stage_context(plan, "posegraph", Path(tempfile.mkdtemp(prefix="bench-pg-")))
    cfg = ctx.params
    drives, _ = read_drive_inputs(ctx)
    sim = dataset_dir(plan.root, "raw_drives", plan.stages["simulate"].fingerprint) / "artifacts" / "all"
    truth = truth_poses(sim, drives[0].name, drives[0].stamps_ns)
    stamps_s = drives[0].stamps_ns * 1e-9
    load = scan_loader(ctx)
    print(f"machine: {os.cpu_count()} cores; root {plan.root}; map drives {[d.name for d in drives]}; "
          f"{sum(d.n for d in drives)} poses; survey anchoring off")

    rows = {"RTK/INS only": drives[0].gnss_T, "ICP + wheel only (dead reckoning)": dead_reckoning(drives[0])}
    t0 = time.perf_counter()
    sol = solve_map(drives, load, cfg)
    print(f"solve {time.perf_counter() - t0:.0f} s (timings {({k: round(v, 1) for k, v in sol.timings_s.items()})}); "
          f"loops {sum(r.accepted for r in sol.loops)} accepted of {len(sol.loops)}")
    rows["optimised"] = sol.poses[:drives[0].n]
    if not args.no_plant:
        i = drives[0].n // 8
        j = int(np.argmin(np.abs(np.linalg.norm(truth[:, :2, 3] - truth[i, :2, 3], axis=1) - 20.0)
                          + 1e3 * (np.abs(np.arange(drives[0].n) - i) < 300)))  # another pass, 20 m away
        planted = LoopRecord(i, j, 0.0, 0.95, 0.02, np.eye(4), True, "planted",
                             np.diag([0.0005 ** -2] * 3 + [0.02 ** -2] * 3))
        t0 = time.perf_counter()
        sol_false = solve_map(drives, load, cfg, extra_loops=[planted])
        d_true = float(np.linalg.norm(truth[i, :2, 3] - truth[j, :2, 3]))
        print(f"planted loop scans {i} <-> {j} ({d_true:.1f} m apart in truth): accepted={planted.accepted} "
              f"({planted.reason}); solve {time.perf_counter() - t0:.0f} s")
        rows["optimised + planted false loop"] = sol_false.poses[:drives[0].n]
    keys = ["abs_horizontal_rms_m", "abs_horizontal_max_m", "self_consistency_rms_m",
            "self_consistency_heading_rms_deg", "relative_10m_rms_m", "relative_10m_horizontal_rms_m",
            "heading_rms_deg", "vertical_rms_m", "drift_100m_percent"]
    print(f"| {drives[0].name} | " + " | ".join(keys) + " |")
    print("|---" * (len(keys) + 1) + "|")
    for name, T in rows.items():
        s = M.summarize(T, truth, stamps_s)
        print(f"| {name} | " + " | ".join(f"{s[k]:.3f}" for k in keys) + " |")
    print_information_bound(truth, drives[0].gnss_T, drives[0].gnss_valid, rows["ICP + wheel only (dead reckoning)"])
    print_edge_heading_calibration(drives[0], truth)


def print_information_bound(truth: np.ndarray, gnss_T: np.ndarray, valid: np.ndarray, dead_reckoning: np.ndarray):
    from stages.common import trajectory_metrics as M
    from stages.common.geometry import fit_rigid_2d, wrap_angle_rad

    xy, g = truth[:, :2, 3], gnss_T[:, :2, 3]
    R, t = fit_rigid_2d(xy[valid], g[valid])
    err = np.linalg.norm(xy @ R.T + t - xy, axis=1)
    print(f"GNSS fixes vs truth: horizontal RMS {M.rms(np.linalg.norm(g[valid] - xy[valid], axis=1)):.3f} m; "
          f"true shape rigidly fitted to them (a perfect odometry): abs RMS {M.rms(err):.3f} m, max {err.max():.3f} m, "
          f"heading {abs(np.rad2deg(np.arctan2(R[1, 0], R[0, 0]))):.3f} deg")
    h_dr = M.heading_errors_rad(dead_reckoning, truth)
    parts = []
    for L in (50.0, 100.0, 200.0, 400.0, 800.0):
        i, j = M.pairs_at_travel(truth, L)
        ok = valid[i] & valid[j]
        chord = xy[j[ok]] - xy[i[ok]]
        normal = np.column_stack([-chord[:, 1], chord[:, 0]]) / np.linalg.norm(chord, axis=1)[:, None] ** 2
        gnss_deg = np.rad2deg(M.rms(np.sum((g[j[ok]] - xy[j[ok]] - g[i[ok]] + xy[i[ok]]) * normal, axis=1)))
        dr_deg = np.rad2deg(M.rms(wrap_angle_rad(h_dr[j] - h_dr[i])))
        parts.append(f"{L:.0f} m: GNSS chord {gnss_deg:.3f} / dead reckoning {dr_deg:.3f}")
    print("heading error over a travel of " + "; ".join(parts) + " deg (RMS)")


def print_edge_heading_calibration(drive, truth: np.ndarray) -> None:
    """Heading error of the accepted ICP edges vs truth by the edge's turn, beside the std their information
    claims (odometry's floors and ``rot_sigma_per_rad``): the check behind that parameter's default."""
    from stages.common.trajectory_metrics import edge_yaw_calibration

    k = np.flatnonzero(drive.edge_ok[1:]) + 1
    sets = [("consecutive", k - 1, k, drive.edge_T[k], drive.edge_info[k])]
    if drive.spans is not None:
        span = drive.spans.j - drive.spans.i
        sets += [(f"span {n}", drive.spans.i[span == n], drive.spans.j[span == n], drive.spans.T_i_j[span == n],
                  drive.spans.information[span == n]) for n in np.unique(span)]
    print("edge heading vs truth by turn (deg): bin n error-RMS / model-std-median NEES")
    for name, i, j, T, info in sets:
        rows = edge_yaw_calibration(T, info, truth, i, j, (0.0, 1.0, 5.0, 20.0, 45.0, 180.0))
        print(f"  {name}: " + "; ".join(f"[{r['lo_deg']:.0f},{r['hi_deg']:.0f}) {r['n']} {r['error_rms_deg']:.4f} / "
                                        f"{r['model_sigma_median_deg']:.4f} {r['nees']:.2f}" for r in rows))


if __name__ == "__main__":
    main()
