"""Benchmark of map tiles: publish time, tile load time, radius query time, size per km of drive.

    .venv/bin/python -m bench.bench_tiles [--blocks 10] [--cell-m 0.1] [--repeats 200]

A synthetic grid city (60 m blocks, 30 x 20 m buildings, 4 corners each) driven in a serpentine along every
north-south street; marking rasters written with the markings stage's own writer (0.1 m cells, 100 m tiles):
solid + dashed lane lines, 16 m roads traversable, noisy intensity. Numbers go to docs/map-format.md.
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

from mapformat.loader import open_map
from pipeline.declare import PartitionKey
from pipeline.testing import make_context
from schemas import SCHEMAS
from stages.common.tiling import DEFAULT_TILE_SIZE_M
from stages.tiles.compute import compute
from stages.tiles.params import TilesParams

TILE_M = DEFAULT_TILE_SIZE_M
PITCH_M = 60.0
ORIGIN = {"lat_deg": 37.4979, "lon_deg": 127.0276, "h_m": 38.0}


def city(blocks: int, seed: int) -> tuple[pa.Table, np.ndarray]:
    rng = np.random.default_rng(seed)
    c = PITCH_M / 2 + PITCH_M * np.arange(blocks)
    ce, cn = (a.ravel() for a in np.meshgrid(c, c, indexing="ij"))
    xy = np.stack([np.column_stack([ce - 15, cn - 10]), np.column_stack([ce + 15, cn - 10]),
                   np.column_stack([ce + 15, cn + 10]), np.column_stack([ce - 15, cn + 10])], 1).reshape(-1, 2)
    n = len(xy)
    xy = xy + rng.normal(0, 0.02, xy.shape)
    corners = pa.table({
        "corner_id": np.arange(n, dtype=np.int64), "east_m": xy[:, 0], "north_m": xy[:, 1],
        "theta1_rad": rng.uniform(-np.pi, np.pi, n), "theta2_rad": rng.uniform(-np.pi, np.pi, n),
        "cov_ee_m2": rng.uniform(1e-3, 4e-3, n), "cov_en_m2": rng.uniform(-5e-4, 5e-4, n),
        "cov_nn_m2": rng.uniform(1e-3, 4e-3, n), "n_obs": rng.integers(3, 60, n), "n_drives": np.ones(n, np.int32),
        "drives": ["drive_a"] * n, "first_seen_ns": np.zeros(n, np.int64), "last_seen_ns": np.ones(n, np.int64),
        "interior_angle_rad": np.full(n, np.pi / 2), "convex": np.ones(n, bool)}, schema=SCHEMAS["corner_map"])
    top = PITCH_M * blocks
    legs = []
    for k, x in enumerate(PITCH_M * np.arange(blocks + 1)):
        y0, y1 = (1.0, top - 1.0) if k % 2 == 0 else (top - 1.0, 1.0)
        legs.append(np.column_stack([np.full(200, x), np.linspace(y0, y1, 200)]))
    return corners, np.vstack(legs)


def poses(path: np.ndarray) -> pa.Table:
    n = len(path)
    d = np.gradient(path, axis=0)
    yaw = np.arctan2(d[:, 1], d[:, 0])
    return pa.table({"drive": ["drive_a"] * n, "scan_id": np.arange(n, dtype=np.int64),
                     "stamp_ns": np.arange(n, dtype=np.int64) * 100_000_000, "x_m": path[:, 0], "y_m": path[:, 1],
                     "z_m": np.zeros(n), "qx": np.zeros(n), "qy": np.zeros(n), "qz": np.sin(yaw / 2),
                     "qw": np.cos(yaw / 2), "cov_xy_yaw": [[0.0] * 9] * n}, schema=SCHEMAS["poses_optimized"])


def rasters(base: Path, path: np.ndarray, cell_m: float, seed: int) -> pa.Table:
    """Marking rasters of every tile the path crosses, with the markings stage's writer."""
    from stages.common.tiling import tile_key_of
    from stages.markings.raster_io import TileRasters, write_tile_rasters

    rng = np.random.default_rng(seed)
    n = int(round(TILE_M / cell_m))
    keys = sorted(set(zip(*(a.tolist() for a in tile_key_of(path[:, 0], path[:, 1], TILE_M)))))
    rows = []
    for i, j in keys:
        e = i * TILE_M + (np.arange(n) + 0.5) * cell_m
        nn = (j + 1) * TILE_M - (np.arange(n) + 0.5) * cell_m
        E, N = np.meshgrid(e, nn)
        dx = np.abs(((E + PITCH_M / 2) % PITCH_M) - PITCH_M / 2)  # distance to the nearest street centre
        road = dx < 8.0
        marking = (np.abs(dx - 0.1) < 0.08) | ((np.abs(dx - 3.5) < 0.08) & ((N % 9.0) < 3.0))
        intensity = np.where(marking, 80.0, 20.0) + rng.normal(0, 4, E.shape)
        write_tile_rasters(base / PartitionKey(tile_i=i, tile_j=j).label, TileRasters(
            marking_mask=marking & road, traversable_mask=road, intensity=np.where(road, intensity, np.nan),
            min_up_m=np.where(road, 0.02 * np.sin(E / 7.0), np.nan), mean_up_m=np.where(road, 0.03, np.nan),
            count=np.where(road, rng.integers(1, 30, E.shape), 0), origin_east_m=i * TILE_M,
            origin_north_m=j * TILE_M, cell_m=cell_m, meta={"tile_i": i, "tile_j": j}))
        rows.append({"tile_i": i, "tile_j": j, "origin_east_m": i * TILE_M, "origin_north_m": j * TILE_M,
                     "cell_m": cell_m, "width_px": n, "height_px": n, "n_marking_px": int((marking & road).sum()),
                     "n_traversable_px": int(road.sum()), "n_points": 0, "source": "drives"})
    return pa.Table.from_pylist(rows, schema=SCHEMAS["marking_raster"])


def _ms(samples: list[float]) -> str:
    s = sorted(samples)
    return f"median {statistics.median(s) * 1e3:.2f} ms, p95 {s[int(0.95 * (len(s) - 1))] * 1e3:.2f} ms"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--blocks", type=int, default=10)
    ap.add_argument("--cell-m", type=float, default=0.1)
    ap.add_argument("--repeats", type=int, default=200)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--keep", action="store_true", help="keep the temporary map directory")
    args = ap.parse_args()
    print(f"machine: {os.cpu_count()} cores (shared); tile {TILE_M:g} m, cell {args.cell_m} m")
    root = Path(tempfile.mkdtemp(prefix="bench-tiles-"))
    corners, path = city(args.blocks, args.seed)
    drive_km = float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum()) / 1000
    t0 = time.perf_counter()
    raster_rows = rasters(root / "rasters", path, args.cell_m, args.seed)
    t_rasters = time.perf_counter() - t0
    ctx = make_context("tiles", TilesParams(), {"corner_map": corners, "poses": poses(path),
                                                "drive_info": pa.table({"drive": ["drive_a"]}),
                                                "raster": raster_rows},
                       metadata={"drive_info": {"enu_origin": ORIGIN}}, input_artifacts={"rasters": root / "rasters"},
                       settings={"map_name": "bench", "root": str(root)}, outputs=("published",),
                       workdir=root / "work")
    ctx.inputs.artifact_dir = lambda arg, partition=None: root / "rasters" / partition.label
    t0 = time.perf_counter()
    row = compute(ctx)["published"].to_pylist()[0]
    t_publish = time.perf_counter() - t0
    print(f"city: {corners.num_rows} corners, drive {drive_km:.2f} km ({corners.num_rows / drive_km:.0f} corners/km), "
          f"{row['n_tiles']} tiles; writing rasters {t_rasters:.1f} s; publish (gates, copy, sha256, fsync) "
          f"{t_publish:.2f} s")

    vdir = root / row["path"]
    sizes: dict[str, int] = {}
    for p in vdir.rglob("*"):
        if p.is_file():
            kind = "corners" if p.name.endswith(".parquet") else p.stem if p.suffix == ".png" else p.parent.name \
                if p.parent.name == "trajectories" else p.name
            sizes[kind] = sizes.get(kind, 0) + p.stat().st_size
    total = sum(sizes.values())
    raster_total = sum(v for k, v in sizes.items() if k not in ("corners", "trajectories", "manifest.json"))
    print(f"size: total {total / 1e6:.2f} MB = {total / 1e6 / drive_km:.2f} MB/km")
    for k, v in sorted(sizes.items(), key=lambda kv: -kv[1]):
        print(f"  {k:18s} {v / 1e3:10.1f} kB  {v / 1e3 / drive_km:9.1f} kB/km")
    print(f"  {'(all raster files)':18s} {raster_total / 1e3:10.1f} kB  {raster_total / 1e3 / drive_km:9.1f} kB/km")

    reader = open_map(vdir.parent, cache_tiles=4096)
    keys = reader.tile_keys()
    rng = np.random.default_rng(args.seed)
    cold_corners, cold_both = [], []
    for _ in range(args.repeats):
        i, j = keys[rng.integers(len(keys))]
        reader.clear_cache()
        t0 = time.perf_counter()
        reader.tile_corners(i, j)
        t1 = time.perf_counter()
        reader.tile_marking(i, j)
        t2 = time.perf_counter()
        cold_corners.append(t1 - t0)
        cold_both.append(t2 - t0)
    print(f"load one tile (cold cache, OS page cache warm): corners {_ms(cold_corners)}; corners + marking "
          f"{_ms(cold_both)}")
    from mapformat import loader as loader_module

    first, trusted = [], []
    for _ in range(args.repeats):
        i, j = keys[rng.integers(len(keys))]
        for out, trust in ((first, False), (trusted, True)):
            reader.clear_cache()
            loader_module._VERIFIED.clear()
            reader.trust_files = trust
            t0 = time.perf_counter()
            reader.tile_corners(i, j)
            reader.tile_marking(i, j)
            out.append(time.perf_counter() - t0)
    reader.trust_files = False
    print(f"load one tile, first read by the process: sha256-verified {_ms(first)}; trust_files=True {_ms(trusted)}")
    centres = path[rng.integers(len(path), size=args.repeats)]
    reader.clear_cache()
    cold_q = []
    for e, n in centres[: min(30, len(centres))]:
        reader.clear_cache()
        t0 = time.perf_counter()
        reader.corners_within(e, n, 100.0)
        cold_q.append(time.perf_counter() - t0)
    reader.corners_in_bbox(-1e9, -1e9, 1e9, 1e9)  # warm every tile
    warm_q, counts = [], []
    for e, n in centres:
        t0 = time.perf_counter()
        counts.append(reader.corners_within(e, n, 100.0).num_rows)
        warm_q.append(time.perf_counter() - t0)
    print(f"radius 100 m query: warm {_ms(warm_q)} (mean {np.mean(counts):.0f} corners); cold {_ms(cold_q)}")
    warm_w = []
    for e, n in centres[:50]:
        t0 = time.perf_counter()
        reader.marking_window(e - 50, n - 50, e + 50, n + 50)
        warm_w.append(time.perf_counter() - t0)
    print(f"marking window 100 m x 100 m (warm): {_ms(warm_w)}")
    if args.keep:
        print(f"kept {root}")
    else:
        shutil.rmtree(root)


if __name__ == "__main__":
    main()
