"""Change detection against the simulator's truth: precision and recall of the changelog's corner and marking
changes on a changed city, and its false alarms on an unchanged re-drive.

    .venv/bin/python -m bench.bench_change_detection --preset tiny --seeds 321 322 --root runs/loc

Per seed, in the root ``bench_localizability`` uses (``ROOT/<preset>-<seed>``: ``simulate --drives 3 --changes``;
drives 0 and 1 see the city as generated, drive 2 the changed city: a building demolished, one built, a crosswalk
moved 2 m; truth in truth/changes.json), two maps are built with ``cornermap build`` (fresh each run):
  chg   v1 from drive 0, v2 from drive 2 (after the change)
  same  v1 from drive 0, v2 from drive 1 (the same city, another drive: every change listed is a false alarm)
Scored on each v2's changelog (a listed corner "is" a truth corner within ``--radius-m``, 1 m):
  corners   precision = listed removed/added that are truth removed/added (moved count as false: nothing moved)
            recall    = truth removed corners v1 mapped that are listed removed, and truth added corners v2 mapped
                        that are listed added
  markings  precision = listed cells holding >= 20 changed truth pixels (old or new crosswalk paint, not both)
            recall    = such truth cells (observed by both versions) listed
  same      false alarms: corners listed removed / added / moved, and marking cells, on the unchanged re-drive
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

ORIGIN = "37.4979,127.0276,57"
MAPS = {"chg": ("drive_0", "drive_2"), "same": ("drive_0", "drive_1")}


def _near(a: np.ndarray, b: np.ndarray, radius_m: float) -> np.ndarray:
    from scipy.spatial import cKDTree

    a, b = np.asarray(a, float).reshape(-1, 2), np.asarray(b, float).reshape(-1, 2)
    if len(a) == 0 or len(b) == 0:
        return np.full(len(a), -1)
    d, i = cKDTree(b).query(a, distance_upper_bound=radius_m)
    return np.where(np.isfinite(d), i, -1)


def _en(entries: list[dict]) -> np.ndarray:
    return np.array([[e["east_m"], e["north_m"]] for e in entries], float).reshape(-1, 2)


def truth_cells(changes: dict, cell_m: float = 10.0, raster_m: float = 0.1, min_px: int = 20) -> set[tuple[int, int]]:
    """The cells where the moved crosswalk's old and new paint differ by at least ``min_px`` raster cells."""
    import cv2

    polys = [np.asarray(p, float) for m in changes["markings"] for k in ("old_stripes_en", "new_stripes_en")
             for p in m.get(k, [])]
    if not polys:
        return set()
    allp = np.vstack(polys)
    e0, n0 = np.floor(allp.min(axis=0) / cell_m) * cell_m - cell_m
    e1, n1 = np.ceil(allp.max(axis=0) / cell_m) * cell_m + cell_m
    w, h = int(round((e1 - e0) / raster_m)), int(round((n1 - n0) / raster_m))

    def paint(kind: str) -> np.ndarray:
        img = np.zeros((h, w), np.uint8)
        for m in changes["markings"]:
            for p in m.get(kind, []):
                px = np.column_stack([(np.asarray(p)[:, 0] - e0) / raster_m, (n1 - np.asarray(p)[:, 1]) / raster_m])
                cv2.fillPoly(img, [np.round(px).astype(np.int32)], 1)
        return img

    xor = paint("old_stripes_en") ^ paint("new_stripes_en")
    rows, cols = np.nonzero(xor)
    keys = np.column_stack([np.floor((e0 + (cols + 0.5) * raster_m) / cell_m),
                            np.floor((n1 - (rows + 0.5) * raster_m) / cell_m)]).astype(int)
    uniq, count = np.unique(keys, axis=0, return_counts=True)
    return {(int(i), int(j)) for (i, j), c in zip(uniq, count) if c >= min_px}


def build_maps(root: Path, sim: Path) -> None:
    for name, drives in MAPS.items():
        shutil.rmtree(root / "maps" / name, ignore_errors=True)
        for d in drives:
            subprocess.run([sys.executable, "-m", "mapservice", "build", "--drive", str(sim / d / "drive.yaml"),
                            "--map", name, "--root", str(root), "--origin", ORIGIN, "-q"], check=True)


def score(root: Path, sim: Path, radius_m: float = 1.0) -> dict:
    from mapformat.changelog import read_changelog
    from mapformat.loader import open_map

    changes = json.loads((sim / "truth" / "changes.json").read_text())
    out = {}
    for name in MAPS:
        v1, v2 = open_map(root / "maps" / name, 1), open_map(root / "maps" / name, 2)
        log = read_changelog(v2.path, v2.manifest)
        c, m = log["corners"], log["markings"]
        cells = {tuple(x["cell"]) for x in m["cells"]}
        if name == "same":
            out[name] = {"removed": len(c["removed"]), "added": len(c["added"]), "moved": len(c["moved"]),
                         "kept": c["kept"], "marking_cells": len(cells),
                         "marking_cells_compared": (m.get("test") or {}).get("cells_compared"),
                         "not_reobserved": len(c["not_reobserved"]), "newly_observed": len(c["newly_observed"])}
            continue
        t1, t2 = v1.all_corners(), v2.all_corners()
        en1 = np.column_stack([t1["east_m"].to_numpy(), t1["north_m"].to_numpy()])
        en2 = np.column_stack([t2["east_m"].to_numpy(), t2["north_m"].to_numpy()])
        tr_rm, tr_add = _en(changes["corners"]["removed"]), _en(changes["corners"]["added"])
        rm_mapped = _near(tr_rm, en1, radius_m) >= 0
        add_mapped = _near(tr_add, en2, radius_m) >= 0
        rm_found = (_near(tr_rm, _en(c["removed"]), radius_m) >= 0) & rm_mapped
        add_found = (_near(tr_add, _en(c["added"]), radius_m) >= 0) & add_mapped
        rm_true = int((_near(_en(c["removed"]), tr_rm, radius_m) >= 0).sum())
        add_true = int((_near(_en(c["added"]), tr_add, radius_m) >= 0).sum())
        listed = len(c["removed"]) + len(c["added"]) + len(c["moved"])
        truth = truth_cells(changes, float(m.get("cell_m") or 10.0))
        out[name] = {"truth_removed_mapped": int(rm_mapped.sum()), "truth_added_mapped": int(add_mapped.sum()),
                     "found": int(rm_found.sum() + add_found.sum()), "listed": listed,
                     "listed_true": rm_true + add_true, "moved": len(c["moved"]),
                     "not_reobserved": len(c["not_reobserved"]), "newly_observed": len(c["newly_observed"]),
                     "truth_cells": len(truth), "cells_listed": len(cells), "cells_true": len(cells & truth),
                     "cells_found": len(truth & cells)}
    return out


def _ratio(a: int, b: int) -> float | None:
    return round(a / b, 3) if b else None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--seeds", type=int, nargs="+", required=True)
    ap.add_argument("--root", type=Path, default=Path("runs/bench_localizability"))
    ap.add_argument("--no-build", action="store_true", help="score the maps as they are")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    os.environ.setdefault("PYTHONPATH", str(Path(__file__).resolve().parents[1]))
    from bench.bench_localizability import workflow_for
    from bench.roots import simulator_dir

    rows = []
    for seed in args.seeds:
        root = (args.root / f"{args.preset}-{seed}").resolve()
        if not args.no_build:
            if not (root / "datasets" / "raw_drives").is_dir():
                subprocess.run([sys.executable, "-m", "mapservice", "run", str(workflow_for(args.preset, seed, root)),
                                "-q", "--only", "simulate"], check=True)
            build_maps(root, simulator_dir(root))
        r = {"seed": seed, **score(root, simulator_dir(root))}
        print(json.dumps(r))
        rows.append(r)
    tot = {k: sum(r["chg"][k] for r in rows) for k in rows[0]["chg"]}
    same = {k: sum(r["same"][k] or 0 for r in rows) for k in rows[0]["same"]}
    pooled = {"corner_precision": _ratio(tot["listed_true"], tot["listed"]),
              "corner_recall": _ratio(tot["found"], tot["truth_removed_mapped"] + tot["truth_added_mapped"]),
              "cell_precision": _ratio(tot["cells_true"], tot["cells_listed"]),
              "cell_recall": _ratio(tot["cells_found"], tot["truth_cells"]),
              "same_false_corners": same["removed"] + same["added"] + same["moved"], "same_kept": same["kept"],
              "same_false_cells": same["marking_cells"], "same_cells_compared": same["marking_cells_compared"]}
    per = [{"seed": r["seed"], "corner_precision": _ratio(r["chg"]["listed_true"], r["chg"]["listed"]),
            "corner_recall": _ratio(r["chg"]["found"], r["chg"]["truth_removed_mapped"]
                                    + r["chg"]["truth_added_mapped"]),
            "cell_precision": _ratio(r["chg"]["cells_true"], r["chg"]["cells_listed"]),
            "cell_recall": _ratio(r["chg"]["cells_found"], r["chg"]["truth_cells"])} for r in rows]
    worst = {k: min((p[k] for p in per if p[k] is not None), default=None) for k in per[0] if k != "seed"}
    print(json.dumps({"preset": args.preset, "seeds": args.seeds, "pooled": pooled, "per_seed": per,
                      "worst_seed": worst}, indent=1))
    if args.json:
        args.json.write_text(json.dumps({"runs": rows, "pooled": pooled, "per_seed": per, "worst_seed": worst},
                                        indent=1))


if __name__ == "__main__":
    main()
