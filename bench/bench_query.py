"""Query where the vehicle is, on a gangnam-size map: warm and cold times of ``MapReader.query_latlon`` (corners with
lat/lon, localizability cells; the marking window timed apart) at random places along the roads.

    .venv/bin/python -m bench.bench_query [--blocks 40] [--radius-m 150] [--repeats 300]

A synthetic grid city (``bench_tiles``' city: 60 m blocks, 4 corners per building; 40 x 40 blocks = 2.4 km x 2.4 km,
6,400 corners, 576 tiles of 100 m) published by the tiles stage with its localizability layer along a serpentine of
``--legs`` streets and marking rasters on the tiles those streets cross. Warm: the tiles the query needs are in the
reader's caches (a vehicle moving through the map asks about the same tiles again and again); cold: a new reader.
"""
from __future__ import annotations

import argparse
import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow as pa


def _ms(samples: list[float]) -> str:
    s = sorted(samples)
    return f"median {statistics.median(s) * 1e3:.2f} ms, p95 {s[int(0.95 * (len(s) - 1))] * 1e3:.2f} ms"


def publish(root: Path, blocks: int, legs: int, seed: int) -> Path:
    from bench.bench_tiles import ORIGIN, city, poses, rasters
    from pipeline.testing import make_context
    from stages.tiles.compute import compute
    from stages.tiles.params import TilesParams

    corners, path = city(blocks, seed)
    path = path[: 200 * legs]
    rows = rasters(root / "rasters", path, 0.1, seed)
    ctx = make_context("tiles", TilesParams(), {"corner_map": corners, "poses": poses(path),
                                                "drive_info": pa.table({"drive": ["drive_a"]}), "raster": rows},
                       metadata={"drive_info": {"enu_origin": ORIGIN}}, input_artifacts={"rasters": root / "rasters"},
                       settings={"map_name": "bench", "root": str(root)}, outputs=("published",),
                       workdir=root / "work")
    ctx.inputs.artifact_dir = lambda arg, partition=None: root / "rasters" / partition.label
    row = compute(ctx)["published"].to_pylist()[0]
    return root / "maps" / "bench", row, path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--blocks", type=int, default=40)
    ap.add_argument("--legs", type=int, default=4, help="streets of the serpentine with rasters and the layer")
    ap.add_argument("--radius-m", type=float, default=150.0)
    ap.add_argument("--repeats", type=int, default=300)
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args()
    from mapformat.loader import open_map
    from stages.common.geodesy import EnuOrigin, enu_to_geodetic

    root = Path(tempfile.mkdtemp(prefix="bench-query-"))
    try:
        t0 = time.perf_counter()
        mdir, row, path = publish(root, args.blocks, args.legs, args.seed)
        print(f"machine: {os.cpu_count()} cores (shared); map: {row['n_corners']} corners, {row['n_tiles']} tiles; "
              f"published in {time.perf_counter() - t0:.1f} s")
        reader = open_map(mdir)
        origin = EnuOrigin.from_dict(reader.manifest["enu_origin"])
        rng = np.random.default_rng(args.seed)
        places = path[rng.integers(0, len(path), args.repeats)]
        ll = enu_to_geodetic(np.column_stack([places, np.zeros(len(places))]), origin)
        for lat, lon, _ in ll[:20]:  # warm the caches along the way
            reader.query_latlon(lat, lon, args.radius_m)
        warm, warm_cpu, warm_marking, n_corners, n_cells = [], [], [], [], []
        for lat, lon, _ in ll:
            t0, c0 = time.perf_counter(), time.thread_time()
            q = reader.query_latlon(lat, lon, args.radius_m, markings=False)
            warm.append(time.perf_counter() - t0)
            warm_cpu.append(time.thread_time() - c0)
            t0 = time.perf_counter()
            reader.marking_window(q.east_m - args.radius_m, q.north_m - args.radius_m, q.east_m + args.radius_m,
                                  q.north_m + args.radius_m)
            warm_marking.append(time.perf_counter() - t0)
            n_corners.append(q.corners.num_rows)
            n_cells.append(q.localizability.num_rows)
        cold = []
        for lat, lon, _ in ll[:20]:
            fresh = open_map(mdir)
            t0 = time.perf_counter()
            fresh.query_latlon(lat, lon, args.radius_m, markings=False)
            cold.append(time.perf_counter() - t0)
        print(f"query {args.radius_m:g} m by lat/lon (corners with lat/lon + localizability cells), warm: "
              f"{_ms(warm)} wall, {_ms(warm_cpu)} CPU (the thread's: the machine's load aside); "
              f"{np.median(n_corners):.0f} corners, {np.median(n_cells):.0f} localizability rows; load average "
              f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
        print(f"  marking window {2 * args.radius_m:g} m square at 0.1 m, warm: {_ms(warm_marking)}")
        print(f"  cold (new reader, tiles read and verified): {_ms(cold)}")
    finally:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
