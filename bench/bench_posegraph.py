"""Pose-graph bench on a simulated city: RTK/INS-only, ICP-only and optimised errors against ground truth,
with and without survey anchoring, with a planted false loop, and the optimisation time.

    .venv/bin/python -m bench.bench_posegraph --preset tiny --seed 7 --sim runs/sim-tiny

Keeps the scans in memory (fine for tiny/demo; gangnam needs the engine's store: `cornermap run`).
"""
from __future__ import annotations

import argparse
import logging
import os
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from pipeline.declare import PartitionKey
from pipeline.testing import make_context


def _tables(out) -> pa.Table:
    parts = [out] if isinstance(out, pa.Table) else list(out)
    return pa.concat_tables(parts) if parts else None


def ingest(sim: Path, drives: list[str]) -> dict[str, pa.Table]:
    import json

    from stages.ingest.compute import compute
    from stages.ingest.params import IngestParams

    origin = json.loads((sim / "simulation.json").read_text())["enu_origin"]  # the truth's ENU frame

    paths = {d: sim / d / "drive.yaml" for d in drives}
    acc: dict[str, list] = {}
    for d in drives:
        ctx = make_context("ingest", IngestParams(), {}, partition=PartitionKey(drive=d), drives=paths,
                           settings={"enu_origin": origin})
        out = compute(ctx)
        for key in ("scans", "poses_gnss", "drive_info", "survey", "odometry"):
            t = _tables(out[key])
            if t is not None and t.num_rows:
                acc.setdefault(key, []).append(t)
    return {k: pa.concat_tables(v) for k, v in acc.items()}


def _overrides(pairs: list[str]) -> dict:
    """KEY=VALUE strings -> dict (values parsed as JSON when possible, else kept as strings); a dotted KEY names a
    section's key (``loops.radius_m=20`` -> ``{"loops": {"radius_m": 20}}``)."""
    import json

    from pipeline.declare import nested

    out = {}
    for kv in pairs:
        key, _, value = kv.partition("=")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return nested(out)


def run_odometry(tables, overrides: dict | None = None) -> tuple[pa.Table, float, int]:
    from stages.odometry.compute import compute
    from stages.odometry.params import OdometryParams

    parts = sorted(set(zip(tables["scans"]["drive"].to_pylist(), tables["scans"]["chunk"].to_pylist())))
    t0 = time.perf_counter()
    edges = []
    for d, c in parts:
        ctx = make_context("odometry", OdometryParams(**(overrides or {})), tables,
                           partition=PartitionKey(drive=d, chunk=c))
        edges.append(compute(ctx)["edges"])
    dt = time.perf_counter() - t0
    e = pa.concat_tables(edges)
    return e, dt, e.num_rows


def truth_poses(sim: Path, drive, stamps_ns: np.ndarray) -> np.ndarray:
    from stages.common.records import Trajectory

    truth = Trajectory.from_tum(sim / "truth" / f"{drive}_poses_tum.txt")
    t, T = truth.stamp_s, truth.T
    s = stamps_ns * 1e-9
    if abs(s[0] - t[0]) > 1e5:  # different epochs (week seconds vs full GPS time): align on the first scan
        s = s - s[0] + t[0]
    idx = np.clip(np.searchsorted(t, s - 1e-4), 0, len(t) - 1)
    return T[idx]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--sim", type=Path, default=None)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a posegraph param (repeatable), e.g. --set gnss.every_s=2")
    ap.add_argument("--odometry-set", action="append", default=[], metavar="KEY=VALUE",
                    help="override an odometry param (repeatable)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    from stages.common import trajectory_metrics as M
    from stages.posegraph.anchors.survey_anchor import SurveyArrays, survey_anchor_callback
    from stages.posegraph.factors.drive import dead_reckoning
    from stages.posegraph.factors.graph import marginal_cov_xy_yaw
    from stages.posegraph.loops.verify import LoopRecord
    from stages.posegraph.params import PosegraphParams
    from stages.posegraph.solve import solve_map, solve_reference
    from stages.posegraph.tables import drive_input

    sim = args.sim or Path(f"runs/sim-{args.preset}-{args.seed}")
    if not (sim / "simulation.json").exists():
        from stages.simulate.core import simulate

        simulate(args.preset, args.seed, sim)
    drives = sorted(p.name for p in sim.iterdir() if p.name.startswith("drive_"))
    from stages.odometry.params import OdometryParams
    print(f"machine: {os.cpu_count()} cores; preset {args.preset} seed {args.seed}; drives {drives}")
    tables = ingest(sim, drives)
    edges, dt, n = run_odometry(tables, _overrides(args.odometry_set))
    print(
        f"odometry: {n} edges in {dt:.1f} s = {n / dt:.1f} scans/s incl. in-memory table filtering "
        f"(GICP, {OdometryParams().prepare.voxel_m} m voxels)"
    )
    tables["edges"] = edges
    scans = tables["scans"]

    def load(requests):
        out = {}
        for d in sorted({r[0] for r in requests}):
            ids = sorted({s for dd, s in requests if dd == d})
            tab = scans.filter((pc.field("drive") == d) & pc.field("scan_id").isin(ids))
            sid = tab["scan_id"].to_numpy()
            xyz = np.column_stack([tab[c].to_numpy().astype(float) for c in ("x_m", "y_m", "z_m")])
            toff = tab["time_offset_s"].to_numpy().astype(float)
            for s in ids:
                m = sid == s
                out[(d, s)] = (xyz[m], toff[m] if np.any(toff[m] != 0) else None)
        return out

    cfg = PosegraphParams.model_validate(_overrides(args.set))
    map_d = [drive_input(drives[0], tables["poses_gnss"], edges, tables["drive_info"])]
    truth = truth_poses(sim, drives[0], map_d[0].stamps_ns)
    stamps_s = map_d[0].stamps_ns * 1e-9
    rows = {"RTK/INS only": map_d[0].gnss_T, "ICP only (dead reckoning)": dead_reckoning(map_d[0])}
    t0 = time.perf_counter()
    sol = solve_map(map_d, load, cfg)
    t_solve = time.perf_counter() - t0
    rows["optimised"] = sol.poses
    t0 = time.perf_counter()
    marginal_cov_xy_yaw(sol.problem, sol.poses)
    t_marg = time.perf_counter() - t0
    # planted false loop: two scans ~20 m apart in truth declared the same place
    i = 10
    j = int(np.argmin(np.abs(np.linalg.norm(truth[:, :2, 3] - truth[i, :2, 3], axis=1) - 20.0)))
    planted = LoopRecord(i, j, 0.0, 0.95, 0.05, np.eye(4), True, "planted",
                         np.diag([0.0005 ** -2] * 3 + [0.02 ** -2] * 3))
    sol_false = solve_map(map_d, load, cfg, extra_loops=[planted])
    rows["optimised + planted false loop"] = sol_false.poses
    if "survey" in tables:
        pts = np.column_stack([tables["survey"][c].to_numpy() for c in ("east_m", "north_m", "up_m")])
        matches = []
        anchors = survey_anchor_callback(map_d, load, SurveyArrays(pts), cfg.anchors, matches)
        sol_s = solve_map(map_d, load, cfg, survey_priors=anchors)
        rows["optimised + survey anchors"] = sol_s.poses
        print(f"survey anchors: {sum(m.accepted for m in matches)} accepted of {len(matches)}")
    print(f"map drive {drives[0]}: {len(truth)} scans; loops {sum(r.accepted for r in sol.loops)} accepted of "
          f"{len(sol.loops)}; planted loop accepted={planted.accepted} ({planted.reason})")
    print(f"optimisation {t_solve:.2f} s (timings {({k: round(v, 2) for k, v in sol.timings_s.items()})}), "
          f"marginals {t_marg:.2f} s")
    keys = ["abs_horizontal_rms_m", "abs_horizontal_max_m", "self_consistency_rms_m", "n_revisit_pairs",
            "relative_10m_rms_m", "heading_rms_deg", "vertical_rms_m", "pitch_rms_deg", "drift_100m_percent"]
    print("| trajectory | " + " | ".join(keys) + " |")
    for name, T in rows.items():
        s = M.summarize(T, truth, stamps_s)
        print(f"| {name} | " + " | ".join(f"{s[k]:.3f}" if isinstance(s[k], float) else str(s[k]) for k in keys) + " |")
    for d in drives[1:]:
        ref_d = drive_input(d, tables["poses_gnss"], edges, tables["drive_info"])
        ref = solve_reference(ref_d, map_d, sol.poses, load, cfg)
        T_true = truth_poses(sim, d, ref_d.stamps_ns)
        both_est = np.concatenate([sol.poses, ref.poses])
        both_true = np.concatenate([truth, T_true])
        both_t = np.concatenate([stamps_s, ref_d.stamps_ns * 1e-9 + 1e6])
        pairs = M.revisit_pairs(both_true, both_t, radius_m=6.0)  # tiny's second drive: the other lane, 3.5 m
        sc = M.rms(M.self_consistency_errors_m(both_est, both_true, pairs))
        s = M.summarize(ref.poses, T_true, ref_d.stamps_ns * 1e-9)
        print(
            f"reference drive {d}: loops {sum(r.accepted for r in ref.loops)}/{len(ref.loops)}; map vs "
            f"reference self-consistency RMS {sc:.3f} m over {len(pairs)} pairs; abs horizontal RMS "
            f"{s['abs_horizontal_rms_m']:.3f} m; "
            f"RTK/INS-only {M.rms(M.horizontal_errors_m(ref_d.gnss_T, T_true)):.3f} m"
        )


if __name__ == "__main__":
    main()
