"""Keyframe drives: the odometry's edges and a build's trajectory against the simulator's truth.

A keyframe drive is made from a simulated drive by keeping every N-th scan (``fixtures.keyframes``: renumbered, one
stamp per line, no wheel odometry). Variants: ``gnss`` (the drive's GNSS/INS, no prior), ``gnss+prior`` (and a prior
trajectory in ENU), ``prior`` (no GNSS: the ENU prior is the drive's absolute input), ``local`` (no GNSS: a prior in a
local frame aligned at a start heading 0.3 deg off), ``none`` (neither: odometry alone, edges only; no build). Each
built variant runs ingest, odometry and posegraph through the engine (one thread) under ``--root``.

Per variant: edges (consecutive keyframes), how many the gate rejected, the accepted edges' error against the truth
(RMS and max of the translation and yaw errors), how each edge was started (prior / GNSS / global registration /
constant velocity: ``odometry_edges`` does not record it, the log does), and the optimised trajectory against the
truth (``trajectory_metrics.summarize``: horizontal RMS / max, heading RMS).

    .venv/bin/cornermap simulate --preset tiny --seed 7 --out SIM --drives 1
    .venv/bin/python -m bench.bench_keyframes --sim SIM --every 12 --root ROOT [--variants gnss prior none]
        [--set odometry.KEY=VALUE]

The benches are not installed with the product: run them from the checkout.
"""
from __future__ import annotations

import argparse
import json
import logging
import shutil
import time
from pathlib import Path

import numpy as np
import yaml

VARIANTS = ("gnss", "gnss+prior", "prior", "local", "none")


def _edges_vs_truth(edges, T_true: np.ndarray) -> dict:
    from stages.common.records import pose_matrices

    e = edges.sort_by("scan_id")
    ids = e["scan_id"].to_numpy()
    T_e = pose_matrices(e, position=("dx_m", "dy_m", "dz_m"))
    accepted = e["accepted"].to_numpy(zero_copy_only=False).astype(bool)
    rel = np.linalg.inv(T_true[ids - 1]) @ T_true[ids]
    D = np.linalg.inv(rel) @ T_e
    dt = np.linalg.norm(D[:, :3, 3], axis=1)
    dyaw = np.degrees(np.abs(np.arctan2(D[:, 1, 0], D[:, 0, 0])))
    step = np.linalg.norm(rel[:, :2, 3], axis=1)
    a = accepted
    return {"edges": int(len(ids)), "rejected": int((~a).sum()), "spacing_median_m": float(np.median(step)),
            "accepted_rms_m": float(np.sqrt(np.mean(dt[a] ** 2))) if a.any() else float("nan"),
            "accepted_max_m": float(dt[a].max()) if a.any() else float("nan"),
            "accepted_yaw_rms_deg": float(np.sqrt(np.mean(dyaw[a] ** 2))) if a.any() else float("nan"),
            "all_over_0.3m": int((dt > 0.3).sum())}


def _odometry_in_memory(drive_yaml: Path, name: str, odometry_params: dict):
    """ingest + odometry without the engine (a drive no build accepts: no GNSS, no prior)."""
    import pyarrow as pa

    from fixtures.keyframes import SIM_ORIGIN
    from pipeline.declare import PartitionKey, nested
    from pipeline.testing import make_context
    from stages.ingest.compute import compute as ingest
    from stages.ingest.params import IngestParams
    from stages.odometry.compute import compute as odometry
    from stages.odometry.params import OdometryParams

    ctx = make_context("ingest", IngestParams(), partition=PartitionKey(drive=name), drives={name: drive_yaml},
                       settings={"enu_origin": SIM_ORIGIN})
    out = ingest(ctx)
    tables = {}
    for key, ds in (("scans", "scans"), ("poses_gnss", "poses_gnss"), ("drive_info", "drive_info"),
                    ("poses_prior", "poses_prior")):
        parts = [out[ds]] if isinstance(out[ds], pa.Table) else list(out[ds])
        tables[key] = pa.concat_tables(parts)
    chunks = sorted(set(tables["scans"]["chunk"].to_pylist()))
    edges = []
    for c in chunks:
        octx = make_context("odometry", OdometryParams.model_validate(nested(odometry_params)), tables,
                            partition=PartitionKey(drive=name, chunk=c))
        edges.append(odometry(octx)["edges"])
    return pa.concat_tables(edges)


def _build(drive_yaml: Path, name: str, root: Path, params: dict):
    """ingest, odometry, posegraph of the drive through the engine; (odometry_edges, poses_optimized)."""
    from bench.bench_posegraph_eval import committed
    from fixtures.keyframes import SIM_ORIGIN
    from pipeline.api import execute_workflow
    from stages.common.tiling import DEFAULT_TILE_SIZE_M

    wf = {"name": f"keyframes-{name}", "root": str(root), "map_name": "keyframes", "scheduler": "sync",
          "enu_origin": SIM_ORIGIN, "tile_size_m": DEFAULT_TILE_SIZE_M,
          "drives": [{"name": name, "path": str(drive_yaml), "role": "map"}],
          "stages": ["ingest", "odometry", "posegraph"], "params": params}
    path = root / "workflow.yaml"
    root.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(wf, sort_keys=False))
    plan = execute_workflow(path, root=root, scheduler="sync", quiet=True)["plan"]
    edges = committed(plan, "odometry", "edges", "odometry_edges").read("edges")
    poses = committed(plan, "posegraph", "poses", "poses_optimized").read("poses")
    return edges, poses


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sim", type=Path, required=True)
    ap.add_argument("--drive", default="drive_0")
    ap.add_argument("--every", type=int, default=12)
    ap.add_argument("--root", type=Path, required=True)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    ap.add_argument("--seed", type=int, default=0, help="of the prior's error")
    ap.add_argument("--set", action="append", default=[], metavar="STAGE.KEY=VALUE")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    from fixtures.keyframes import keyframe_drive, truth_at_keyframes
    from stages.common import trajectory_metrics as M
    from stages.common.records import Trajectory

    params: dict = {}
    for kv in args.set:
        key, _, value = kv.partition("=")
        stage, _, name = key.partition(".")
        params.setdefault(stage, {})[name] = json.loads(value) if value[:1] in "[{0123456789-tf" else value
    T_true = truth_at_keyframes(args.sim, args.drive, args.every)
    results = {}
    for variant in args.variants:
        name = "kf_" + variant.replace("+", "_")
        work = args.root / name
        shutil.rmtree(work, ignore_errors=True)
        drive_yaml = keyframe_drive(args.sim, args.drive, args.every, work / "drive" / name,
                                    gnss=variant.startswith("gnss"),
                                    prior={"gnss+prior": "enu", "prior": "enu", "local": "local"}.get(variant),
                                    seed=args.seed)
        t0 = time.perf_counter()
        if variant == "none":
            edges, poses = _odometry_in_memory(drive_yaml, name, params.get("odometry", {})), None
        else:
            edges, poses = _build(drive_yaml, name, work / "root", params)
        row = {"wall_s": round(time.perf_counter() - t0, 1), **_edges_vs_truth(edges, T_true)}
        if poses is not None:
            traj = Trajectory.from_table(poses, name)
            s = M.summarize(traj.T, T_true[traj.scan_id], traj.stamp_s)
            row.update({k: s[k] for k in ("abs_horizontal_rms_m", "abs_horizontal_max_m", "heading_rms_deg")})
        results[variant] = row
        print(variant, json.dumps(row), flush=True)
    keys = list(dict.fromkeys(k for r in results.values() for k in r))
    print("| variant | " + " | ".join(keys) + " |")
    print("|---|" + "---|" * len(keys))
    for v, r in results.items():
        cells = [f"{r[k]:.3f}" if isinstance(r.get(k), float) else str(r.get(k, "")) for k in keys]
        print(f"| {v} | " + " | ".join(cells) + " |")
    if args.json:
        args.json.write_text(json.dumps({"sim": str(args.sim), "every": args.every, "results": results}, indent=1))


if __name__ == "__main__":
    main()
