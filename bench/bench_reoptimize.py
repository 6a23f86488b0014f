"""``cornermap maps reoptimize`` of a map grown by nightly incremental rebuilds: accuracy against the joint solve, and
its cost on 1 and 2 dask workers.

    .venv/bin/python -m bench.bench_incremental --preset tiny --seed 381 --drives 5 --no-single --work W
    .venv/bin/python -m bench.bench_reoptimize --work W [--workers 1 2] [--region-max-poses 600] [--json out.json]

``W`` holds ``root`` (map ``city`` after the nights) and ``sim`` (the drives and their truth). Each measurement runs on
its own copy of the root (so that no run reuses another's committed pose graph): ``maps reoptimize --no-gate
--scheduler distributed --workers K`` (a local dask cluster of K one-thread workers) in a child process (CPU = user
+ system seconds of the child and every process it waited for; peak RSS = the largest of them, ``RUSAGE_CHILDREN``),
then ``--region-max-poses 0`` (one joint graph: the solve of ``rebuild --full``) as the reference. Per run: CPU s,
wall s, peak MB, the pose graph stage's wall / CPU s, the region solve's figures (regions, separator poses, rounds)
and the corners against the truth (``corner_accuracy``: absolute, precision and RMS m); the region solve's poses
against the joint's (mm, RMS and max over every pose) and the incremental map's (LATEST before) corners. CPU and
wall depend on the machine and its load: state both.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from bench.bench_incremental import _machine, corner_accuracy


def reoptimize_run(root: Path, workers: int, region_max_poses: int, params: Path | None = None) -> dict:
    """One ``maps reoptimize`` child process (``--params``: a params file, e.g. the nights' own)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    cmd = [sys.executable, "-m", "mapservice", "maps", "reoptimize", "--root", str(root), "--map", "city", "--no-gate",
           "--min-free-gib", "0.5", "--scheduler", "distributed", "--workers", str(workers),
           "--region-max-poses", str(region_max_poses), "--json", "-q"] + (["--params", str(params)] if params else [])
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if res.returncode != 0:
        raise SystemExit(f"reoptimize exited {res.returncode}: {res.stderr.strip()[-2000:]}")
    doc = json.loads(res.stdout)
    stages = doc.get("stages") or {}
    pg = stages.get("posegraph") or {}
    return {"workers": workers, "region_max_poses": region_max_poses, "version": doc.get("version"),
            "cpu_s": round((after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), 2),
            "wall_s": round(wall, 2), "peak_rss_mb": round(after.ru_maxrss / 1024.0, 1),
            "posegraph_wall_s": round(float(pg.get("wall_s", 0.0)), 2),
            "posegraph_cpu_s": round(float(pg.get("cpu_s", 0.0)), 2)}


def version_poses(root: Path, vdir: Path) -> dict[str, np.ndarray]:
    """drive -> (N,2) east/north of the poses_optimized rows the version was published from."""
    import pyarrow.dataset as pads

    from pipeline.store import dataset_dir, read_manifest
    from schemas.registry import schema_of

    fp = json.loads((vdir / "manifest.json").read_text())["inputs"]["poses"]["fingerprint"]
    ddir = dataset_dir(root, "poses_optimized", fp)
    files = [str(ddir / f["path"]) for f in read_manifest(ddir)["files"]]
    t = pads.dataset(files, schema=schema_of("poses_optimized"), format="parquet").to_table()
    t = t.sort_by([("drive", "ascending"), ("scan_id", "ascending")])
    drives = t["drive"].to_numpy(zero_copy_only=False)
    xy = np.column_stack([t["x_m"].to_numpy(), t["y_m"].to_numpy()])
    return {d: xy[drives == d] for d in sorted(set(drives))}


def region_figures(root: Path, vdir: Path) -> dict:
    """The region solve's figures the posegraph stage wrote into its dataset's metadata (``region_solve``)."""
    from pipeline.store import dataset_dir, read_manifest

    fp = json.loads((vdir / "manifest.json").read_text())["inputs"]["poses"]["fingerprint"]
    m = read_manifest(dataset_dir(root, "poses_optimized", fp)) or {}
    return (m.get("extra") or {}).get("region_solve") or {}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True, help="a bench_incremental --work folder (root, sim)")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--region-max-poses", type=int, default=600)
    ap.add_argument("--no-joint", action="store_true", help="skip the joint reference run")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    base, sim = a.work / "root", a.work / "sim"
    mbase = base / "maps" / "city"
    from pipeline.versioned import read_latest, version_name

    latest = version_name(read_latest(mbase))
    out = {"machine": _machine(), "work": str(a.work), "incremental_version": latest,
           "incremental": {k: v for k, v in corner_accuracy(mbase / latest, sim).items() if k not in ("ids", "en")},
           "runs": []}
    runs = [(w, a.region_max_poses) for w in a.workers] + ([] if a.no_joint else [(2, 0)])
    poses = {}
    for w, m in runs:
        root = a.work / f"reopt-w{w}-m{m}"
        shutil.rmtree(root, ignore_errors=True)
        shutil.copytree(base, root, symlinks=True)
        try:
            run = reoptimize_run(root, w, m)
            vdir = root / "maps" / "city" / run["version"]
            run["corners"] = {k: v for k, v in corner_accuracy(vdir, sim).items() if k not in ("ids", "en")}
            run["regions"] = region_figures(root, vdir)
            poses[(w, m)] = version_poses(root, vdir)
        finally:
            shutil.rmtree(root, ignore_errors=True)
        out["runs"].append(run)
        print(json.dumps(run), flush=True)
    if not a.no_joint:
        joint = poses[(2, 0)]
        for (w, m), p in poses.items():
            if m == 0:
                continue
            d = np.concatenate([np.linalg.norm(p[k] - joint[k], axis=1) for k in joint])
            rms_mm, max_mm = float(np.sqrt(np.mean(d ** 2))) * 1e3, float(d.max()) * 1e3
            out.setdefault("poses_vs_joint_mm", {})[f"workers {w}"] = {"rms": round(rms_mm, 3),
                                                                       "max": round(max_mm, 3)}
    print(json.dumps({k: out[k] for k in ("incremental", "poses_vs_joint_mm") if k in out}), flush=True)
    if a.json:
        a.json.write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    main()
