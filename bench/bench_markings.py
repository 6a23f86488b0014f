"""Benchmark of the markings stage: throughput, and precision / recall against simulator truth.

    .venv/bin/python -m bench.bench_markings                         # synthetic throughput + Amsterdam tile
    .venv/bin/python -m bench.bench_markings --sim runs/sim/gangnam  # precision/recall vs truth/markings.png
    .venv/bin/python -m bench.bench_markings --sim DIR --figure docs/figures/markings_gangnam.png
    .venv/bin/python -m bench.bench_markings --amsterdam --figure docs/figures/markings_amsterdam_2293_9698.png
    .venv/bin/python -m bench.bench_markings --traffic    # recall with cars standing on the paint in a share of
                                                          # the scans (synthetic street, seeds 2-5), band on / off
    .venv/bin/python -m bench.bench_markings --sim DIR --rasters ROOT/datasets/marking_rasters/<fp> \
        --poses ROOT/datasets/poses_optimized/<fp>   # a pipeline's tiles (e.g. source: drives) vs truth

With ``--rasters`` the tiles the pipeline wrote are scored as they are (absolute) and in the map's own frame:
a map built from drive scans sits where ``poses_optimized`` puts it, which can be decimetres off the true
frame (GNSS bias); each tile is shifted back by the local offset of drive 0's optimized poses vs truth within
50 m of the tile centre (the same rule as the corner-map bench).

Every tile goes through the real stage code (``plan_tiles`` + ``compute`` on an in-memory input reader), so
the timings include reading the tile's rows, the elevation grid, both masks and writing the PNG rasters.
Precision / recall: a predicted marking pixel is a hit when a truth pixel lies within one cell (and vice
versa), counted inside the surveyed area (cells with points, closed by 0.3 m), because truth also paints
streets the survey never drove.
Over 300 lines on purpose: three benchmarks (throughput, scores against simulator truth, traffic on
the paint) share the loaders of simulated and real inputs.
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa

from pipeline.testing import make_context
from schemas import SCHEMAS
from stages.common.tiling import DEFAULT_TILE_SIZE_M
from stages.markings.compute import compute, plan_tiles
from stages.markings.metrics import match_masks
from stages.markings.params import MarkingParams
from stages.markings.raster_io import read_tile_rasters

REPO = Path(__file__).resolve().parents[1]
AMSTERDAM_TILE = "2293_9698"


def _crop_to_data(occupied: np.ndarray, origin_e: float, origin_n: float, cell_m: float, *arrays):
    """Crop arrays (row 0 = north) to the bounding box of ``occupied``; returns (arrays, extent_m)."""
    rows, cols = np.nonzero(occupied)
    r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    n_rows = occupied.shape[0]
    extent = (origin_e + c0 * cell_m, origin_e + c1 * cell_m, origin_n + (n_rows - r1) * cell_m,
              origin_n + (n_rows - r0) * cell_m)
    return [a[r0:r1, c0:c1] for a in arrays], extent


def _machine() -> str:
    return f"{os.cpu_count()} cores (shared), numpy {np.__version__}, OpenCV {cv2.__version__}"


def survey_table(points: np.ndarray, intensity: np.ndarray) -> pa.Table:
    return pa.table({"drive": ["survey"] * len(points), "east_m": points[:, 0], "north_m": points[:, 1],
                     "up_m": points[:, 2], "intensity": np.asarray(intensity, np.float32)},
                    schema=SCHEMAS["survey_enu"])


def run_tiles(tables: dict, params: MarkingParams, tile_size_m: float, workdir: Path) -> list[dict]:
    """Plan and compute every tile; returns per tile the decoded rasters, its row and the seconds taken."""
    settings = {"tile_size_m": tile_size_m}
    keys = plan_tiles(make_context("markings", params, tables, settings=settings))
    out = []
    for key in keys:
        ctx = make_context("markings", params, tables, partition=key, settings=settings,
                           outputs=("raster", "rasters"), workdir=workdir / key.label)
        t0 = time.perf_counter()
        result = compute(ctx)
        seconds = time.perf_counter() - t0
        out.append({"key": key, "row": result["raster"].to_pylist()[0], "seconds": seconds,
                    "rasters": read_tile_rasters(ctx.artifact_dirs["rasters"])})
    return out


def throughput(tiles: list[dict], tile_size_m: float, cell_m: float) -> dict:
    seconds = sum(t["seconds"] for t in tiles)
    cells = len(tiles) * (tile_size_m / cell_m) ** 2
    return {"tiles": len(tiles), "seconds": round(seconds, 3), "cells_per_s": round(cells / seconds),
            "s_per_km2": round(seconds / (len(tiles) * tile_size_m**2 / 1e6), 1),
            "points": int(sum(t["row"]["n_points"] for t in tiles))}


def bench_synthetic(params: MarkingParams, workdir: Path) -> dict:
    """A 100 m tile filled with 5 x 5 copies of the synthetic street (about 200 points / m^2)."""
    from fixtures.markings import make_street

    pieces, inten = [], []
    for a in range(5):
        for b in range(5):
            s = make_street(np.random.default_rng(100 + 5 * a + b), density_per_m2=200.0)
            pieces.append(s.points_enu_m + [20.0 * a, 20.0 * b, 0.0])
            inten.append(s.intensity)
    tables = {"survey": survey_table(np.concatenate(pieces), np.concatenate(inten))}
    tiles = run_tiles(tables, params, 100.0, workdir)
    return throughput(tiles, 100.0, params.cell_m)


def _local_amsterdam(path: Path) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    import laspy

    las = laspy.read(path)
    x0, y0 = (float(v) for v in las.header.mins[:2])
    x0, y0 = np.floor(x0 / 50.0) * 50.0, np.floor(y0 / 50.0) * 50.0
    pts = np.column_stack([np.asarray(las.x) - x0, np.asarray(las.y) - y0, np.asarray(las.z)])
    return pts, np.asarray(las.intensity, np.float32), (x0, y0)


def bench_amsterdam(params: MarkingParams, workdir: Path, data_dir: Path, figure: Path | None) -> dict:
    """Tile 2293_9698 in local RD coordinates (x - x0, y - y0; EPSG:28992 minus the tile corner)."""
    pts, inten, (x0, y0) = _local_amsterdam(data_dir / f"{AMSTERDAM_TILE}.laz")
    tiles = run_tiles({"survey": survey_table(pts, inten)}, params, 50.0, workdir)
    tile = max(tiles, key=lambda t: t["row"]["n_points"])  # a few points sit on the east/north border
    r = tile["rasters"]
    result = {**throughput(tiles, 50.0, params.cell_m), "n_marking_px": tile["row"]["n_marking_px"],
              "n_traversable_px": tile["row"]["n_traversable_px"], "occupied_px": int((r.count > 0).sum())}
    if figure:
        from stages.common.marking_raster.threshold import normalise_intensity
        from stages.markings.figure import plot_marking_layers

        image, _, _ = normalise_intensity(r.intensity, r.traversable_mask, params.intensity_low_pct,
                                          params.intensity_high_pct)
        (img, trav, mark), extent = _crop_to_data(r.count > 0, r.origin_east_m, r.origin_north_m, r.cell_m,
                                                  image, r.traversable_mask, r.marking_mask)
        plot_marking_layers(img, trav, mark, figure,
                            f"Amsterdam MLS tile {AMSTERDAM_TILE} (EPSG:28992, local: x-{x0:.0f}, y-{y0:.0f}), "
                            f"cell {params.cell_m} m", extent_m=extent)
    return result


def _load_sim_survey(sim_dir: Path) -> tuple[np.ndarray, np.ndarray, dict]:
    from stages.common.geodesy import EnuOrigin
    from stages.ingest.survey import iter_survey_enu

    truth_meta = json.loads((sim_dir / "truth" / "markings.json").read_text())
    summary = json.loads((sim_dir / "simulation.json").read_text())
    origin = EnuOrigin.from_dict(truth_meta["origin"])
    pts, inten = [], []
    for las in sorted((sim_dir / "survey").glob("*.la[sz]")):
        for enu, i in iter_survey_enu(las, f"EPSG:{summary['utm_epsg']}", origin):
            pts.append(enu)
            inten.append(i)
    return np.concatenate(pts), np.concatenate(inten), truth_meta


def _paste_into_truth_frame(tiles: list[dict], meta: dict, shape: tuple[int, int]):
    """Predicted marking / surveyed-cell masks resampled (nearest, by pixel centre) into the truth raster."""
    pred = np.zeros(shape, bool)
    surveyed = np.zeros(shape, bool)
    res, west, north = meta["resolution_m"], meta["west_m"], meta["north_m"]
    for t in tiles:
        r = t["rasters"]
        rows_px = r.marking_mask.shape[0]
        for mask, target in ((r.marking_mask, pred), (r.count > 0, surveyed)):
            row, col = np.nonzero(mask)
            east = r.origin_east_m + (col + 0.5) * r.cell_m
            nrth = r.origin_north_m + (rows_px - row - 0.5) * r.cell_m
            tc = np.floor((east - west) / res).astype(int)
            tr = np.floor((north - nrth) / res).astype(int)
            ok = (tr >= 0) & (tr < shape[0]) & (tc >= 0) & (tc < shape[1])
            target[tr[ok], tc[ok]] = True
    kernel = np.ones((3, 3), np.uint8)
    surveyed = cv2.morphologyEx(surveyed.astype(np.uint8), cv2.MORPH_CLOSE, kernel).astype(bool)
    return pred, surveyed


def bench_sim(params: MarkingParams, workdir: Path, sim_dir: Path, figure: Path | None,
              tile_size_m: float) -> dict:
    t0 = time.perf_counter()
    pts, inten, meta = _load_sim_survey(sim_dir)
    load_s = time.perf_counter() - t0
    truth = cv2.imread(str(sim_dir / "truth" / "markings.png"), cv2.IMREAD_UNCHANGED) > 0
    tiles = run_tiles({"survey": survey_table(pts, inten)}, params, tile_size_m, workdir)
    pred, surveyed = _paste_into_truth_frame(tiles, meta, truth.shape)
    scores = match_masks(pred & surveyed, truth & surveyed, tolerance_px=1)
    exact = match_masks(pred & surveyed, truth & surveyed, tolerance_px=0)
    result = {"survey_points": len(pts), "survey_load_s": round(load_s, 1),
              **throughput(tiles, tile_size_m, params.cell_m),
              "precision_1cell": round(scores["precision"], 4), "recall_1cell": round(scores["recall"], 4),
              "precision_exact": round(exact["precision"], 4), "recall_exact": round(exact["recall"], 4),
              "n_predicted": scores["n_predicted"], "n_truth_in_survey": scores["n_truth"]}
    if figure:
        _sim_figure(tiles, truth, meta, params, figure, sim_dir.name)
    return result


def _pipeline_tiles(rasters_dir: Path) -> list[dict]:
    tiles = []
    for sidecar in sorted(rasters_dir.glob("artifacts/*/raster.json")):
        tiles.append({"rasters": read_tile_rasters(sidecar.parent)})
    if not tiles:
        raise SystemExit(f"{rasters_dir}: no artifacts/*/raster.json tiles (expected a marking_rasters dataset)")
    return tiles


def _tile_offsets(tiles: list[dict], poses_dir: Path, sim_dir: Path, radius_m: float = 50.0) -> list[np.ndarray]:
    """Per tile: mean (optimized - true) position of drive 0's poses within ``radius_m`` of the tile centre."""
    import pyarrow.dataset as ds

    from stages.common.records import Trajectory
    from stages.cornermap.metrics import local_frame_offset

    poses = ds.dataset(str(poses_dir), format="parquet", partitioning="hive").to_table()
    drive0 = sorted(set(poses["drive"].to_pylist()))[0]
    opt = Trajectory.from_table(poses, drive0)
    T_true = Trajectory.from_tum(sim_dir / "truth" / f"{drive0}_poses_tum.txt").T
    true_en = T_true[opt.scan_id, :2, 3]
    opt_en = opt.T[:, :2, 3]
    centres = np.array([[t["rasters"].origin_east_m + 0.5 * t["rasters"].cell_m * t["rasters"].marking_mask.shape[1],
                         t["rasters"].origin_north_m + 0.5 * t["rasters"].cell_m * t["rasters"].marking_mask.shape[0]]
                        for t in tiles])
    return list(local_frame_offset(centres, true_en, opt_en, radius_m))


def bench_pipeline_rasters(sim_dir: Path, rasters_dir: Path, poses_dir: Path | None) -> dict:
    """Score the tiles a pipeline run wrote (absolute, and in the map's frame when poses are given)."""
    from dataclasses import replace

    truth = cv2.imread(str(sim_dir / "truth" / "markings.png"), cv2.IMREAD_UNCHANGED) > 0
    meta = json.loads((sim_dir / "truth" / "markings.json").read_text())
    tiles = _pipeline_tiles(rasters_dir)
    out = {"tiles": len(tiles), "source": sorted({t["rasters"].meta.get("source", "?") for t in tiles})}
    frames = {"absolute": tiles}
    if poses_dir is not None:
        offsets = _tile_offsets(tiles, poses_dir, sim_dir)
        out["frame_offset_m_median"] = round(float(np.median([np.hypot(*o) for o in offsets])), 3)
        frames["map_frame"] = [{"rasters": replace(t["rasters"], origin_east_m=t["rasters"].origin_east_m - o[0],
                                                   origin_north_m=t["rasters"].origin_north_m - o[1])}
                               for t, o in zip(tiles, offsets)]
    for name, ts in frames.items():
        pred, covered = _paste_into_truth_frame(ts, meta, truth.shape)
        one = match_masks(pred & covered, truth & covered, tolerance_px=1)
        two = match_masks(pred & covered, truth & covered, tolerance_px=2)
        out[name] = {"precision_1cell": round(one["precision"], 4), "recall_1cell": round(one["recall"], 4),
                     "precision_2cells": round(two["precision"], 4), "recall_2cells": round(two["recall"], 4),
                     "n_predicted": one["n_predicted"], "n_truth_covered": one["n_truth"]}
    return out


def _sim_figure(tiles, truth, meta, params, figure: Path, name: str) -> None:
    """The tile with the most marking pixels, with the truth overlay."""
    from stages.common.marking_raster.threshold import normalise_intensity
    from stages.markings.figure import plot_marking_layers

    best = max(tiles, key=lambda t: t["row"]["n_marking_px"])
    r = best["rasters"]
    rows_px, cols_px = r.marking_mask.shape
    row, col = np.mgrid[0:rows_px, 0:cols_px]
    east = r.origin_east_m + (col + 0.5) * r.cell_m
    nrth = r.origin_north_m + (rows_px - row - 0.5) * r.cell_m
    tc = np.clip(np.floor((east - meta["west_m"]) / meta["resolution_m"]).astype(int), 0, truth.shape[1] - 1)
    tr = np.clip(np.floor((meta["north_m"] - nrth) / meta["resolution_m"]).astype(int), 0, truth.shape[0] - 1)
    image, _, _ = normalise_intensity(r.intensity, r.traversable_mask, params.intensity_low_pct,
                                      params.intensity_high_pct)
    (img, trav, mark, tru), extent = _crop_to_data(r.count > 0, r.origin_east_m, r.origin_north_m, r.cell_m,
                                                   image, r.traversable_mask, r.marking_mask,
                                                   truth[tr, tc] & (r.count > 0))
    plot_marking_layers(img, trav, mark, figure,
                        f"simulated '{name}' survey, tile ({best['key'].tile_i}, {best['key'].tile_j}), "
                        f"cell {r.cell_m} m", truth=tru, extent_m=extent)


def bench_traffic(seeds=(2, 3, 4, 5), shares=(0.0, 0.5, 0.8, 1.0), density_per_m2: float = 2500.0) -> dict:
    """Marking recall / precision (1 cell) of the synthetic street (fixtures.markings.traffic_scans: two
    box cars on the lane line and the crosswalk in ``share`` of 10 scans), with the lowest surface (default
    band) and without it (band 0); the worst seed per row."""
    from fixtures.markings import traffic_scans, truth_raster
    from stages.common.marking_raster.elevation_grid import GridAccumulator
    from stages.common.marking_raster.rasterize import halo_px_for, rasterize_grid

    truth = truth_raster(200, 200, 0.0, 0.0, 0.1)
    out = {}
    for band in (MarkingParams().surface_band_m, 0.0):
        params = MarkingParams(surface_band_m=band)
        halo = halo_px_for(0.1, params.threshold_block_m, params.ground_window_m)
        for share in shares:
            scores = []
            for seed in seeds:
                acc = GridAccumulator(-halo * 0.1, -halo * 0.1, 0.1, (200 + 2 * halo, 200 + 2 * halo), band)
                for scan in traffic_scans(np.random.default_rng(seed), traffic_share=share,
                                          density_per_m2=density_per_m2):
                    acc.add(scan.points_enu_m, scan.intensity)
                layer = rasterize_grid(acc.finish(params.min_points_per_cell), halo, **params.rasterize_kwargs())
                scores.append(match_masks(layer.marking, truth, tolerance_px=1))
            out[f"band {band} m, cars in {share:.0%} of scans"] = {
                "recall_worst": round(min(s["recall"] for s in scores), 4),
                "recall_mean": round(float(np.mean([s["recall"] for s in scores])), 4),
                "precision_worst": round(min(s["precision"] for s in scores), 4)}
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sim", type=Path, help="simulator output directory (survey/*.las, truth/markings.*)")
    ap.add_argument("--amsterdam", action="store_true", help="run the real Amsterdam tile only")
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data" / "amsterdam_mls_laz")
    ap.add_argument("--figure", type=Path, help="write the documentation figure here")
    ap.add_argument("--tile-size", type=float, default=DEFAULT_TILE_SIZE_M, help="tile size for --sim, metres")
    ap.add_argument("--cell", type=float, default=0.1, help="cell size, metres")
    ap.add_argument("--rasters", type=Path, help="a pipeline's marking_rasters dataset folder (with --sim): score "
                                                 "its tiles instead of running the stage on the survey")
    ap.add_argument("--poses", type=Path, help="poses_optimized dataset folder of that run (map-frame score)")
    ap.add_argument("--traffic", action="store_true", help="recall with cars standing on the paint (synthetic)")
    args = ap.parse_args(argv)
    params = MarkingParams(cell_m=args.cell)
    if args.traffic:
        for name, row in bench_traffic().items():
            print(name, json.dumps(row))
        return
    print(f"machine: {_machine()}")
    with tempfile.TemporaryDirectory(prefix="bench-markings-") as tmp:
        workdir = Path(tmp)
        if args.sim and args.rasters:
            print("pipeline rasters", json.dumps(bench_pipeline_rasters(args.sim, args.rasters, args.poses)))
            return
        if args.sim:
            print("sim", json.dumps(bench_sim(params, workdir / "sim", args.sim, args.figure, args.tile_size)))
            return
        if not args.amsterdam:
            print("synthetic 100 m tile", json.dumps(bench_synthetic(params, workdir / "syn")))
        if (args.data / f"{AMSTERDAM_TILE}.laz").is_file():
            print(f"amsterdam {AMSTERDAM_TILE}",
                  json.dumps(bench_amsterdam(params, workdir / "ams", args.data, args.figure)))
        else:
            print(f"amsterdam: {args.data} not found, skipped")


if __name__ == "__main__":
    main()
