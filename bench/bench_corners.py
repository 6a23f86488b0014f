"""Corner extraction benchmarks: throughput (synthetic + real) and accuracy against simulator truth.

    .venv/bin/python -m bench.bench_corners                 # throughput: synthetic 8 x 2250 rings, nuScenes
    .venv/bin/python -m bench.bench_corners --sim DIR       # + accuracy on DIR (cornermap simulate output)
    .venv/bin/python -m bench.bench_corners --sim DIR --drive drive_1 --max-scans 500
    .venv/bin/python -m bench.bench_corners --no-throughput --root ROOT   # the stage's own output in a root

Accuracy: each extracted corner is mapped into ENU with the true vehicle pose (DIR/truth/drive_K_poses_tum.txt,
T_vehicle_lidar from drive.yaml) interpolated at the corner's own time (scan stamp + the mean time of its points;
the scan is not deskewed), and compared with the nearest building corner (DIR/truth/corners.csv, plus both
vertices of each chamfered corner: docs/cornermap.md). Corners farther than 0.5 m from every one count as false
positives, broken down by what they stand near (a rounded corner's arc, street furniture, other). The same
numbers with the scan-start pose show what motion distortion costs.
"""
from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np

from fixtures.corners import HDL32E_ELEVATION_DEG, cast_scan, city_block_scene
from pipeline.errors import FormatError
from stages.corners.core import extract_corners, select_scan_layers
from stages.corners.params import CornerParams

_PCD_TYPES = {("F", 4): "<f4", ("F", 8): "<f8", ("U", 1): "u1", ("U", 2): "<u2", ("U", 4): "<u4",
              ("I", 1): "i1", ("I", 2): "<i2", ("I", 4): "<i4"}


def read_pcd_binary(path: Path) -> np.ndarray:
    """A binary PCD as a structured array (fields from the header)."""
    raw = Path(path).read_bytes()
    end = raw.find(b"DATA binary\n")
    if end < 0:
        raise FormatError(f"{path}: not a binary PCD (no 'DATA binary' line)")
    head = dict(ln.split(" ", 1) for ln in raw[:end].decode("ascii").splitlines() if ln and not ln.startswith("#"))
    names, sizes, types = head["FIELDS"].split(), head["SIZE"].split(), head["TYPE"].split()
    dtype = np.dtype([(n, _PCD_TYPES[(t, int(s))]) for n, s, t in zip(names, sizes, types)])
    n = int(head["POINTS"])
    return np.frombuffer(raw, dtype, count=n, offset=end + len(b"DATA binary\n"))


def machine() -> str:
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores shared (load {load:.1f}), "
            f"1 thread, CPU time")


def time_scans(scans: list[tuple[np.ndarray, np.ndarray]], params: CornerParams, layers, repeat: int) -> float:
    """CPU seconds per scan of this process (the machine is shared: wall time would count other jobs)."""
    extract_corners(*scans[0], params, layers=layers)  # warm up
    t0 = time.process_time()
    for _ in range(repeat):
        for pts, ring in scans:
            extract_corners(pts, ring, params, layers=layers)
    return (time.process_time() - t0) / (repeat * len(scans))


def bench_throughput(data_dir: Path, repeat: int) -> None:
    params = CornerParams()
    print(f"# corner extraction throughput ({machine()})")
    upper = HDL32E_ELEVATION_DEG[-8:]
    scans8 = [cast_scan(city_block_scene(seed), (0.0, 0.0, 0.05 * seed), elevation_deg=upper, seed=seed)
              for seed in range(5)]
    n_pts = np.mean([len(s[0]) for s in scans8])
    dt = time_scans(scans8, params, select_scan_layers(*scans8[0], params), repeat)
    print(f"synthetic city, 8 layers x 2250 azimuths ({n_pts:.0f} returns/scan): {dt * 1e3:.2f} ms/scan "
          f"= {1 / dt:.0f} scans/s per core (layers known per chunk, as in compute())")
    dt = time_scans(scans8, params, None, repeat)
    print(f"  same, layers re-selected per scan: {dt * 1e3:.2f} ms/scan = {1 / dt:.0f} scans/s")
    scans32 = [cast_scan(city_block_scene(seed), (0.0, 0.0, 0.05 * seed), seed=seed) for seed in range(5)]
    layers = select_scan_layers(*scans32[0], params)
    dt = time_scans(scans32, params, layers, repeat)
    print(f"synthetic city, full 32-ring scans ({np.mean([len(s[0]) for s in scans32]):.0f} points, layers known "
          f"per chunk as in compute()): {dt * 1e3:.2f} ms/scan = {1 / dt:.0f} scans/s")
    dt = time_scans(scans32, params, None, repeat)
    print(f"  same, layers re-selected per scan: {dt * 1e3:.2f} ms/scan = {1 / dt:.0f} scans/s")
    for f in sorted((data_dir / "nuscenes_hdl32e_sweep").glob("*.pcd.bin")):
        rec = np.fromfile(f, np.float32).reshape(-1, 5)
        scan = (rec[:, :3], rec[:, 4].astype(np.int16))
        dt = time_scans([scan], params, None, repeat * 5)
        print(f"nuScenes HDL-32E sweep ({len(rec)} points): {dt * 1e3:.2f} ms/scan = {1 / dt:.0f} scans/s, "
              f"{len(extract_corners(*scan, params))} corners")


def _interp_poses(stamps_s: np.ndarray, T: np.ndarray, query_s: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation, Slerp

    q = np.clip(query_s, stamps_s[0], stamps_s[-1])
    out = np.tile(np.eye(4), (len(q), 1, 1))
    for k in range(3):
        out[:, k, 3] = np.interp(q, stamps_s, T[:, k, 3])
    out[:, :3, :3] = Slerp(stamps_s, Rotation.from_matrix(T[:, :3, :3]))(q).as_matrix()
    return out


def _report(label: str, en: np.ndarray, theta: np.ndarray, range_m: np.ndarray, truth, sets: dict, n_scans: int,
            detail: bool, cov_en: np.ndarray) -> None:
    from scipy.spatial import cKDTree

    from bench.bench_corner_vertex import label_corners

    true_en = np.vstack([np.column_stack([truth["east_m"], truth["north_m"]]), sets["chamfer_en"]])
    true_theta = np.vstack([np.radians(np.column_stack([truth["theta1_deg"], truth["theta2_deg"]])),
                            sets["chamfer_theta"]])
    d, j = cKDTree(true_en).query(en)
    ok = d <= 0.5
    kinds = label_corners(en[~ok], sets["building"], sets["rounded"], sets["radius"], sets["furniture"])
    print(f"{label}: {len(en)} corners ({len(en) / max(n_scans, 1):.2f}/scan); false positives (> 0.5 m from every "
          f"building corner or chamfer vertex) {100 * np.mean(~ok):.2f}% (near a rounded corner "
          f"{100 * np.sum(kinds == 'rounded') / max(len(en), 1):.2f}%, street furniture "
          f"{100 * np.sum(kinds == 'furniture') / max(len(en), 1):.2f}%, other "
          f"{100 * np.sum(kinds == 'other') / max(len(en), 1):.2f}%); "
          f"matched error p50 {np.percentile(d[ok], 50):.3f} m, "
          f"p95 {np.percentile(d[ok], 95):.3f} m, p99 {np.percentile(d[ok], 99):.3f} m "
          f"(targets p95 <= 0.15: {np.percentile(d[ok], 95) <= 0.15}, p99 <= 0.25: {np.percentile(d[ok], 99) <= 0.25})")
    if not detail:
        return
    wrap = lambda a: np.abs((a + np.pi) % (2 * np.pi) - np.pi)  # noqa: E731
    tt = true_theta[j[ok]]
    th = theta[ok]
    err = np.minimum(np.maximum(wrap(th[:, 0] - tt[:, 0]), wrap(th[:, 1] - tt[:, 1])),
                     np.maximum(wrap(th[:, 0] - tt[:, 1]), wrap(th[:, 1] - tt[:, 0])))
    print(f"  wall direction error (worse of the two): p50 {np.degrees(np.percentile(err, 50)):.2f} deg, "
          f"p95 {np.degrees(np.percentile(err, 95)):.2f} deg, p99 {np.degrees(np.percentile(err, 99)):.2f} deg")
    for lo, hi in ((0, 20), (20, 40), (40, 80)):
        sel = ok & (range_m >= lo) & (range_m < hi)
        if sel.any():
            print(f"  range {lo}-{hi} m: {sel.sum()} corners, p50 {np.percentile(d[sel], 50):.3f} m, "
                  f"p95 {np.percentile(d[sel], 95):.3f} m")
    true_en_ok = true_en[j[ok]]
    e = en[ok] - true_en_ok
    nees = np.einsum("ni,nij,nj->n", e, np.linalg.inv(cov_en[ok]), e)
    print(f"  covariance consistency: NEES median {np.median(nees):.2f} (chi2 2 dof: 1.39), "
          f"{100 * np.mean(nees <= 5.991):.1f}% inside the 95% ellipse")
    visible = [c for c in (truth.dtype.names or ()) if c.startswith("scans_visible_")]
    n_vis = int(np.sum(truth[visible[0]] > 0)) if visible else len(truth)
    print(f"  distinct true corners detected: {len(np.unique(j[ok]))} (true corners visible from this drive: {n_vis})")


def bench_accuracy(sim_dir: Path, drive: str, max_scans: int | None, params: CornerParams) -> None:
    import json

    import yaml

    from stages.common.deskew import deskew_with_wheel
    from stages.common.records import Trajectory

    truth, sets = _truth_inputs(sim_dir)
    poses = Trajectory.from_tum(sim_dir / "truth" / f"{drive}_poses_tum.txt")
    stamps_s, T_world_vehicle = poses.stamp_s, poses.T
    spec = yaml.safe_load((sim_dir / drive / "drive.yaml").read_text())
    T_vehicle_lidar = np.asarray(spec["T_vehicle_lidar"], float)
    odo_spec = spec["odometry"]
    odo = np.genfromtxt(sim_dir / drive / odo_spec["file"], delimiter=",", names=True)
    odo_t = odo[odo_spec["time_column"]].astype(np.float64)
    if odo_spec.get("week_column"):  # GPS week + seconds of week -> GPS seconds, the TUM time base
        odo_t = odo_t + 604800.0 * odo[odo_spec["week_column"]]
    if stamps_s[0] < 604800.0 <= odo_t[0]:  # an older simulator wrote the TUM in seconds of week
        odo_t = odo_t - 604800.0 * np.floor(odo_t[0] / 604800.0)
    distorted = json.loads((sim_dir / "simulation.json").read_text()).get("motion_distortion", True)
    files = sorted((sim_dir / drive / "scans").glob("*.pcd"))[:max_scans]
    out = {"start": [], "timed": [], "deskewed": []}  # per mode: rows e, n, theta1, theta2, range
    layers, cpu = None, 0.0
    for f in files:
        rec = read_pcd_binary(f)
        pts = np.column_stack([rec["x"], rec["y"], rec["z"]])
        ring = rec["ring"].astype(np.int16)
        t_s = rec["time"].astype(np.float64)
        scan_id = int(f.stem)
        if layers is None:
            layers = select_scan_layers(pts, ring, params)
        t0 = time.process_time()
        raw = extract_corners(pts, ring, params, layers=layers, time_offset_s=t_s)
        cpu += time.process_time() - t0
        near = np.flatnonzero(np.abs(odo_t - stamps_s[scan_id] - 0.05) < 0.1)
        if near.size < 2:  # sparse odometry: the two samples around the scan
            k = int(np.clip(np.searchsorted(odo_t, stamps_s[scan_id]), 1, odo_t.size - 1))
            near = np.array([k - 1, k])
        pts_start = deskew_with_wheel(pts, t_s, odo[odo_spec["speed"]][near], odo[odo_spec["yaw_rate"]][near],
                                      T_vehicle_lidar, odo_time_s=odo_t[near] - stamps_s[scan_id])
        fixed = extract_corners(pts_start, ring, params, layers=layers)
        T_start = T_world_vehicle[scan_id] @ T_vehicle_lidar
        for mode, c in (("start", raw), ("timed", raw), ("deskewed", fixed)):
            if not len(c):
                continue
            if mode == "timed":
                T = _interp_poses(stamps_s, T_world_vehicle, stamps_s[scan_id] + c.time_offset_s) @ T_vehicle_lidar
            else:
                T = np.broadcast_to(T_start, (len(c), 4, 4))
            p = np.column_stack([c.x_m, c.y_m, np.zeros(len(c)), np.ones(len(c))])
            en = np.einsum("nij,nj->ni", T, p)[:, :2]
            yaw = np.arctan2(T[:, 1, 0], T[:, 0, 0])
            R2 = T[:, :2, :2]
            cov_en = np.einsum("nij,njk,nlk->nil", R2, c.cov_m2, R2).reshape(-1, 4)
            out[mode].append(np.column_stack([en, c.theta1_rad + yaw, c.theta2_rad + yaw, c.range_m, cov_en]))
    print(f"# corner accuracy on {sim_dir} {drive}: {len(files)} scans, motion distortion {distorted} "
          f"({machine()}); extraction {len(files) / max(cpu, 1e-9):.0f} scans/s")
    primary = "deskewed" if distorted else "start"
    labels = {"start": "scan-start pose, no deskew", "timed": "pose at each corner's own time, no deskew",
              "deskewed": "deskewed with wheel speed + yaw rate, scan-start pose"}
    for mode in (primary, *[m for m in out if m != primary]):
        if not out[mode]:
            print(f"{labels[mode]}: no corners")
            continue
        r = np.concatenate(out[mode])
        _report(("PRIMARY " if mode == primary else "") + labels[mode], r[:, :2], r[:, 2:4], r[:, 4], truth, sets,
                len(files), mode == primary, r[:, 5:9].reshape(-1, 2, 2))


def _truth_inputs(sim_dir: Path) -> tuple[np.ndarray, dict]:
    from bench.bench_corner_vertex import truth_sets
    from bench.bench_cornermap import chamfer_vertices

    truth = np.genfromtxt(sim_dir / "truth" / "corners.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    building, rounded, radius, furniture = truth_sets(sim_dir)
    chamfer_en, chamfer_theta = chamfer_vertices(sim_dir)
    return truth, {"building": building, "rounded": rounded, "radius": radius, "furniture": furniture,
                   "chamfer_en": chamfer_en, "chamfer_theta": chamfer_theta}


def bench_stage_output(root: Path, drive: str) -> None:
    """Score the corners stage's own committed ``corners_per_scan`` of a workflow root (a simulated city) the way
    ``bench_accuracy`` scores its extraction: each corner placed with the true pose of its scan (the stage deskews
    to the scan start where odometry_raw exists; otherwise at the scan time plus the corner's time offset)."""
    import pyarrow.dataset as ds

    from bench.roots import dataset, simulator_dir
    from stages.common.records import Extrinsics, Trajectory

    sim_dir = simulator_dir(root)
    truth, sets = _truth_inputs(sim_dir)
    poses = Trajectory.from_tum(sim_dir / "truth" / f"{drive}_poses_tum.txt")
    T_vl = Extrinsics.from_table(dataset(root, "drive_info").to_table(columns=["drive", "T_vehicle_lidar"])).of(drive)
    c = dataset(root, "corners_per_scan").to_table(filter=ds.field("drive") == drive)
    t_s = c["stamp_ns"].to_numpy() * 1e-9 + c["time_offset_s"].to_numpy()
    T = _interp_poses(poses.stamp_s, poses.T, t_s) @ T_vl
    p = np.column_stack([c["x_m"].to_numpy(), c["y_m"].to_numpy(), np.zeros(c.num_rows), np.ones(c.num_rows)])
    en = np.einsum("nij,nj->ni", T, p)[:, :2]
    yaw = np.arctan2(T[:, 1, 0], T[:, 0, 0])
    theta = np.column_stack([c["theta1_rad"].to_numpy() + yaw, c["theta2_rad"].to_numpy() + yaw])
    cov = np.stack([np.stack([c["cov_xx_m2"].to_numpy(), c["cov_xy_m2"].to_numpy()], -1),
                    np.stack([c["cov_xy_m2"].to_numpy(), c["cov_yy_m2"].to_numpy()], -1)], -2)
    R2 = T[:, :2, :2]
    n_scans = len(np.unique(c["scan_id"].to_numpy()))
    print(f"# corners stage output of {root} {drive}: {c.num_rows} corners from {n_scans} scans with corners")
    _report("PRIMARY stage output (corners_per_scan)", en, theta, c["range_m"].to_numpy(), truth, sets, n_scans,
            True, np.einsum("nij,njk,nlk->nil", R2, cov, R2))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sim", type=Path, help="a cornermap simulate output directory (accuracy vs truth)")
    ap.add_argument("--root", type=Path, help="a workflow root of a simulated city: score the corners stage's own "
                    "committed corners_per_scan")
    ap.add_argument("--drive", default="drive_0")
    ap.add_argument("--max-scans", type=int, default=None)
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--no-throughput", action="store_true")
    ap.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                    help="override a CornerParams field for the accuracy run (repeatable), e.g. clusters.min_layers=4")
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    args = ap.parse_args(argv)
    if not args.no_throughput:
        bench_throughput(args.data, args.repeat)
    if args.sim:
        import json

        overrides = {k: json.loads(v) for k, v in (p.split("=", 1) for p in args.param)}
        from bench.params_args import nested

        bench_accuracy(args.sim, args.drive, args.max_scans, CornerParams.model_validate(nested(overrides)))
    if args.root:
        bench_stage_output(args.root, args.drive)


if __name__ == "__main__":
    main()
