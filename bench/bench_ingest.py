"""Ingest throughput (scans/s on one core, PCD binary, ~70k points) and peak memory against drive length.

    .venv/bin/python -m bench.bench_ingest [--scans 200] [--long 2000]
    .venv/bin/python -m bench.bench_ingest --lzf      # the LZF (binary_compressed) PCD decoder alone

One synthetic 70,400-point HDL-32E PCD (x y z intensity ring time) is hard-linked N times into a drive
folder (no disk blow-up), then the ingest compute runs and every streamed scans_raw piece is written to
Parquet (zstd) as the store would. Peak RSS is measured in a fresh subprocess per drive length.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _make_drive(root: Path, n_scans: int) -> Path:
    import csv

    import numpy as np
    import yaml

    from fixtures.ingest import make_scan
    from stages.ingest.pcd import write_pcd

    scans = root / "drive_0" / "scans"
    scans.mkdir(parents=True)
    template = root / "template.pcd"
    write_pcd(template, make_scan(np.random.default_rng(0), n_per_ring=2200), "binary")
    for i in range(n_scans):
        os.link(template, scans / f"{i:06d}.pcd")
    with open(scans / "stamps.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["scan_id", "gps_seconds"])
        w.writerows([i, 1000.0 + 0.1 * i] for i in range(n_scans))
    spec = {"name": "drive_0", "sensor": "hdl32e", "scans": {"folder": "scans", "format": "pcd"},
            "scan_rate_hz": 10.0, "T_vehicle_lidar": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
            "scan_times": {"source": "stamps_csv"}}
    (root / "drive_0" / "drive.yaml").write_text(yaml.safe_dump(spec))
    return root / "drive_0" / "drive.yaml"


def run_once(n_scans: int) -> dict:
    import pyarrow.parquet as pq

    from pipeline.declare import PartitionKey
    from pipeline.testing import make_context
    from stages.ingest.compute import compute
    from stages.ingest.params import IngestParams

    with tempfile.TemporaryDirectory(prefix="bench-ingest-") as tmp:
        drive_file = _make_drive(Path(tmp), n_scans)
        ctx = make_context("ingest", IngestParams(), partition=PartitionKey(drive="drive_0"),
                           drives={"drive_0": drive_file}, workdir=Path(tmp) / "work")
        t0, c0 = time.perf_counter(), time.process_time()
        out = compute(ctx)
        points = 0
        for k, piece in enumerate(out["scans"]):
            pq.write_table(piece, Path(tmp) / f"scans-{k:05d}.parquet", compression="zstd")
            points += piece.num_rows
        index = list(out["scan_index"])[0]
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {"n_scans": n_scans, "points": points, "wall_s": round(wall, 2), "cpu_s": round(cpu, 2),
            "scans_per_s_wall": round(n_scans / wall, 1), "scans_per_cpu_s": round(n_scans / cpu, 1),
            "ok": int(sum(s == "ok" for s in index["status"].to_pylist())),
            "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)}


def bench_lzf(repeat: int = 3) -> None:
    """Decode time of a binary_compressed (LZF) PCD of a real KITTI HDL-64E scan from ../shared/data (about 120 k
    points), written by open3d, read by the ingest stage's reader (pure-Python LZF)."""
    import numpy as np
    import open3d as o3d

    from stages.ingest.pcd import read_pcd

    kitti = sorted((Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti_raw_0048_city").glob("*.pcd"))
    if not kitti:
        raise SystemExit("bench_ingest --lzf: no KITTI scan in ../shared/data/kitti_raw_0048_city")
    xyz = np.column_stack([read_pcd(kitti[0]).columns[c] for c in "xyz"]).astype(np.float32)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "scan.pcd"
        pc = o3d.t.geometry.PointCloud()
        pc.point.positions = o3d.core.Tensor(xyz)
        if not o3d.t.io.write_point_cloud(str(path), pc, write_ascii=False, compressed=True):
            raise SystemExit(f"bench_ingest --lzf: open3d could not write {path}")
        times = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            cloud = read_pcd(path)
            times.append(time.perf_counter() - t0)
        assert cloud.header.encoding == "binary_compressed" and cloud.header.points == len(xyz)
        print(f"LZF PCD decode ({kitti[0].name}: {len(xyz)} points, {path.stat().st_size / 1e6:.2f} MB compressed, "
              f"{xyz.nbytes / 1e6:.2f} MB raw): best {min(times):.3f} s, median {float(np.median(times)):.3f} s "
              f"of {repeat}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scans", type=int, default=200, help="scans for the throughput run")
    parser.add_argument("--long", type=int, default=2000, help="scans for the long-drive memory run")
    parser.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--lzf", action="store_true", help="only time the LZF (binary_compressed) PCD decoder")
    args = parser.parse_args()
    if args.lzf:
        bench_lzf()
        return
    if args.child is not None:
        print(json.dumps(run_once(args.child)))
        return
    print(f"machine: {os.cpu_count()} cores (shared), python {sys.version.split()[0]}; one process, one core")
    for n in (args.scans // 4, args.scans, args.long):
        env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
        res = subprocess.run([sys.executable, "-m", "bench.bench_ingest", "--child", str(n)], env=env,
                             capture_output=True, text=True, check=True)
        print(res.stdout.strip())


if __name__ == "__main__":
    main()
