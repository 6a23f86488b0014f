"""Is the localizability layer honest? Its predicted sigma_2d per cell against the corner EKF's real errors in the
truth frame, on drives the map was not built from.

    .venv/bin/python -m bench.bench_localizability --preset tiny --seeds 321 322 323 --root runs/loc [--figure DIR]

Per seed: ``workflows/<preset>.yaml`` with the simulator's seed (and ``--drives 3 --changes``, so the roots serve
``bench_changed_city`` too: drive 0 maps the city, drive 1 is the evaluation drive, both before the change) runs
through the engine under ``ROOT/<preset>-<seed>`` (committed stages are skipped). Then, on the evaluation of the
map's LATEST version:
  error      the estimate minus the simulator's truth moved into the map frame by geodesy
             (``reference_truth_tum.txt``: the truth frame, not a fit onto the map), 2-D, per epoch; the EKF's epochs
             from its first map-corner association on (its start-up is not a localized pose)
  sigma      sigma_2d_m of the localizability cell holding the true position (method ekf, or mcl)
  beyond_3   share of epochs with error > 3 sigma              (target: <= 0.05)
  ratio      median sigma / median error over the epochs        (target: within 1/4 .. 4)
  detection  mean associated corners / mean corners the layer predicts in view (the EKF's)
Prints one JSON line per seed and the worst seed (largest beyond_3, ratio farthest from 1).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def workflow_for(preset: str, seed: int, root: Path) -> Path:
    import yaml

    from bench.bench_seeds import write_workflow

    path = write_workflow(preset, seed, root, None)
    spec = yaml.safe_load(path.read_text())
    spec["params"]["simulate"].update(drives=3, changes=True)
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


def _truth_at(tum: Path, stamps_s: np.ndarray) -> np.ndarray:
    rows = np.loadtxt(tum, comments="#", ndmin=2)
    out = np.full((len(stamps_s), 2), np.nan)
    inside = (stamps_s >= rows[0, 0]) & (stamps_s <= rows[-1, 0])
    for c in (0, 1):
        out[inside, c] = np.interp(stamps_s[inside], rows[:, 0], rows[:, 1 + c])
    return out


def score_seed(root: Path, map_name: str = "tiny") -> dict:
    """The figures of one seed's root (see the module doc)."""
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    from bench.roots import latest
    from mapformat.loader import open_map

    reader = open_map(root / "maps" / map_name)
    cells = reader.localizability_in_bbox(-np.inf, -np.inf, np.inf, np.inf)
    if cells.num_rows == 0:
        raise SystemExit(f"{root}: map {map_name} v{reader.version} has no localizability layer")
    cell_m = float(reader.manifest["localizability"]["cell_m"])
    report = max((p for p in latest(root, "eval_report").glob("artifacts/*")
                  if (p / "metrics.json").is_file()), key=lambda p: (p / "metrics.json").stat().st_mtime)
    metrics = json.loads((report / "metrics.json").read_text())
    epochs = pq.read_table(report / "epochs.parquet")
    out = {"seed_root": str(root), "version": reader.version}
    for method in ("ekf", "mcl"):
        e = epochs.filter(pc.equal(epochs["method"], method)).sort_by("epoch")
        est = np.column_stack([e["x_m"].to_numpy(), e["y_m"].to_numpy()])
        truth = _truth_at(report / "reference_truth_tum.txt", e["stamp_ns"].to_numpy() * 1e-9)
        keep = np.isfinite(est).all(axis=1) & np.isfinite(truth).all(axis=1)
        if method == "ekf":
            first = int(metrics["methods"]["ekf"].get("localized_from_epoch") or 0)
            keep &= e["epoch"].to_numpy() >= first
        err = np.linalg.norm(est - truth, axis=1)
        lt = cells.filter(pc.equal(cells["method"], method))
        table = {(i, j): k for k, (i, j) in enumerate(zip(lt["cell_i"].to_pylist(), lt["cell_j"].to_pylist()))}
        key = np.floor(truth / cell_m)
        row = np.array([table.get((int(a), int(b)), -1) if np.isfinite(a) else -1 for a, b in key])
        scored = keep & (row >= 0)
        sigma = lt["sigma_2d_m"].to_numpy()[row[scored]]
        r = err[scored] / sigma
        res = {"epochs": int(keep.sum()), "scored": int(scored.sum()),
               "beyond_3": round(float((r > 3).mean()), 4) if len(r) else None,
               "median_sigma_m": round(float(np.median(sigma)), 4) if len(r) else None,
               "median_error_m": round(float(np.median(err[scored])), 4) if len(r) else None,
               "p95_error_over_sigma": round(float(np.percentile(r, 95)), 3) if len(r) else None}
        res["ratio"] = round(res["median_sigma_m"] / res["median_error_m"], 3) if len(r) else None
        if method == "ekf":
            vis = lt["n_corners_visible"].to_numpy()[row[scored]]
            assoc = e["n_associated"].to_numpy()[scored]
            res["detection"] = round(float(assoc.mean() / max(vis.mean(), 1e-9)), 3)
        out[method] = res
    return out


def figure(root: Path, path: Path, map_name: str = "tiny") -> None:
    """The layer of one seed over its map: cells coloured by the EKF's sigma_2d, corners, weak cells named."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pyarrow.compute as pc

    from mapformat.loader import open_map

    reader = open_map(root / "maps" / map_name)
    cells = reader.localizability_in_bbox(-np.inf, -np.inf, np.inf, np.inf)
    corners = reader.all_corners()
    fig, axes = plt.subplots(1, 2, figsize=(11, 5), constrained_layout=True)
    for ax, method in zip(axes, ("ekf", "mcl")):
        t = cells.filter(pc.equal(cells["method"], method))
        sc = ax.scatter(t["east_m"].to_numpy(), t["north_m"].to_numpy(), c=t["sigma_2d_m"].to_numpy(), cmap="viridis",
                        s=120, marker="s")
        weak = np.asarray(t["status"].to_pylist()) != "ok"
        ax.scatter(t["east_m"].to_numpy()[weak], t["north_m"].to_numpy()[weak], s=200, facecolors="none",
                   edgecolors="red", label="weak / fail")
        ax.plot(corners["east_m"].to_numpy(), corners["north_m"].to_numpy(), "k^", label="map corners")
        fig.colorbar(sc, ax=ax, label=f"{method}: predicted sigma_2d (m)")
        ax.set(title=f"{method}: {reader.manifest['map_name']} v{reader.version}", xlabel="east (m, map ENU)",
               ylabel="north (m)", aspect="equal")
        ax.legend(loc="best", fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def worst(rows: list[dict], method: str) -> dict:
    vals = [r[method] for r in rows if r[method]["beyond_3"] is not None]
    far = max(vals, key=lambda v: max(v["ratio"], 1.0 / v["ratio"]))
    return {"beyond_3": max(v["beyond_3"] for v in vals), "ratio_farthest_from_1": far["ratio"],
            "ratio_range": [min(v["ratio"] for v in vals), max(v["ratio"] for v in vals)]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--seeds", type=int, nargs="+", required=True)
    ap.add_argument("--root", type=Path, default=Path("runs/bench_localizability"))
    ap.add_argument("--no-run", action="store_true", help="score the roots as they are (no workflow run)")
    ap.add_argument("--figure", type=Path, help="write one figure per seed into this folder")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    os.environ.setdefault("PYTHONPATH", str(REPO))
    rows = []
    for seed in args.seeds:
        root = (args.root / f"{args.preset}-{seed}").resolve()
        if not args.no_run:
            wf = workflow_for(args.preset, seed, root)
            subprocess.run([sys.executable, "-m", "mapservice", "run", str(wf), "-q"], check=True)
        row = {"seed": seed, **score_seed(root)}
        if args.figure:
            figure(root, args.figure / f"localizability_{args.preset}_{seed}.png")
        rows.append(row)
        print(json.dumps(row))
    summary = {"preset": args.preset, "seeds": args.seeds, "worst_seed": {m: worst(rows, m) for m in ("ekf", "mcl")}}
    print(json.dumps(summary, indent=1))
    if args.json:
        args.json.write_text(json.dumps({"runs": rows, **summary}, indent=1))


if __name__ == "__main__":
    main()
