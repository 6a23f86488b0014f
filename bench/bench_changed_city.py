"""Changed-city benchmark: does a map's changelog find what changed in the city, and do unchanged corners keep
their ids?

    .venv/bin/python -m bench.bench_changed_city --seeds 7 11 12 13 [--preset tiny] [--work runs/changed]

Per seed: ``cornermap simulate --changes`` with 3 drives (drives 0 and 1 see the city as generated, drive 2 the
changed city: a building demolished, one built, a crosswalk moved; truth in truth/changes.json), then
``cornermap build`` of version 1 from drives 0 + 1 and of version 2 from drive 2 into one map. Scored on
version 2's changelog against the truth (a map corner "is" a truth corner within ``--radius-m``, 1 m):
  removed recall     truth-removed corners that version 1 mapped and the changelog lists as removed
  removed precision  changelog-removed corners that are truth-removed corners
  id kept            unchanged truth corners mapped in both versions whose id is the same in both
Counts are pooled over seeds; the worst seed is printed too.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ORIGIN = "37.4979,127.0276,57"  # the simulator's origin


def _near(a: np.ndarray, b: np.ndarray, radius_m: float) -> np.ndarray:
    """(len(a),) index of the nearest row of b within radius_m, -1 when none."""
    from scipy.spatial import cKDTree

    a, b = np.asarray(a, float).reshape(-1, 2), np.asarray(b, float).reshape(-1, 2)
    if len(a) == 0 or len(b) == 0:
        return np.full(len(a), -1)
    d, i = cKDTree(b).query(a, distance_upper_bound=radius_m)
    return np.where(np.isfinite(d), i, -1)


def score_changelog(changes: dict, truth_before_en: np.ndarray, v1: dict, v2: dict, changelog: dict,
                    radius_m: float = 1.0) -> dict:
    """Counts of the three scores above. ``v1``/``v2``: {"en": (N,2), "ids": (N,)} of the two versions' corners;
    ``truth_before_en``: truth/corners.csv positions (the city as of drive 0)."""
    removed_truth = np.array([[c["east_m"], c["north_m"]] for c in changes["corners"]["removed"]]).reshape(-1, 2)
    removed_log = np.array([[c["east_m"], c["north_m"]] for c in changelog["corners"]["removed"]]).reshape(-1, 2)
    mapped = _near(removed_truth, v1["en"], radius_m) >= 0
    found = _near(removed_truth, removed_log, radius_m) >= 0
    true_pos = _near(removed_log, removed_truth, radius_m) >= 0
    unchanged = np.ones(len(truth_before_en), bool)
    unchanged[_near(removed_truth, truth_before_en, 0.01)[_near(removed_truth, truth_before_en, 0.01) >= 0]] = False
    truth_u = np.asarray(truth_before_en, float)[unchanged]
    i1, i2 = _near(truth_u, v1["en"], radius_m), _near(truth_u, v2["en"], radius_m)
    both = (i1 >= 0) & (i2 >= 0)
    same = np.asarray(v1["ids"])[i1[both]] == np.asarray(v2["ids"])[i2[both]]
    return {"removed_truth": int(len(removed_truth)), "removed_mapped": int(mapped.sum()),
            "removed_found": int((found & mapped).sum()), "removed_listed": int(len(removed_log)),
            "removed_listed_true": int(true_pos.sum()), "unchanged_in_both": int(both.sum()),
            "unchanged_same_id": int(same.sum())}


def _ratio(a: int, b: int) -> float | None:
    return round(a / b, 4) if b else None


def ratios(c: dict) -> dict:
    return {"removed_recall": _ratio(c["removed_found"], c["removed_mapped"]),
            "removed_precision": _ratio(c["removed_listed_true"], c["removed_listed"]),
            "id_kept": _ratio(c["unchanged_same_id"], c["unchanged_in_both"])}


def _corners(version_dir: Path) -> dict:
    from mapformat.loader import open_map

    t = open_map(version_dir).all_corners()
    return {"en": np.column_stack([t["east_m"].to_numpy(), t["north_m"].to_numpy()]), "ids": t["corner_id"].to_numpy()}


def run_seed(preset: str, seed: int, work: Path, scheduler: str) -> dict:
    from mapformat.changelog import read_changelog
    from mapformat.loader import open_map

    sim, root = work / f"sim_{preset}_{seed}", work / f"root_{preset}_{seed}"
    cli = [sys.executable, "-m", "mapservice"]
    t0 = time.perf_counter()
    if not (sim / "truth" / "changes.json").is_file():
        subprocess.run(cli + ["simulate", "--preset", preset, "--seed", str(seed), "--drives", "3", "--changes",
                              "--out", str(sim), "--quiet"], check=True)
    t_sim = time.perf_counter() - t0
    walls = []
    for drives in (["drive_0", "drive_1"], ["drive_2"]):
        t0 = time.perf_counter()
        subprocess.run(
            cli
            + ["build", "--map", "city", "--root", str(root), "--origin", ORIGIN, "-q", "--scheduler", scheduler]
            + [a for d in drives for a in ("--drive", str(sim / d / "drive.yaml"))],
            check=True,
        )
        walls.append(round(time.perf_counter() - t0, 1))
    d = root / "maps" / "city"
    v2 = open_map(d, 2)
    log = read_changelog(v2.path, v2.manifest)
    changes = json.loads((sim / "truth" / "changes.json").read_text())
    truth = np.loadtxt(sim / "truth" / "corners.csv", delimiter=",", skiprows=1, usecols=(1, 2))
    counts = score_changelog(changes, truth, _corners(d / "v0001"), _corners(d / "v0002"), log)
    return {
        "seed": seed,
        **counts,
        **ratios(counts),
        "marking_px_changed_truth": changes["markings"][0]["pixels_changed"],
        "marking_px_changed_log": log["markings"]["total_px_changed"],
        "wall_s": {"simulate": round(t_sim, 1), "build_v1": walls[0], "build_v2": walls[1]},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[11, 12, 13])
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--work", type=Path, default=Path("runs/bench_changed_city"))
    ap.add_argument("--scheduler", default="sync")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    os.environ.setdefault("PYTHONPATH", str(Path(__file__).resolve().parents[1]))
    rows = [run_seed(args.preset, s, args.work, args.scheduler) for s in args.seeds]
    for r in rows:
        print(json.dumps(r))
    pooled = {k: sum(r[k] for r in rows) for k in ("removed_truth", "removed_mapped", "removed_found", "removed_listed",
                                                   "removed_listed_true", "unchanged_in_both", "unchanged_same_id")}
    worst = {k: min((r[k] for r in rows if r[k] is not None), default=None)
             for k in ("removed_recall", "removed_precision", "id_kept")}
    out = {"preset": args.preset, "seeds": args.seeds, "pooled": {**pooled, **ratios(pooled)}, "worst_seed": worst}
    print(json.dumps(out, indent=1))
    if args.json:
        args.json.write_text(json.dumps({"runs": rows, **out}, indent=1))


if __name__ == "__main__":
    main()
