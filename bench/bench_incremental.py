"""Nightly rebuilds of a growing map: one drive added per night with ``cornermap rebuild --no-gate``.

    .venv/bin/python -m bench.bench_incremental --preset tiny --seed 351 --drives 5 [--full] [--sim DIR] \
        [--json out.json]

Simulates ``--drives`` N drives of one city (or takes them from ``--sim``), makes a map (``maps create``) and adds
drive k on night k (an inbox holding drives 0..k), each night a ``python -m mapservice rebuild`` child process.
``--full`` runs every night with ``rebuild --full`` (the joint re-solve) instead of the incremental default; then
drive N-1 alone is built as a one-drive map (night 1's cost for that drive).

Per night: CPU seconds of the rebuild's whole process tree (the child's and its descendants' user + system time,
``os.wait4``), wall seconds, the pose graph's wall and CPU seconds (the build summary), tiles in the new version,
tiles whose files changed against the parent (new, changed, gone), bytes a localizer downloads (the files whose
sha256 the parent does not hold at that path), and the corners against the truth (``score_corner_map``, absolute:
no frame offset; precision over every map corner within 0.3 m, RMS of the matched pairs). The ratios the issue
asks for: night k's CPU / night 2's, and night N's CPU / drive N-1's one-drive build. CPU seconds depend on the
machine and its load: state ``lscpu`` with the figures.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.bench_rebuild import ORIGIN, deliver, simulated


def rebuild_night(root: Path, inbox: Path, full: bool, params: Path | None = None) -> dict:
    """One ``rebuild`` child process: its CPU seconds are those of the child and every descendant it waited for
    (``RUSAGE_CHILDREN`` before and after)."""
    import resource

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    cmd = [sys.executable, "-m", "mapservice", "rebuild", "--root", str(root), "--map", "city", "--inbox", str(inbox),
           "--no-gate", "--quiet-period-min", "0", "--min-free-gib", "0.5", "--json", "-q"] \
        + (["--full"] if full else []) + (["--params", str(params)] if params else [])
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if res.returncode != 0:
        raise SystemExit(f"rebuild exited {res.returncode}: {res.stderr.strip()[-2000:]}")
    doc = json.loads(res.stdout)
    stages = doc.get("stages") or {}
    return {"cpu_s": round(cpu, 2), "wall_s": round(wall, 2), "version": doc.get("version"),
            "stage_wall_s": {s: round(float(v.get("wall_s", 0.0)), 2) for s, v in stages.items()},
            "stage_cpu_s": {s: round(float(v.get("cpu_s", 0.0)), 2) for s, v in stages.items()}}


def tile_changes(vdir: Path, parent: Path | None) -> dict:
    """Tiles of ``vdir`` whose files differ from ``parent``'s (by path and sha256), and the bytes to download."""
    man = json.loads((vdir / "manifest.json").read_text())
    old = json.loads((parent / "manifest.json").read_text()) if parent is not None else {"tiles": [], "files": {}}
    old_tiles = {(t["i"], t["j"]): t["files"] for t in old["tiles"]}
    new_tiles = {(t["i"], t["j"]): t["files"] for t in man["tiles"]}
    changed = [k for k, f in new_tiles.items() if k in old_tiles and f != old_tiles[k]]
    added = [k for k in new_tiles if k not in old_tiles]
    gone = [k for k in old_tiles if k not in new_tiles]
    tile_bytes = sum(rec["bytes"] for path, rec in man["files"].items() if path.startswith("tiles/"))
    download = sum(rec["bytes"] for path, rec in man["files"].items()
                   if old["files"].get(path, {}).get("sha256") != rec["sha256"])
    download_tiles = sum(rec["bytes"] for path, rec in man["files"].items() if path.startswith("tiles/")
                         and old["files"].get(path, {}).get("sha256") != rec["sha256"])
    return {"n_tiles": len(new_tiles), "tiles_changed": len(changed), "tiles_added": len(added),
            "tiles_gone": len(gone), "tiles_unchanged": len(new_tiles) - len(changed) - len(added),
            "tile_bytes": tile_bytes, "download_bytes": download, "download_tile_bytes": download_tiles}


def corner_accuracy(vdir: Path, sim: Path) -> dict:
    """The version's corners against the simulator's truth, absolute (no frame offset). ``precision``: the share of
    map corners that are a truth corner (``bench_corner_vertex.label_corners``: within 0.3 m of a building corner's
    wall intersection or chamfer vertex, on a rounded corner's arc, or within 0.5 m of a street-furniture corner);
    ``rms_m``: the building corners' distance to the nearest such truth point. ``precision_sharp`` / ``rms_sharp_m``:
    ``score_corner_map`` against the wall intersections alone (stricter: a chamfer vertex counts false)."""
    from bench.bench_corner_vertex import label_corners, truth_sets
    from mapformat.loader import open_map
    from stages.cornermap.metrics import score_corner_map

    t = open_map(vdir).all_corners()
    en = np.column_stack([t["east_m"].to_numpy(), t["north_m"].to_numpy()])
    th = np.column_stack([t["theta1_rad"].to_numpy(), t["theta2_rad"].to_numpy()])
    building, rounded, radius, furniture = truth_sets(sim)
    labels = label_corners(en, building, rounded, radius, furniture)
    b = en[labels == "building"]
    dist = np.linalg.norm(b[:, None] - building[None], axis=2).min(axis=1) if len(b) else np.zeros(0)
    truth = np.loadtxt(sim / "truth" / "corners.csv", delimiter=",", skiprows=1, usecols=(1, 2, 3, 4)).reshape(-1, 4)
    s = score_corner_map(en, th, truth[:, :2], np.radians(truth[:, 2:4]), np.ones(len(truth), bool))
    return {"n_corners": len(en), "precision": round(float(np.mean(labels != "other")), 4) if len(en) else None,
            "rms_m": round(float(np.sqrt(np.mean(dist ** 2))), 4) if len(dist) else None,
            "labels": {k: int(np.sum(labels == k)) for k in ("building", "rounded", "furniture", "other")},
            "precision_sharp": round(s["precision"], 4), "rms_sharp_m": round(s["rms_pos_m"], 4),
            "ids": t["corner_id"].to_numpy().tolist(), "en": en.tolist()}


def ids_kept(prev: dict, cur: dict, radius_m: float = 0.05) -> dict:
    """Of the parent's corners, how many the new version holds within ``radius_m`` under the same id."""
    from scipy.spatial import cKDTree

    if not prev["en"] or not cur["en"]:
        return {"kept_same_id": 0, "of": len(prev["en"])}
    d, k = cKDTree(np.asarray(cur["en"])).query(np.asarray(prev["en"]), distance_upper_bound=radius_m)
    ok = d < radius_m
    same = np.asarray(cur["ids"])[k[ok]] == np.asarray(prev["ids"])[ok]
    return {"kept_same_id": int(same.sum()), "near": int(ok.sum()), "of": len(prev["en"])}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--seed", type=int, default=351)
    ap.add_argument("--drives", type=int, default=5, help="N nights, one drive each")
    ap.add_argument("--sim", type=Path, help="simulated drives to reuse (drive_0 .. drive_{N-1})")
    ap.add_argument("--work", type=Path, help="work folder (default: a temporary one, deleted)")
    ap.add_argument("--full", action="store_true", help="every night `rebuild --full` (joint re-solve)")
    ap.add_argument("--no-single", action="store_true", help="skip the one-drive build of the last drive")
    ap.add_argument("--min-corners-per-km", type=float, help="the tiles quality gate's corner density (default: the "
                    "stage's); tiny maps of 5+ laps of one short loop fall under it (corners over summed laps)")
    ap.add_argument("--joint", action="store_true", help="also build every drive in one night on a fresh map (the "
                    "joint solve of the same drives) and score its corners: the incremental map's reference")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    from mapservice.maps import create_map

    work = a.work or Path(tempfile.mkdtemp(prefix="bench-incremental-"))
    try:
        sim = simulated(a.sim, work, a.preset, a.seed, a.drives)
        root, inbox = work / "root", work / "inbox"
        params = None
        if a.min_corners_per_km is not None:
            params = work / "params.json"
            params.write_text(json.dumps({"tiles": {"min_corners_per_km": a.min_corners_per_km}}))
        create_map(root, "city", ORIGIN)
        nights, prev_acc = [], None
        for k in range(a.drives):
            deliver(sim, [f"drive_{k}"], inbox, ready=True)
            night = rebuild_night(root, inbox, a.full, params)
            vdir = root / "maps" / "city" / night["version"]
            parent = root / "maps" / "city" / f"v{int(night['version'][1:]) - 1:04d}" if k else None
            night["tiles"] = tile_changes(vdir, parent)
            acc = corner_accuracy(vdir, sim)
            if prev_acc is not None:
                night["corner_ids"] = ids_kept(prev_acc, acc)
            night["corners"] = {key: v for key, v in acc.items() if key not in ("ids", "en")}
            night["drift"] = drift_summary(root / "maps" / "city")
            prev_acc = acc
            night["night"], night["drives"] = k + 1, k + 1
            nights.append(night)
            print(json.dumps({key: night[key] for key in ("night", "cpu_s", "wall_s", "stage_cpu_s", "tiles",
                                                          "corners", "drift")}), flush=True)
        sim_doc = json.loads((sim / "simulation.json").read_text()) if (sim / "simulation.json").is_file() else {}
        out = {"preset": sim_doc.get("preset", a.preset), "seed": sim_doc.get("seed", a.seed), "drives": a.drives,
               "mode": "full" if a.full else "incremental",
               "machine": _machine(), "nights": nights}
        if not a.no_single:
            last = f"drive_{a.drives - 1}"
            root1, inbox1 = work / "root1", work / "inbox1"
            create_map(root1, "city", ORIGIN)
            deliver(sim, [last], inbox1, ready=True)
            out["one_drive_build"] = rebuild_night(root1, inbox1, False, params)
        if a.joint:
            rootj, inboxj = work / "rootj", work / "inboxj"
            create_map(rootj, "city", ORIGIN)
            deliver(sim, [f"drive_{k}" for k in range(a.drives)], inboxj, ready=True)
            joint = rebuild_night(rootj, inboxj, False, params)
            acc = corner_accuracy(rootj / "maps" / "city" / joint["version"], sim)
            joint["corners"] = {key: v for key, v in acc.items() if key not in ("ids", "en")}
            out["joint_build"] = joint
            print(json.dumps({"joint_corners": joint["corners"]}), flush=True)
        if len(nights) >= 2:
            out["ratio_last_over_night2"] = round(nights[-1]["cpu_s"] / nights[1]["cpu_s"], 3)
        if "one_drive_build" in out:
            out["ratio_last_over_one_drive"] = round(nights[-1]["cpu_s"] / out["one_drive_build"]["cpu_s"], 3)
        print(json.dumps({k: out[k] for k in out if k.startswith("ratio")}))
        if a.json:
            a.json.write_text(json.dumps(out, indent=1))
        return out
    finally:
        if a.work is None:
            shutil.rmtree(work, ignore_errors=True)


def drift_summary(mdir: Path) -> dict | None:
    """LATEST's drift statistic (``maps show``'s): the frame test of the window and the largest region's share of
    its threshold."""
    from mapservice.maps_show import latest_drift

    d = latest_drift(mdir)
    if not d:
        return None
    rows = [r for r in d.get("regions", []) if r.get("loops")]
    f = d.get("frame") or {}
    return {"region_share_max": round(max((r["chi2"] / r["threshold"] for r in rows), default=0.0), 3),
            "frame_chi2": f.get("chi2"), "frame_threshold": f.get("threshold"), "frame_dof": f.get("dof"),
            "window_poses": f.get("window_poses"), "held_poses": f.get("held_poses"),
            "anchor_moved_m": f.get("anchor_moved_m"), "prior_std_en_m": f.get("prior_std_en_m"),
            "posterior_std_en_m": f.get("posterior_std_en_m"), "advised": d.get("advised"),
            "quantile": d.get("quantile"), "scale": d.get("scale"),
            "regions": [{k: r.get(k) for k in ("region", "loops", "chi2", "dof", "threshold")} for r in rows]}


def region_nights(path: Path) -> list[dict]:
    """Every (night, region with loops) of a bench JSON: the seed, night, loops k, T, dof = 6 k and the number m of
    regions with loops that night."""
    doc = json.loads(Path(path).read_text())
    out = []
    for n in doc["nights"]:
        regions = [r for r in ((n.get("drift") or {}).get("regions") or []) if r.get("loops")]
        out += [{"seed": doc["seed"], "night": n["night"], "loops": r["loops"], "chi2": r["chi2"], "dof": r["dof"],
                 "m": len(regions)} for r in regions]
    return out


def drift_threshold(argv: list[str] | None = None) -> dict:
    """``python -m bench.bench_incremental drift-threshold --calibration A.json ... --validation B.json ...``: the
    drift trigger's scale from the calibration seeds' nights, and its false alarms on the validation seeds'.

    Test (``stages/posegraph/drift.py``): under a map that agrees with the new drives' loops, a region's T is
    ``s x chi2(6 k)``, ``s`` the loops' variance factor (ICP's information is optimistic by it); a night is one
    test per region its loops reach (m of them), at a family-wise level ``alpha`` (Bonferroni: each at alpha / m):
    threshold ``s x chi2.ppf(1 - alpha / m, 6 k)``. ``s`` from calibration: each clean region-night's one-sided
    ``conf`` upper confidence bound of its variance factor, ``T / chi2.ppf(1 - conf, 6 k)``; the scale is the
    largest of them, rounded up to 0.1. Every night of these benches is clean (its map as close to the truth as the
    joint solve), so every flag is a false alarm."""
    from scipy.stats import chi2

    ap = argparse.ArgumentParser(prog="bench.bench_incremental drift-threshold")
    ap.add_argument("--calibration", type=Path, nargs="+", required=True)
    ap.add_argument("--validation", type=Path, nargs="*", default=[])
    ap.add_argument("--alpha", type=float, default=0.001, help="false-alarm rate of a night (all its regions)")
    ap.add_argument("--conf", type=float, default=0.99, help="confidence of each calibration night's bound")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    cal = [r for f in a.calibration for r in region_nights(f)]
    val = [r for f in a.validation for r in region_nights(f)]
    for r in cal + val:
        r["variance_factor"] = round(r["chi2"] / r["dof"], 3)
        r["upper_bound"] = round(r["chi2"] / chi2.ppf(1.0 - a.conf, r["dof"]), 3)
    scale = float(np.ceil(10.0 * max(r["upper_bound"] for r in cal)) / 10.0)

    def share(r: dict, s: float, bonferroni: bool) -> float:
        q = 1.0 - (a.alpha / r["m"] if bonferroni else a.alpha)
        return round(r["chi2"] / (s * chi2.ppf(q, r["dof"])), 3)

    for r in cal + val:
        r["share_old"] = share(r, 1.0, False)  # DRIFT_SCALE 1.0, chi2.ppf(0.999, 6 k) per region
        r["share_new"] = share(r, scale, True)
    out = {"alpha": a.alpha, "conf": a.conf, "scale": scale, "calibration": cal, "validation": val}
    for name, rows in (("calibration", cal), ("validation", val)):
        nights = {(r["seed"], r["night"]) for r in rows}
        out[f"{name}_nights"] = len(nights)
        out[f"{name}_false_alarms_old"] = sorted({(r["seed"], r["night"]) for r in rows if r["share_old"] > 1})
        out[f"{name}_false_alarms_new"] = sorted({(r["seed"], r["night"]) for r in rows if r["share_new"] > 1})
    print("| set | seed | night | regions | loops | T | dof | T/dof | share, old | share, new |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, rows in (("calibration", cal), ("validation", val)):
        for r in rows:
            print(f"| {name} | {r['seed']} | {r['night']} | {r['m']} | {r['loops']} | {r['chi2']:.1f} | {r['dof']} | "
                  f"{r['variance_factor']:.2f} | {r['share_old']:.2f} | {r['share_new']:.2f} |")
    print(json.dumps({k: v for k, v in out.items() if k not in ("calibration", "validation")}))
    if a.json:
        a.json.write_text(json.dumps(out, indent=1))
    return out


def _machine() -> dict:
    model = ""
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
        model = next((ln.split(":", 1)[1].strip() for ln in out.splitlines() if ln.startswith("Model name")), "")
    except OSError:
        pass
    return {"cpu": model, "cores": os.cpu_count(), "load_1min": os.getloadavg()[0]}


if __name__ == "__main__":
    if sys.argv[1:2] == ["drift-threshold"]:
        drift_threshold(sys.argv[2:])
    else:
        main()
