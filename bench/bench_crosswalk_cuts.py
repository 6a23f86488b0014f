"""Crosswalk outlines on synthetic crosswalks cut by a straight coverage edge at random (fixtures/crosswalk_cuts.py).

    .venv/bin/python -m bench.bench_crosswalk_cuts                  # 120 cuts, 80 whole crosswalks
    .venv/bin/python -m bench.bench_crosswalk_cuts --cuts 300 --seed 5

Per cut crosswalk found: its corners' signed distance to the paint's rectangle (negative = outside the paint) and
how far past the coverage edge (into the unseen part) they lie; per whole crosswalk, the largest distance of a
corner to the paint's corner it stands for. The test suite's random cuts (seed 2026) are not these seeds.
"""
from __future__ import annotations

import argparse
import json

import numpy as np


def main(argv: list[str] | None = None) -> dict:
    from fixtures.crosswalk_cuts import CELL_M, cut_crosswalk, random_cuts, signed_inside_m
    from stages.common.marking_vectors import vectorize_markings

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cuts", type=int, default=120)
    ap.add_argument("--whole", type=int, default=80)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    outside, past, nan = [], [], 0
    for angle, cut, at, seed in random_cuts(args.cuts, args.seed):
        mask, rect, (p0, normal) = cut_crosswalk(angle, cut, at, seed)
        for f in vectorize_markings(mask, 0.0, 0.0, CELL_M):
            if f.type != "crosswalk":
                continue
            if not np.isfinite(f.xy_m).all():
                nan += 1
                continue
            outside.append(-min(signed_inside_m(rect, p) for p in f.xy_m))
            past.append(float(((f.xy_m - p0) @ normal).max()))
    whole = []
    for angle, _, _, seed in random_cuts(args.whole, args.seed + 1):
        mask, rect, _ = cut_crosswalk(angle, None, 0.0, seed)
        for f in vectorize_markings(mask, 0.0, 0.0, CELL_M):
            if f.type == "crosswalk":
                whole.append(max(np.linalg.norm(rect - p, axis=1).min() for p in f.xy_m))
    outside_a, past_a = np.array(outside), np.array(past)
    result = {"cut_crosswalks": len(outside) + nan, "with_nan_corner": nan,
              "outside_paint_worst_m": float(outside_a.max()), "outside_paint_over_5cm": int((outside_a > 0.05).sum()),
              "past_edge_worst_m": float(past_a.max()), "past_edge_over_5cm": int((past_a > 0.05).sum()),
              "past_edge_over_10cm": int((past_a > 0.1).sum()),
              "whole_crosswalks": len(whole), "whole_corner_worst_m": float(max(whole))}
    print(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
