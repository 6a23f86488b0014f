"""Delta bundle sizes: the bytes a vehicle downloads to go from one version to the next, against the whole version.

    .venv/bin/python -m bench.bench_bundle --preset tiny --seeds 321 --root runs/loc

Per seed, in ``bench_localizability``'s root (``simulate --drives 3 --changes``): map ``grow`` gets v1 from drive 0
and v2 from drives 0 + 1 (a rebuild adding a drive of the same city), built fresh with ``cornermap build``; the
bundle v1 -> v2 (``cornermap tiles bundle``) is measured per kind of file, and applied to a copy of v1 whose files
are then compared with v2's (sha256). A rebuild re-runs the pose graph over all drives, so every pose, corner and
raster moves a little: only files whose bytes stay the same stay home.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ORIGIN = "37.4979,127.0276,57"


def _kind(rel: str) -> str:
    name = rel.rsplit("/", 1)[-1]
    return "trajectories" if rel.startswith("trajectories/") else name


def measure(root: Path) -> dict:
    from mapformat.bundle import apply_bundle, make_bundle
    from pipeline.versioned import write_latest

    mdir = root / "maps" / "grow"
    work = Path(tempfile.mkdtemp(prefix="bench-bundle-"))
    try:
        doc = make_bundle(mdir, 1, 2, work / "delta")
        car = work / "car"
        car.mkdir()
        shutil.copytree(mdir / "v0001", car / "v0001")
        write_latest(car, 1)
        apply_bundle(work / "delta", car)
        same = all(hashlib.sha256((car / "v0002" / e["path"]).read_bytes()).hexdigest() == e["sha256"]
                   for e in doc["files"])
    finally:
        shutil.rmtree(work, ignore_errors=True)
    kinds: dict[str, dict[str, int]] = {}
    for e in doc["files"]:
        k = kinds.setdefault(_kind(e["path"]), {"files": 0, "carried": 0, "bytes": 0, "carried_bytes": 0})
        k["files"] += 1
        k["bytes"] += e["bytes"]
        if e["source"] == "bundle":
            k["carried"] += 1
            k["carried_bytes"] += e["bytes"]
    return {"bundle_bytes": doc["bytes"]["bundle"], "target_bytes": doc["bytes"]["target"],
            "share": round(doc["bytes"]["bundle"] / doc["bytes"]["target"], 4), "applied_identical": same,
            "kinds": kinds}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--seeds", type=int, nargs="+", required=True)
    ap.add_argument("--root", type=Path, default=Path("runs/bench_localizability"))
    args = ap.parse_args()
    os.environ.setdefault("PYTHONPATH", str(Path(__file__).resolve().parents[1]))
    from bench.roots import simulator_dir

    for seed in args.seeds:
        root = (args.root / f"{args.preset}-{seed}").resolve()
        sim = simulator_dir(root)
        shutil.rmtree(root / "maps" / "grow", ignore_errors=True)
        for drives in (["drive_0"], ["drive_0", "drive_1"]):
            subprocess.run([sys.executable, "-m", "mapservice", "build", "--map", "grow", "--root", str(root),
                            "--origin", ORIGIN, "-q"]
                           + [a for d in drives for a in ("--drive", str(sim / d / "drive.yaml"))],
                           check=True)
        print(json.dumps({"seed": seed, **measure(root)}))


if __name__ == "__main__":
    main()
