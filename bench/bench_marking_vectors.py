"""Vector road markings of a published map scored against the simulator's typed marking truth.

    .venv/bin/python -m bench.bench_marking_vectors --root runs/demo            # map from the root, truth there
    .venv/bin/python -m bench.bench_marking_vectors --root runs/demo --map demo --tol-m 0.3 --json out.json
    .venv/bin/python -m bench.bench_marking_vectors --root runs/demo --rasters   # the markings stage's tiles

``--rasters`` scores the markings stage's committed tiles (``marking_rasters`` under the root) vectorized by the
same code the tiles stage publishes with, without a published map.

Predicted: every tile's ``markings.parquet`` of the LATEST version (what the tiles stage published). Truth: the
simulator's painted elements, typed (``stages.simulate.markings.marking_truth_features``), regenerated from the
run's ``truth/city.json`` (pixel-identical to ``truth/markings.png``). Only truth the map observed counts
(cells with LiDAR points, ``point_count`` > 0), since the simulator also paints streets no drive took. Scores per
type: lines as sampled centrelines within ``--tol-m``, crosswalks/arrows as objects (stages/common/marking_scores).
Also times the vectorization of every tile (what publishing adds), on the same masks.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from bench.roots import latest


def observed_fn(reader):
    """(N, 2) ENU -> bool: the cell holding the point has LiDAR points in the map."""
    counts = {}
    for key in reader.tile_keys():
        meta = reader.tile_entry(*key).get("marking")
        if meta:
            counts[key] = (reader.tile_layer(*key, "point_count"), meta)

    def observed(xy: np.ndarray) -> np.ndarray:
        out = np.zeros(len(xy), bool)
        size = reader.tile_size_m
        for k, (e, n) in enumerate(np.asarray(xy, float)):
            got = counts.get((int(np.floor(e / size)), int(np.floor(n / size))))
            if got is None:
                continue
            img, meta = got
            cell = float(meta["cell_m"])
            col = int((e - meta["origin_east_m"]) // cell)
            row = img.shape[0] - 1 - int((n - meta["origin_north_m"]) // cell)
            r0, r1, c0, c1 = max(0, row - 3), min(img.shape[0], row + 4), max(0, col - 3), min(img.shape[1], col + 4)
            out[k] = bool((img[r0:r1, c0:c1] > 0).any())  # within 0.3 m of an observed cell
        return out

    return observed


class RasterDirReader:
    """The loader calls the bench uses, served from a ``marking_rasters`` dataset (tile+IIII+JJJJ directories)."""

    def __init__(self, dataset_dir: Path):
        import cv2

        self.path, self.tile_size_m, self._tiles = dataset_dir, None, {}
        for d in sorted((dataset_dir / "artifacts").glob("tile*")):
            meta = json.loads((d / "raster.json").read_text())
            self.tile_size_m = tile_size_m = float(meta["tile_size_m"])  # the markings stage states its tile size
            key = (int(round(meta["origin_east_m"] / tile_size_m)), int(round(meta["origin_north_m"] / tile_size_m)))
            self._tiles[key] = {"dir": d, "marking": meta, "n_marking_px": 0,
                                "mask": cv2.imread(str(d / "marking_mask.png"), cv2.IMREAD_GRAYSCALE),
                                "count": cv2.imread(str(d / "point_count.png"), cv2.IMREAD_UNCHANGED)}
            self._tiles[key]["n_marking_px"] = int((self._tiles[key]["mask"] > 0).sum())

    def tile_keys(self):
        return sorted(self._tiles)

    def tile_entry(self, i, j):
        return self._tiles[(i, j)]

    def tile_marking(self, i, j):
        return self._tiles[(i, j)]["mask"]

    def tile_layer(self, i, j, layer):
        return self._tiles[(i, j)]["count"]

    def marking_window(self, e0, n0, e1, n1):
        from mapformat.vectors import mosaic_window

        cell = float(next(iter(self._tiles.values()))["marking"]["cell_m"])
        parts = [(t["mask"], float(t["marking"]["origin_east_m"]), float(t["marking"]["origin_north_m"]))
                 for t in self._tiles.values()]
        return mosaic_window(e0, n0, e1, n1, cell, parts), (e0, n0), cell


def main(argv: list[str] | None = None) -> dict:
    from mapformat.loader import open_map
    from mapformat.vectors import read_map_features, tile_features
    from stages.common.marking_scores import score_markings
    from stages.simulate.markings import city_from_description, marking_truth_features
    from stages.tiles.cli import map_dir_of

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, required=True)
    ap.add_argument("--map", default=None)
    ap.add_argument("--truth", type=Path, default=None, help="truth/city.json (default: the root's simulate run)")
    ap.add_argument("--tol-m", type=float, default=0.3)
    ap.add_argument("--rasters", action="store_true", help="score the root's marking_rasters, not a map")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--figure", type=Path, default=None, help="PNG: the densest raster tile, mask + vectors")
    args = ap.parse_args(argv)
    if args.rasters:
        from mapformat.vectors import tile_features as _tf

        reader = RasterDirReader(latest(args.root, "marking_rasters"))
    else:
        reader = open_map(map_dir_of(args.root, args.map))
    city_json = args.truth or next(iter(sorted((args.root / "datasets" / "raw_drives").glob(
        "*/artifacts/all/truth/city.json"))), None)
    if city_json is None:
        raise SystemExit(f"no truth/city.json under {args.root}/datasets/raw_drives; pass --truth")
    truth = marking_truth_features(city_from_description(json.loads(Path(city_json).read_text())))
    if args.rasters:
        def mask_of0(key):
            if key not in reader.tile_keys():
                return None
            marking = reader.tile_entry(*key)["marking"]
            return (reader.tile_marking(*key), float(marking["origin_east_m"]), float(marking["origin_north_m"]),
                    float(marking["cell_m"]))
        feats = [f for k in reader.tile_keys() for f in _tf(k, reader.tile_size_m, mask_of0)]
    else:
        feats = read_map_features(reader.path, [reader.tile_entry(*k) for k in reader.tile_keys()])
    scores = score_markings([(f.type, f.xy_m) for f in feats], truth, tol_m=args.tol_m, observed=observed_fn(reader))

    def mask_of(key):
        if key not in reader.tile_keys() or not reader.tile_entry(*key).get("marking"):
            return None
        meta = reader.tile_entry(*key)["marking"]
        return (reader.tile_marking(*key), float(meta["origin_east_m"]), float(meta["origin_north_m"]),
                float(meta["cell_m"]))

    keys = [k for k in reader.tile_keys() if reader.tile_entry(*k).get("marking")]
    times = []
    for key in keys:
        t0 = time.perf_counter()
        tile_features(key, reader.tile_size_m, mask_of)
        times.append(time.perf_counter() - t0)
    result = {"map": str(reader.path), "tol_m": args.tol_m, "scores": scores, "n_tiles": len(keys),
              "vectorize_s_per_tile_median": float(np.median(times)) if times else None,
              "vectorize_s_per_tile_max": float(np.max(times)) if times else None}
    print(f"{reader.path}: {len(feats)} features in {len(keys)} raster tiles; tolerance {args.tol_m} m")
    print(f"{'type':<12} {'precision':>9} {'recall':>7} {'predicted':>9} {'truth seen':>10}")
    for kind, s in scores.items():
        print(f"{kind:<12} {s['precision']:>9.3f} {s['recall']:>7.3f} {s['n_predicted']:>9d} {s['n_truth']:>10d}")
    if times:
        print(f"vectorize per tile (window with 10 m margin): median {np.median(times) * 1e3:.0f} ms, "
              f"max {np.max(times) * 1e3:.0f} ms")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    if args.figure and keys:
        draw_figure(reader, feats, truth, keys, args.figure)
    return result


def draw_figure(reader, feats, truth, keys, path: Path) -> None:
    """The densest tile: marking mask in grey, truth in thin black, vectors coloured by type."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    key = max(keys, key=lambda k: reader.tile_entry(*k).get("n_marking_px", 0))
    e0, n0 = key[0] * reader.tile_size_m, key[1] * reader.tile_size_m
    e1, n1 = e0 + reader.tile_size_m, n0 + reader.tile_size_m
    mask, (we, sn), cell = reader.marking_window(e0, n0, e1, n1)
    fig, ax = plt.subplots(figsize=(9, 9))
    ax.imshow(mask > 0, cmap="Greys", alpha=0.35, extent=(we, we + mask.shape[1] * cell, sn, sn + mask.shape[0] * cell))
    colours = {"lane_solid": "tab:blue", "lane_dashed": "tab:green", "stop_line": "tab:red",
               "crosswalk": "tab:purple", "arrow": "tab:orange"}
    for kind, xy in truth:
        ring = np.vstack([xy, xy[:1]]) if kind in ("crosswalk", "arrow") else xy
        ax.plot(ring[:, 0], ring[:, 1], color="k", lw=0.5, ls=":")
    seen = set()
    for f in feats:
        ring = np.vstack([f.xy_m, f.xy_m[:1]]) if f.is_polygon else f.xy_m
        ax.plot(ring[:, 0], ring[:, 1], color=colours[f.type], lw=1.6, label=None if f.type in seen else f.type)
        seen.add(f.type)
    ax.set_xlim(e0, e1)
    ax.set_ylim(n0, n1)
    ax.set_aspect("equal")
    ax.set_xlabel("east (m, map ENU)")
    ax.set_ylabel("north (m)")
    ax.set_title(f"tile {key}: marking mask (grey), truth (dotted), vector markings (colour)")
    ax.legend(loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
