"""Vertex support of per-scan corners against simulator truth: how far the facing end points of a corner's two
lines stop from the corner (the lines' intersection), for corners on building vertices and for false ones.

A sharp building corner is seen up to its vertex on at least one wall: the last return of that wall's line lies
within about one point spacing of the intersection. A line that ends short of the intersection on both sides
means the vertex was extrapolated into empty space: a chord of a rounded corner meeting a straight wall, the
gap where part of the arc was left out, is the case (docs/cornermap.md "What counts as a corner").

    python -m bench.bench_corner_vertex --root ROOT [--drive drive_0] [--every 10] [--set NAME=VALUE ...]

ROOT is a workflow root of a simulated city (``bench_seeds`` or ``cornermap run``): scans_raw, odometry_raw and
drive_info are read from its datasets, truth from its raw_drives artifacts. Every ``--every``-th scan is traced
with the corners stage's params (``--set`` overrides them) and deskewed as the stage does; each corner it keeps is
placed with the drive's true poses and labelled: ``building`` (within 0.3 m of a truth building corner or a
chamfer vertex), ``rounded`` (within the arc's reach of a rounded corner), ``furniture`` (within 0.5 m of a
street-furniture corner), ``other``. Prints, per label, the count and the quantiles of the vertex gap (the
smaller of the two facing-end gaps in point spacings of its line, the best layer), and how many corners of each
label a limit would drop. ``--set checks.max_vertex_gap_spacings=0`` shows the corners the rule removes.
"""
from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np
import pyarrow.dataset as ds

from bench.bench_cornermap import chamfer_vertices, truth_rows
from bench.roots import dataset, simulator_dir
from stages.common.records import Extrinsics, Trajectory, decode_scans_raw
from stages.common.wheel_odometry import track_from_table
from stages.corners.compute import SCAN_COLUMNS
from stages.corners.core import select_scan_layers, trace_corners, vertex_gaps_spacings
from stages.corners.params import CornerParams

LABELS = ("building", "rounded", "furniture", "other")


def truth_sets(sim: Path):
    """From DIR/truth (a simulator output): building corners (the walls' intersections of sharp and chamfered
    corners plus both vertices of each chamfer, docs/cornermap.md), the rounded corners' intersections with their
    radii, and the street-furniture corners."""
    rows = truth_rows(sim)
    en = np.array([[float(r["east_m"]), float(r["north_m"])] for r in rows]).reshape(-1, 2)
    shape = np.array([r.get("corner_shape", "sharp") for r in rows])
    size = np.array([float(r.get("shape_size_m") or 0.0) for r in rows])
    building = np.vstack([en[shape != "rounded"], chamfer_vertices(sim)[0]])
    furn_path = sim / "truth" / "furniture_corners.csv"
    furniture = np.zeros((0, 2))
    if furn_path.exists():
        with open(furn_path, newline="") as fh:
            furniture = np.array([[float(r["east_m"]), float(r["north_m"])] for r in csv.DictReader(fh)]).reshape(-1, 2)
    return building, en[shape == "rounded"], size[shape == "rounded"], furniture


def label_corners(en: np.ndarray, building, rounded, radius, furniture) -> np.ndarray:
    def near(points, tol):
        if not len(points) or not len(en):
            return np.zeros(len(en), bool)
        return np.linalg.norm(en[:, None] - points[None], axis=2).min(axis=1) <= tol

    out = np.full(len(en), "other", dtype=object)
    arc = np.zeros(len(en), bool)
    if len(rounded):  # an arc's chords lie within r (sqrt 2 - 1) + r of the walls' intersection
        arc = (np.linalg.norm(en[:, None] - rounded[None], axis=2) <= 2.5 * radius[None]).any(axis=1)
    out[near(furniture, 0.5)] = "furniture"
    out[arc] = "rounded"
    out[near(building, 0.3)] = "building"
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", type=Path, required=True)
    ap.add_argument("--drive", default="drive_0")
    ap.add_argument("--every", type=int, default=10, help="trace every N-th scan")
    ap.add_argument("--set", nargs="*", default=[], metavar="NAME=VALUE",
                    help="corners params overrides, e.g. checks.max_vertex_gap_spacings=2")
    args = ap.parse_args(argv)
    from bench.params_args import nested

    params = CornerParams.model_validate(nested({k: float(v) for k, v in (s.split("=", 1) for s in args.set)}))
    truth_dir = simulator_dir(args.root)
    building, rounded, radius, furniture = truth_sets(truth_dir)
    truth = Trajectory.from_tum(truth_dir / "truth" / f"{args.drive}_poses_tum.txt")
    info = dataset(args.root, "drive_info").to_table(columns=["drive", "T_vehicle_lidar"])
    T_vl = Extrinsics.from_table(info).of(args.drive)
    odo = dataset(args.root, "odometry_raw").to_table(filter=ds.field("drive") == args.drive,
                                                     columns=["stamp_ns", "speed_mps", "yaw_rate_radps"])
    track = track_from_table(odo)
    scans = dataset(args.root, "scans_raw")
    ids = np.unique(scans.to_table(columns=["scan_id"], filter=ds.field("drive") == args.drive)["scan_id"]
                    .to_numpy())[:: args.every]
    table = scans.to_table(columns=SCAN_COLUMNS, filter=(ds.field("drive") == args.drive)
                           & ds.field("scan_id").isin(ids))
    rows = decode_scans_raw(table)
    _, bounds = rows.scan_rows()
    xyz, ring, stamp = rows.xyz_lidar_m, rows.ring, rows.stamp_ns
    t_s = rows.time_offset_s.astype(np.float64)
    layers = select_scan_layers(xyz, ring, params)
    rows = {k: [] for k in ("label", "gap_sp", "range_m", "interior_deg")}
    for a, b in zip(bounds[:-1], bounds[1:]):
        pts = track.deskew_scan(xyz[a:b], t_s[a:b], int(stamp[a]), T_vl)
        pts = xyz[a:b] if pts is None else pts
        trace = trace_corners(pts, ring[a:b], params, layers=layers)
        if not len(trace.corners):
            continue
        k = int(np.argmin(np.abs(truth.stamp_ns - stamp[a])))
        T = truth.T[k] @ T_vl
        c = trace.corners
        en = (T[:2, :2] @ np.vstack([c.x_m, c.y_m]) + T[:2, 3:4]).T
        gap_sp = vertex_gaps_spacings(trace.candidate_corner, trace.candidates.vertex_gap_spacings,
                                      len(trace.corners))
        rows["label"] += list(label_corners(en, building, rounded, radius, furniture))
        rows["gap_sp"] += list(gap_sp)
        rows["range_m"] += list(c.range_m)
        rows["interior_deg"] += list(np.degrees(c.interior_angle_rad))
    r = {k: np.asarray(v) for k, v in rows.items()}
    print(f"{args.root} {args.drive}: {len(ids)} scans traced, {len(r['label'])} corners")
    print("| label | corners | vertex gap in spacings p50 / p95 / p99 / max |")
    print("|---|---|---|")
    for lab in LABELS:
        m = r["label"] == lab
        if not m.any():
            continue
        qs = np.quantile(r["gap_sp"][m], [0.5, 0.95, 0.99, 1.0])
        print(f"| {lab} | {int(m.sum())} | {' / '.join(f'{v:.1f}' for v in qs)} |")
    print("corners over a vertex-gap limit (in spacings), per label: " + ", ".join(
        f"{lim:g}: " + " ".join(f"{lab} {int(((r['label'] == lab) & (r['gap_sp'] > lim)).sum())}" for lab in LABELS)
        for lim in (1.0, 1.5, 2.0, 2.5, 3.0)))
    for lab in ("rounded", "furniture", "other"):
        for i in np.flatnonzero(r["label"] == lab)[:20]:
            print(f"  {lab}: vertex gap {r['gap_sp'][i]:.1f} spacings, range {r['range_m'][i]:.1f} m, "
                  f"interior {r['interior_deg'][i]:.0f} deg")


if __name__ == "__main__":
    main()
