"""Corner map benchmark: precision / recall / RMS against simulator truth, size of the exports, run time.

Examples (2-core machine):
  python -m bench.bench_cornermap                                  # built-in grid city, synthetic observations
  python -m bench.bench_cornermap --sim runs/sim/gangnam           # truth buildings of a simulator run
  python -m bench.bench_cornermap --sim DIR --corners C.parquet --poses P.parquet --drive-info I.parquet \\
      [--truth-poses DIR/truth/drive_00.tum]                       # real extraction output of the pipeline
  add --figure docs/figures/cornermap_gangnam.png for the map with covariance ellipses over the buildings.
  add --truth-filter COLUMN=VALUE (e.g. kind=building) to score against the rows of truth/corners.csv with that
  value only: map corners on street furniture then count as false positives (precision against buildings).
  The two real vertices of each chamfered corner (truth lists only the walls' intersection) count as building
  corners for precision (docs/cornermap.md: a facet of 2 m or more gives two obtuse corners), not for recall.
Every run prints "duplicates (1 m, matching walls)": pairs of map corners within 1 m whose walls agree within
12 deg (the issue's definition), besides the map corners matched to one true corner twice.
Over 300 lines on purpose: one command for the three input modes (built-in city, simulator truth, the
pipeline's own output) with the readers of their truth files; the scoring itself is stages/cornermap/metrics.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.dataset as ds
import pyarrow.parquet as pq

from pipeline.testing import make_context
from stages.cornermap.decl import STAGE
from stages.cornermap.export import format_im2016_text
from stages.cornermap.metrics import local_frame_offset, score_corner_map
from stages.cornermap.params import CornerMapParams
from stages.cornermap.transform import covariance_from_components, transform_to_enu

log = logging.getLogger("bench.cornermap")


def read_table(path: str) -> pa.Table:
    return ds.dataset(path, format="parquet", partitioning="hive").to_table()


def truth_rows(sim: Path) -> list[dict[str, str]]:
    """The rows of DIR/truth/corners.csv (``#`` comment lines skipped), as text."""
    import csv

    with open(sim / "truth" / "corners.csv", newline="") as fh:
        return list(csv.DictReader(line for line in fh if not line.startswith("#")))


def truth_filter_mask(sim: Path, truth_filter: str) -> np.ndarray:
    """(K,) rows of DIR/truth/corners.csv whose COLUMN equals VALUE (as text), from 'COLUMN=VALUE'."""
    path = sim / "truth" / "corners.csv"
    rows = truth_rows(sim)
    column, _, value = truth_filter.partition("=")
    if rows and column not in rows[0]:
        raise SystemExit(f"{path}: no column {column!r} for --truth-filter (columns: {sorted(rows[0])})")
    return np.array([str(r[column]).strip() == value for r in rows], bool)


def load_truth_corners(sim: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """DIR/truth/corners.csv -> (K,2) east/north, (K,2) wall directions rad, visible-scan count of drive 0."""
    rows = truth_rows(sim)
    cols = {k: np.array([float(r[k]) for r in rows]) for k in rows[0] if rows and _is_number(rows[0][k])}
    en = np.column_stack([cols["east_m"], cols["north_m"]])
    if "theta1_deg" in cols:
        theta = np.radians(np.column_stack([cols["theta1_deg"], cols["theta2_deg"]]))
    else:
        theta = np.column_stack([cols["theta1_rad"], cols["theta2_rad"]])
    seen_cols = sorted(k for k in cols if "visible" in k or k.startswith("seen"))
    return en, theta, (cols[seen_cols[0]] if seen_cols else None)


def chamfer_vertices(sim: Path) -> tuple[np.ndarray, np.ndarray]:
    """The two real vertices of every chamfered corner of DIR/truth/corners.csv (``corner_shape`` chamfered, cut
    ``shape_size_m`` back along each wall from the listed walls' intersection), with their wall directions (the
    continuing wall and the chamfer facet): building corners as docs/cornermap.md defines them (a facet of 2 m
    or more gives two obtuse corners), which the truth file lists only by the intersection. (M,2), (M,2)."""
    rows = [r for r in truth_rows(sim) if r.get("corner_shape") == "chamfered"]
    en, theta = [], []
    for r in rows:
        p = np.array([float(r["east_m"]), float(r["north_m"])])
        t = np.radians([float(r["theta1_deg"]), float(r["theta2_deg"])])
        u = np.column_stack([np.cos(t), np.sin(t)])
        a = p + float(r["shape_size_m"]) * u  # the cut's two ends, one on each wall
        for i, j in ((0, 1), (1, 0)):
            facet = a[j] - a[i]
            en.append(a[i])
            theta.append([t[i], np.arctan2(facet[1], facet[0])])
    return np.reshape(en, (-1, 2)), np.reshape(theta, (-1, 2))


def _is_number(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def synthetic_inputs(args) -> dict:
    from fixtures.cornermap import (
        drive_info_table,
        footprint_corners,
        grid_city,
        observe_drive,
        serpentine_route,
    )

    if args.sim:
        city = json.loads((Path(args.sim) / "truth" / "city.json").read_text())
        buildings = [np.asarray(b["footprint_en"], float) for b in city["buildings"]]
        nodes = np.asarray(city["intersections_en"], float)
    else:
        buildings, nodes = grid_city(args.cols, args.rows, seed=args.seed)
    truth_en, truth_theta = footprint_corners(buildings)
    route = serpentine_route(nodes, step_m=0.95)  # 9.5 m/s at 10 Hz
    drives = [f"drive_{i:02d}" for i in range(args.drives)]
    parts = [observe_drive(d, route, truth_en, truth_theta, seed=args.seed + i) for i, d in enumerate(drives)]
    corners = pa.concat_tables([p[0] for p in parts])
    poses = pa.concat_tables([p[1] for p in parts])
    d0 = pc.equal(corners["drive"], drives[0])
    idx0 = corners.filter(d0)
    seen = np.zeros(len(truth_en))
    real = idx0["corner_idx"].to_numpy() >= 0
    pairs = np.unique(np.column_stack([idx0["corner_idx"].to_numpy()[real], idx0["scan_id"].to_numpy()[real]]), axis=0)
    np.add.at(seen, pairs[:, 0], 1)
    return {"corners": corners, "poses": poses, "drive_info": drive_info_table(drives), "truth_en": truth_en,
            "truth_theta": truth_theta, "seen": seen, "truth_pose_en": route[:, :2], "buildings": buildings,
            "drive0": drives[0]}


def pipeline_inputs(args) -> dict:
    corners, poses, info = read_table(args.corners), read_table(args.poses), read_table(args.drive_info)
    truth_en, truth_theta, seen = load_truth_corners(Path(args.sim))
    drive0 = sorted(set(poses["drive"].to_pylist()))[0]
    truth_pose_en = None
    tum = args.truth_poses or Path(args.sim) / "truth" / f"{drive0}_poses_tum.txt"
    if Path(tum).is_file():
        from stages.common.records import Trajectory

        truth = Trajectory.from_tum(tum)
        stamps_s, T = truth.stamp_s, truth.T
        p0 = Trajectory.from_table(poses, drive0)
        if p0.scan_id.max() < len(T):  # one TUM row per scan (the simulator's truth): match by scan index
            truth_pose_en = T[p0.scan_id, :2, 3]
        else:
            t = p0.stamp_s
            truth_pose_en = np.column_stack([np.interp(t, stamps_s, T[:, 0, 3]), np.interp(t, stamps_s, T[:, 1, 3])])
    else:
        log.warning("no truth poses for %s at %s: the map-frame score equals the absolute one", drive0, tum)
    if seen is None:
        seen = _seen_from_observations(corners, poses, info, drive0, truth_en)
    city = json.loads((Path(args.sim) / "truth" / "city.json").read_text())
    views = None
    if (Path(args.sim) / "simulation.json").is_file():
        from stages.simulate.corner_views import sensed_corner_truth

        sensed = sensed_corner_truth(Path(args.sim), drive0)
        views, truth_theta = sensed.views.astype(float), sensed.theta_rad
    if args.truth_filter:  # e.g. building corners only: street furniture in the map becomes false positives
        keep = truth_filter_mask(Path(args.sim), args.truth_filter)
        truth_en, truth_theta, seen = truth_en[keep], truth_theta[keep], seen[keep]
        views = views[keep] if views is not None else None
    ch_en, ch_theta = chamfer_vertices(Path(args.sim))  # count for precision; not eligible for recall (no views)
    if len(ch_en):
        log.info("truth: %d chamfer vertices added as building corners", len(ch_en))
        truth_en, truth_theta = np.vstack([truth_en, ch_en]), np.vstack([truth_theta, ch_theta])
        seen = np.concatenate([seen, np.zeros(len(ch_en))])
        views = np.concatenate([views, np.zeros(len(ch_en))]) if views is not None else None
    return {"corners": corners, "poses": poses, "drive_info": info, "truth_en": truth_en, "truth_theta": truth_theta,
            "seen": seen, "views": views, "truth_pose_en": truth_pose_en, "drive0": drive0,
            "buildings": [np.asarray(b["footprint_en"], float) for b in city["buildings"]]}


def _seen_from_observations(corners, poses, info, drive0, truth_en) -> np.ndarray:
    """Scans of drive 0 with an observation within 0.5 m of each true corner (when truth has no count)."""
    from scipy.spatial import cKDTree

    from stages.common.records import Extrinsics, pose_matrices

    c = corners.filter(pc.equal(corners["drive"], drive0))
    p = poses.filter(pc.equal(poses["drive"], drive0))
    row = {s: i for i, s in enumerate(p["scan_id"].to_pylist())}
    keep = np.array([s in row for s in c["scan_id"].to_pylist()], bool)
    c = c.filter(pa.array(keep))
    rows = np.array([row[s] for s in c["scan_id"].to_pylist()], np.int64)
    T = pose_matrices(p, rows)
    Tvl = Extrinsics.from_table(info).of(drive0)
    n = len(rows)
    obs = transform_to_enu(np.column_stack([c["x_m"].to_numpy(), c["y_m"].to_numpy()]),
                           np.column_stack([c["theta1_rad"].to_numpy(), c["theta2_rad"].to_numpy()]),
                           covariance_from_components(np.zeros(n), np.zeros(n), np.zeros(n)), T, Tvl,
                           np.zeros((n, 3, 3)))
    dist, k = cKDTree(truth_en).query(obs.en_m)
    ok = dist < 0.5
    pairs = np.unique(np.column_stack([k[ok], c["scan_id"].to_numpy()[ok]]), axis=0)
    return np.bincount(pairs[:, 0], minlength=len(truth_en)).astype(float)


def drive_km(poses: pa.Table, drive: str) -> float:
    p = poses.filter(pc.equal(poses["drive"], drive)).sort_by("scan_id")
    xy = np.column_stack([p["x_m"].to_numpy(), p["y_m"].to_numpy()])
    return float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum() / 1000.0)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sim", help="simulator output folder (truth/corners.csv, truth/city.json)")
    ap.add_argument("--corners", help="corners_per_scan Parquet (file or hive folder); else synthetic observations")
    ap.add_argument("--poses", help="poses_optimized Parquet (with --corners)")
    ap.add_argument("--drive-info", help="drive_info Parquet (with --corners)")
    ap.add_argument("--truth-poses", help="TUM truth trajectory of drive 0 (frame offset; with --corners)")
    ap.add_argument("--cols", type=int, default=7)
    ap.add_argument("--rows", type=int, default=6)
    ap.add_argument("--drives", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--figure", help="write the map figure (PNG) here")
    ap.add_argument("--truth-filter", help="COLUMN=VALUE: score against these rows of truth/corners.csv only "
                                           "(with --corners), e.g. kind=building")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    if args.corners and not (args.poses and args.drive_info and args.sim):
        ap.error("--corners needs --poses, --drive-info and --sim")

    t0 = time.perf_counter()
    data = pipeline_inputs(args) if args.corners else synthetic_inputs(args)
    t_inputs = time.perf_counter() - t0
    with tempfile.TemporaryDirectory(prefix="bench-cornermap-") as workdir:
        # the map is built from the map drive only (a pipeline's tables also hold the evaluation drive)
        ctx = make_context("cornermap", CornerMapParams(), {k: data[k] for k in ("corners", "poses", "drive_info")},
                           workdir=Path(workdir), settings={"map_drives": [data["drive0"]]} if args.corners else None)
        t0 = time.perf_counter()
        result = STAGE.load_compute()(ctx)
        t_compute = time.perf_counter() - t0
    cmap = result["corner_map"]
    map_en = np.column_stack([cmap["east_m"].to_numpy(), cmap["north_m"].to_numpy()])
    map_theta = np.column_stack([cmap["theta1_rad"].to_numpy(), cmap["theta2_rad"].to_numpy()])

    # eligible: seen as a corner (two opaque walls in view) by >= 20 scans of drive 0 when the simulator's
    # city can be rebuilt; else line of sight to the corner point (which a scan along one wall also has)
    views = data.get("views")
    eligible = (views if views is not None else data["seen"]) >= 20
    absolute = score_corner_map(map_en, map_theta, data["truth_en"], data["truth_theta"], eligible)
    p0 = data["poses"].filter(pc.equal(data["poses"]["drive"], data["drive0"])).sort_by("scan_id")
    if data["truth_pose_en"] is not None:
        opt_en = np.column_stack([p0["x_m"].to_numpy(), p0["y_m"].to_numpy()])
        offset = local_frame_offset(data["truth_en"], data["truth_pose_en"], opt_en, 50.0)
    else:
        offset = np.zeros_like(data["truth_en"])
    in_frame = score_corner_map(map_en, map_theta, data["truth_en"] + offset, data["truth_theta"], eligible)
    in_frame_los = score_corner_map(map_en, map_theta, data["truth_en"] + offset, data["truth_theta"],
                                    data["seen"] >= 20)

    km = drive_km(data["poses"], data["drive0"])
    text = format_im2016_text(cmap)
    with tempfile.TemporaryDirectory() as tmp:
        pq.write_table(cmap, os.path.join(tmp, "m.parquet"), compression="zstd")
        parquet_bytes = os.path.getsize(os.path.join(tmp, "m.parquet"))
    extra = result["_extra"]["cornermap"]
    rej = result["rejected"]
    from collections import Counter

    reasons = Counter(r.split(":")[0] for text in rej["reason"].to_pylist() for r in text.split("; "))
    print(f"machine: {os.cpu_count()} cores; mode: {'pipeline' if args.corners else 'synthetic'}"
          f"{' sim=' + args.sim if args.sim else ' grid city %dx%d' % (args.cols, args.rows)}; drives: {args.drives}")
    print(
        f"observations: {extra['n_observations']}  clusters: {extra['n_clusters']}  kept: {extra['n_kept']}  "
        f"rejected: {extra['n_rejected']} {dict(reasons)}"
    )
    print(
        f"inputs {t_inputs:.1f} s, compute {t_compute:.2f} s ({extra['n_observations'] / t_compute / 1e3:.0f} k obs/s)"
    )
    rule = "seen as a corner (two opaque walls in view)" if views is not None else "line of sight"
    print(f"eligible true corners ({rule} in >= 20 scans of {data['drive0']}): {in_frame['n_eligible']} of "
          f"{len(data['truth_en'])}")
    if views is not None:
        print(f"  (line of sight to the corner point in >= 20 scans: {in_frame_los['n_eligible']}, recall against "
              f"those {in_frame_los['recall']:.4f} in the map frame)")
    print("| frame | precision (<= 0.3 m) | recall | position RMS m | angle RMS deg | duplicates |")
    print("|---|---|---|---|---|---|")
    for name, s in (("map (truth shifted by local pose offset)", in_frame), ("absolute", absolute)):
        print(f"| {name} | {s['precision']:.4f} | {s['recall']:.4f} | {s['rms_pos_m']:.4f} | "
              f"{s['rms_angle_deg']:.3f} | {s['n_duplicates']} |")
    from stages.cornermap.merge import count_duplicates

    print(f"duplicates (1 m, matching walls): {count_duplicates(map_en, map_theta, 1.0)}; merged groups "
          f"{extra.get('n_merged_groups', 0)}, duplicates rejected {extra.get('n_duplicates_rejected', 0)}")
    print(f"drive 0: {km:.2f} km; text export {len(text.encode()) / 1024:.1f} KB = "
          f"{len(text.encode()) / 1024 / km:.1f} KB/km; Parquet (zstd) {parquet_bytes / 1024:.1f} KB = "
          f"{parquet_bytes / 1024 / km:.1f} KB/km")
    if args.figure:
        from stages.cornermap.figure import plot_corner_map

        plot_corner_map(args.figure, data["buildings"], cmap, p0, data["truth_en"])
        print(f"figure: {args.figure}")


if __name__ == "__main__":
    main()
