"""MCL ablation on a published map: the default marking localizer against itself with one part switched off
(blurred raster instead of the distance likelihood field, no wheel-scale / gyro-bias state, no feature deskew),
over several seeds, scored against a truth trajectory (mean |x| along-track, |y| across-track, |heading|).

The drive is ingested once (``cornermap evaluate``'s generated workflow under OUT/work; later runs reuse it), then
the evaluate compute runs per variant and seed.

    .venv/bin/python -m bench.bench_mcl_ablation --root runs/demo --map demo --drive SIM/drive_1/drive.yaml \\
        --reference SIM/truth/drive_1_poses_tum.txt --out runs/mcl_ablation [--seeds 0 1 2 3] [--variants ...]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

VARIANTS = {
    "final": {},
    "blurred_raster": {"markings": {"field": "blur"}},
    "no_scale_bias_state": {"mcl": {"init_sigma_scale": 0.0, "sigma_scale_per_sqrt_m": 0.0,
                                    "init_sigma_gyro_bias_deg_s": 0.0, "sigma_gyro_bias_deg_s_per_sqrt_s": 0.0}},
    "no_deskew": {"features": {"deskew": False}},
}
KEYS = ("mean_abs_x_m", "mean_abs_y_m", "mean_abs_heading_deg")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, required=True, help="output root holding maps/NAME/")
    ap.add_argument("--map", required=True)
    ap.add_argument("--map-version", dest="version", default="LATEST", help="LATEST, vNNNN or N")
    ap.add_argument("--drive", type=Path, required=True, help="the drive's drive.yaml")
    ap.add_argument("--reference", type=Path, required=True, help="truth TUM trajectory (its frame stated)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    args = ap.parse_args()

    from stages.evaluate.cli import open_named_map, run_evaluation
    from stages.evaluate.params import EvaluateParams

    reader = open_named_map(args.root, args.map, args.version)
    args.out.mkdir(parents=True, exist_ok=True)
    print(f"map {reader.path}; drive {args.drive}; seeds {args.seeds}")
    print("| variant | " + " | ".join(KEYS) + " | worst seed (mean |x|) |")
    print("|---" * (len(KEYS) + 2) + "|")
    for name in args.variants:
        rows = []
        for seed in args.seeds:
            v = VARIANTS[name]
            p = EvaluateParams(methods=["mcl"], **{**v, "mcl": {**v.get("mcl", {}), "seed": seed}})
            doc = run_evaluation(reader, args.drive, str(args.reference), p, args.out, True)
            truth = doc["methods"]["mcl"]["absolute"] or {}
            rows.append([np.nan if truth.get(k) is None else float(truth[k]) for k in KEYS])
        arr = np.asarray(rows)
        worst = int(np.nanargmax(arr[:, 0])) if np.isfinite(arr[:, 0]).any() else 0
        print(f"| {name} | " + " | ".join(f"{v:.3f}" for v in np.nanmean(arr, axis=0))
              + f" | seed {args.seeds[worst]}: {arr[worst, 0]:.3f} |")


if __name__ == "__main__":
    main()
