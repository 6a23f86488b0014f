"""The 22 real KITTI HDL-64E scans of ../shared/data built into a map (as tests/stages/ingest/
test_drive_kitti_realworld.py does): marking pixels on and near the driven path, corners, duplicates, the
markings stage's peak RSS, and a figure of the accumulated markings and corners.

    .venv/bin/python -m bench.bench_kitti_map --work DIR [--figure docs/figures/kitti_0048_map.png]
    .venv/bin/python -m bench.bench_kitti_map --work DIR --params P.yaml   # e.g. markings: {surface_band_m: 0}
    .venv/bin/python -m bench.bench_kitti_map --work DIR --no-rerun --self-evaluate   # + the drive on its own map

DIR receives the drive folder (links to the shared scans) and the output root; it is reused when present.
The markings stage is re-run alone in a child process (``cornermap run --only markings --scheduler sync``
with a fingerprint-changing no-op override, under /usr/bin/time) so its peak RSS is measured on its own.
The map's corners are reported with their stored (map-relative) stds and the manifest's stated frame error.
``--self-evaluate`` localizes the map's own drive on it (``cornermap evaluate --reference map --method ekf``, a
child process; self-consistency: no truth exists for these scans) and adds the EKF's figures.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml
from scipy import ndimage

from bench.roots import latest, read

REPO = Path(__file__).resolve().parents[1]
KITTI = REPO.parent / "shared" / "data" / "kitti_raw_0048_city"
NEAR_PATH_M = 3.0


def build(work: Path) -> tuple[Path, Path]:
    from tests.stages.ingest.test_drive_kitti_realworld import init_check_build, make_drive

    root = work / "root"
    if not (root / "maps").is_dir():
        init_check_build(make_drive(work / "drive" / "k0048", KITTI), root)
    [workflow] = sorted((root / "workflows").glob("*.yaml"))
    return root, workflow


def rerun_markings(root: Path, workflow: Path, params: dict) -> dict:
    """Bring every stage up to date with this code, then run the markings stage alone in a child process under
    /usr/bin/time: its wall time and peak RSS."""
    subprocess.run([sys.executable, "-m", "mapservice", "run", str(workflow), "--root", str(root), "--scheduler",
                    "sync", "-q"], check=False, cwd=REPO,
                   capture_output=True)  # upstream refresh (tiles' gate may refuse)
    markings = dict(params.get("markings") or {})
    markings["pose_buffer_m"] = float(markings.get("pose_buffer_m", 30.0)) + (time.time_ns() % 1000) * 1e-9  # new fp
    override = root.parent / "markings_override.yaml"
    override.write_text(yaml.safe_dump({**params, "markings": markings}))
    run = subprocess.run(["/usr/bin/time", "-f", "peak_kb=%M wall_s=%e", sys.executable, "-m", "mapservice", "run",
                          str(workflow), "--root", str(root), "--only", "markings", "--scheduler", "sync", "-q",
                          "--params", str(override)], cwd=REPO, capture_output=True, text=True)
    if run.returncode != 0:
        raise SystemExit(f"markings re-run failed: {run.stderr.strip().splitlines()[-3:]}")
    stats = dict(kv.split("=") for kv in run.stderr.strip().splitlines()[-1].split())
    return {"markings_wall_s": float(stats["wall_s"]), "markings_peak_rss_mb": round(int(stats["peak_kb"]) / 1024, 1)}


def stitch(root: Path):
    from stages.markings.raster_io import read_tile_rasters

    tiles = [
        read_tile_rasters(p.parent) for p in sorted(latest(root, "marking_rasters").glob("artifacts/*/raster.json"))
    ]
    tiles = [t for t in tiles if t.count.any()]
    cell = tiles[0].cell_m
    west = min(t.origin_east_m for t in tiles)
    south = min(t.origin_north_m for t in tiles)
    east = max(t.origin_east_m + t.count.shape[1] * cell for t in tiles)
    north = max(t.origin_north_m + t.count.shape[0] * cell for t in tiles)
    shape = (int(round((north - south) / cell)), int(round((east - west) / cell)))
    layers = {k: np.zeros(shape, bool) for k in ("marking", "traversable", "occupied")}
    intensity = np.full(shape, np.nan)
    for t in tiles:
        r0 = int(round((north - (t.origin_north_m + t.count.shape[0] * cell)) / cell))
        c0 = int(round((t.origin_east_m - west) / cell))
        sl = (slice(r0, r0 + t.count.shape[0]), slice(c0, c0 + t.count.shape[1]))
        layers["marking"][sl] |= t.marking_mask
        layers["traversable"][sl] |= t.traversable_mask
        layers["occupied"][sl] |= t.count > 0
        intensity[sl] = np.where(t.count > 0, t.intensity, intensity[sl])
    return layers, intensity, (west, east, south, north), cell


def measure(root: Path) -> tuple[dict, dict]:
    from stages.cornermap.merge import count_duplicates

    layers, intensity, extent, cell = stitch(root)
    west, east, south, north = extent
    poses = read(root, "poses_optimized").sort_by("scan_id")
    path = np.column_stack([poses["x_m"].to_numpy(), poses["y_m"].to_numpy()])
    on_path = np.zeros(layers["occupied"].shape, bool)
    dense = np.vstack([np.linspace(a, b, 20) for a, b in zip(path[:-1], path[1:])])
    rows = np.clip(((north - dense[:, 1]) / cell).astype(int), 0, on_path.shape[0] - 1)
    cols = np.clip(((dense[:, 0] - west) / cell).astype(int), 0, on_path.shape[1] - 1)
    on_path[rows, cols] = True
    near = ndimage.distance_transform_edt(~on_path) * cell <= NEAR_PATH_M
    occ = layers["occupied"]
    cmap, rejected = read(root, "corner_map"), read(root, "corner_map_rejected")
    en = np.column_stack([cmap["east_m"].to_numpy(), cmap["north_m"].to_numpy()])
    th = np.column_stack([cmap["theta1_rad"].to_numpy(), cmap["theta2_rad"].to_numpy()])
    std = np.sqrt(np.maximum(cmap["cov_ee_m2"].to_numpy(), cmap["cov_nn_m2"].to_numpy()))
    reasons: dict[str, int] = {}
    for r in rejected["reason"].to_pylist():
        for part in r.split("; "):
            reasons[part.split(":")[0]] = reasons.get(part.split(":")[0], 0) + 1
    obs = read(root, "corners_per_scan")
    out = {
        "scans": poses.num_rows,
        "path_m": round(float(np.sum(np.hypot(*np.diff(path, axis=0).T))), 1),
        "occupied_cells_near_path": int((occ & near).sum()),
        "traversable_share_near_path": round(
            float((layers["traversable"] & near).sum() / max((occ & near).sum(), 1)), 3
        ),
        "marking_px": int(layers["marking"].sum()),
        "marking_px_near_path": int((layers["marking"] & near).sum()),
        "corner_observations": obs.num_rows,
        "map_corners": cmap.num_rows,
        "rejected_clusters": rejected.num_rows,
        "rejected_reasons": reasons,
        "duplicates_1m": count_duplicates(en, th),
        "corner_std_m_median": round(float(np.median(std)), 3) if len(std) else None,
        "corner_std_m": [round(float(v), 3) for v in std],
        "map_frame": frame_summary(root),
    }
    fig = {"layers": layers, "intensity": intensity, "extent": extent, "path": path, "corners": en, "theta": th,
           "rejected": np.column_stack([rejected["east_m"].to_numpy(), rejected["north_m"].to_numpy()])}
    return out, fig


def frame_summary(root: Path) -> dict | None:
    """The newest published version's stated frame error (``map_frame``: stds of shift and rotation, source)."""
    manifests = sorted((root / "maps").glob("*/v*/manifest.json"))
    frame = json.loads(manifests[-1].read_text()).get("map_frame") if manifests else None
    if not frame:
        return None
    return {k: round(frame[k], 4) for k in ("std_east_m", "std_north_m", "std_rotation_deg", "relative_std_m")} \
        | {"source": frame.get("source")}


def self_evaluate(work: Path, root: Path) -> dict:
    """``cornermap evaluate`` of the map's own drive against its own map (reference: its pose-graph poses)."""
    drive = work / "drive" / "k0048" / "drive.yaml"
    out = work / "self_eval"
    run = subprocess.run([sys.executable, "-m", "mapservice", "evaluate", "--root", str(root), "--map", "kitti",
                          "--drive", str(drive), "--reference", "map", "--method", "ekf", "--out", str(out), "-q"],
                         cwd=REPO, capture_output=True, text=True)
    metrics = out / "metrics.json"
    if not metrics.is_file():
        raise SystemExit(f"self-evaluation failed (exit {run.returncode}): {run.stderr.strip().splitlines()[-3:]}")
    ekf = json.loads(metrics.read_text())["methods"]["ekf"]
    judged = ekf.get("map_relative") or ekf.get("map") or {}
    keys = ("rms_2d_m", "p99_2d_m", "max_2d_m", "heading_rms_deg", "longitudinal_rms_m", "nees_mean", "epochs",
            "localized_from_epoch")
    return {"self_eval_exit": run.returncode, "self_eval_ekf": {k: judged.get(k) for k in keys},
            "self_eval_ekf_all_epochs": {k: (judged.get("all_epochs") or {}).get(k) for k in keys[:4]}}


def plot(fig: dict, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    layers, inten = fig["layers"], fig["intensity"]
    lo, hi = np.nanpercentile(inten, [1, 99.5])
    gray = np.clip((np.nan_to_num(inten, nan=lo) - lo) / max(hi - lo, 1e-6), 0, 1)
    rgb = np.dstack([gray * 0.8] * 3) * layers["occupied"][..., None]
    rgb[layers["traversable"] & ~layers["marking"]] *= np.array([0.75, 0.85, 1.0])
    rgb[layers["marking"]] = (1.0, 0.15, 0.1)
    f, ax = plt.subplots(figsize=(10, 8), constrained_layout=True)
    ax.imshow(rgb, extent=fig["extent"], interpolation="nearest")
    ax.plot(*fig["path"].T, "-", color="cyan", lw=1.2, label="driven path (poses_optimized)")
    if len(fig["rejected"]):
        ax.plot(*fig["rejected"].T, "x", color="orange", ms=6, label="rejected corner clusters")
    for (e, n), th in zip(fig["corners"], fig["theta"]):
        for t in th:
            ax.plot([e, e + 2.0 * np.cos(t)], [n, n + 2.0 * np.sin(t)], "-", color="lime", lw=1.5)
    if len(fig["corners"]):
        ax.plot(*fig["corners"].T, "o", color="lime", ms=7, mfc="none", label="map corners (ticks: wall directions)")
    occ = np.argwhere(layers["occupied"])
    west, east, south, north = fig["extent"]
    cell = (east - west) / layers["occupied"].shape[1]
    ax.set_xlim(west + occ[:, 1].min() * cell - 2, west + occ[:, 1].max() * cell + 2)
    ax.set_ylim(north - occ[:, 0].max() * cell - 2, north - occ[:, 0].min() * cell + 2)
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title(title + " - grey: intensity, blue tint: traversable, red: markings")
    ax.legend(loc="lower right", fontsize=8)
    f.savefig(path, dpi=80)
    plt.close(f)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, required=True, help="working folder (drive links + output root)")
    ap.add_argument("--params", type=Path, help="YAML {stage: {param: value}} for the markings re-run")
    ap.add_argument("--figure", type=Path, help="write the map figure (PNG) here")
    ap.add_argument("--no-rerun", action="store_true", help="measure the built map only (no markings re-run)")
    ap.add_argument("--self-evaluate", action="store_true", help="also localize the map's own drive on it (EKF)")
    args = ap.parse_args(argv)
    if not KITTI.is_dir():
        raise SystemExit(f"{KITTI}: the KITTI samples are not there")
    root, workflow = build(args.work.resolve())  # child processes run from the repository
    result = {} if args.no_rerun else rerun_markings(root, workflow, yaml.safe_load(args.params.read_text())
                                                     if args.params else {})
    numbers, fig = measure(root)
    result.update(numbers)
    if args.self_evaluate:
        result.update(self_evaluate(args.work.resolve(), root))
    print(json.dumps(result))
    if args.figure:
        plot(fig, args.figure, f"KITTI 2011_09_26 drive 0048, {numbers['scans']} scans")


if __name__ == "__main__":
    main()
