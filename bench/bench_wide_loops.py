"""The two passes of an out-and-back street in a GNSS-free keyframe drive, before and after the wide loop search
(stages/posegraph/loops/wide.py), against the simulator's truth.

    .venv/bin/python -m bench.bench_wide_loops --work DIR --seeds 631 632 [--variants fixed wide] [--walk-deg 3]

Per seed: ``cornermap simulate --preset demo --drives 1 --set route=out_and_back --set gnss=0 --set prior=local
--set keyframe_spacing_m=6 --set sensor=os1-64 --set survey=0 --set prior_heading_walk_deg=W --set prior_std_m=10
--set prior_std_deg=2 --set prior_tau_s=300`` (one drive 440 m along the middle street of the demo city, a U-turn, and
back in the other direction's lane, ~145 Ouster keyframes 3-9 m apart, placed by a start pose and a SLAM-like local
prior whose heading random-walks W deg per sqrt(km), stated as 7 m / 2 deg; the drive file's wheel odometry removed:
a keyframe dataset has none), then ``cornermap build`` per variant into one root (the stages before the pose graph are
built once): ``fixed`` with ``loops.wide.enabled: false`` (the fixed loops.radius_m alone), ``wide`` with the defaults.

Measured on the pose graph's committed poses: for each pose, the truly nearest pose of the other pass (30 s or more
apart, within 15 m in truth): the estimate's offset between the two against the truth's ("passes' error": median and
max), and the estimated distance between them beside the truth's; the loop closures found (candidates), accepted, and
wrong (accepted with a relative pose more than 1 m or 2 deg from the truth's). Child processes run from DIR.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

SIM_ORIGIN = "37.4979,127.0276,57.0"


def cornermap(args: list[str], cwd: Path, allow: tuple[int, ...] = ()) -> None:
    run = subprocess.run([sys.executable, "-m", "mapservice", *args], cwd=cwd, capture_output=True, text=True)
    if run.returncode != 0 and run.returncode not in allow:
        raise SystemExit(f"cornermap {' '.join(args[:3])} failed (exit {run.returncode}): {run.stderr.strip()}")


def simulate(work: Path, seed: int, walk_deg: float, spacing_m: float, std_m: float, std_deg: float) -> Path:
    sim = work / f"sim{seed}"
    if not (sim / "drive_0" / "drive.yaml").exists():
        sets = ["route=out_and_back", "gnss=0", "prior=local", f"keyframe_spacing_m={spacing_m}", "sensor=os1-64",
                "survey=0", f"prior_heading_walk_deg={walk_deg}", f"prior_std_m={std_m}", f"prior_std_deg={std_deg}",
                "prior_tau_s=300"]
        cornermap(["simulate", "--preset", "demo", "--seed", str(seed), "--drives", "1", "--out", str(sim), "-q",
                   *sum((["--set", s] for s in sets), [])], work)
        path = sim / "drive_0" / "drive.yaml"
        path.write_text("".join(ln for ln in path.read_text().splitlines(True) if not ln.startswith("odometry:")))
    return sim


def passes(est: np.ndarray, truth: np.ndarray, stamps_s: np.ndarray, min_dt_s: float = 30.0,
           max_true_m: float = 15.0) -> dict:
    """The passes' error (module docstring) over poses whose truly nearest other-pass pose is within ``max_true_m``."""
    p_t, p_e = truth[:, :2, 3], est[:, :2, 3]
    d = np.linalg.norm(p_t[:, None] - p_t[None], axis=2)
    d[np.abs(stamps_s[:, None] - stamps_s[None]) < min_dt_s] = np.inf
    nn = np.argmin(d, axis=1)
    ok = d[np.arange(len(d)), nn] < max_true_m
    k, n = np.flatnonzero(ok), nn[ok]
    err = np.linalg.norm((p_e[n] - p_e[k]) - (p_t[n] - p_t[k]), axis=1)
    return {"pairs": int(ok.sum()), "passes_err_median_m": round(float(np.median(err)), 2),
            "passes_err_max_m": round(float(err.max()), 2),
            "passes_dist_est_max_m": round(float(np.linalg.norm(p_e[n] - p_e[k], axis=1).max()), 2),
            "passes_dist_true_max_m": round(float(np.linalg.norm(p_t[n] - p_t[k], axis=1).max()), 2)}


def loops(root: Path, truth: np.ndarray, scan_ids: np.ndarray) -> dict:
    from bench.roots import read

    t = read(root, "loop_closures").to_pylist()
    index = {int(s): k for k, s in enumerate(scan_ids)}
    wrong = 0
    for r in t:
        if not r["accepted"]:
            continue
        a, b = truth[index[r["scan_a"]]], truth[index[r["scan_b"]]]
        rel = np.linalg.inv(a) @ b
        dyaw = np.arctan2(rel[1, 0], rel[0, 0]) - r["dyaw_rad"]
        dyaw = (dyaw + np.pi) % (2 * np.pi) - np.pi
        if np.hypot(rel[0, 3] - r["dx_m"], rel[1, 3] - r["dy_m"]) > 1.0 or abs(np.degrees(dyaw)) > 2.0:
            wrong += 1
    wide = [r for r in t if "wide" in r["reason"] or r["prior_distance_m"] > 12.0]
    return {"loops_candidates": len(t), "loops_accepted": sum(r["accepted"] for r in t), "loops_wrong": wrong,
            "wide_candidates": len(wide), "wide_accepted": sum(r["accepted"] for r in wide),
            "pcm_rejected": sum("pairwise consistency" in r["reason"] for r in t)}


def measure(root: Path, sim: Path) -> dict:
    from bench.bench_map_frame import committed
    from bench.bench_posegraph import truth_poses
    from bench.roots import read

    m = committed(root)
    truth = truth_poses(sim, m.names[0], m.stamps_ns)
    scan_ids = np.sort(read(root, "poses_optimized")["scan_id"].to_numpy())
    odo = read(root, "poses_odometry").sort_by("scan_id")
    from stages.common.records import Trajectory

    dead = {f"odometry_{k}": v for k, v in passes(Trajectory.from_table(odo, m.names[0]).T, truth,
                                                   m.stamps_ns * 1e-9).items() if k.startswith("passes_err")}
    edges = read(root, "odometry_edges")
    return {**passes(m.est, truth, m.stamps_ns * 1e-9), **loops(root, truth, scan_ids), **dead,
            "edges_rejected": edges.num_rows - sum(edges["accepted"].to_pylist())}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--seeds", type=int, nargs="+", required=True)
    ap.add_argument("--variants", nargs="+", default=["fixed", "wide"], choices=["fixed", "wide"])
    ap.add_argument("--walk-deg", type=float, default=3.0)
    ap.add_argument("--spacing-m", type=float, default=6.0)
    ap.add_argument("--prior-std-m", type=float, default=10.0)
    ap.add_argument("--prior-std-deg", type=float, default=2.0)
    args = ap.parse_args(argv)
    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    for seed in args.seeds:
        sim = simulate(work, seed, args.walk_deg, args.spacing_m, args.prior_std_m, args.prior_std_deg)
        for variant in args.variants:
            params = work / f"params_{variant}.yaml"
            params.write_text("posegraph:\n  loops: {wide: {enabled: false}}\n" if variant == "fixed"
                              else "posegraph: {}\n")
            root = work / f"root{seed}"
            t0 = time.perf_counter()
            cornermap(["build", "--drive", str(sim / "drive_0" / "drive.yaml"), "--map", "m", "--root", str(root),
                       "--origin", SIM_ORIGIN, "--workers", "1", "-q", "--params", str(params)], work, allow=(3,))
            row = {"seed": seed, "variant": variant, **measure(root, sim),
                   "build_s": round(time.perf_counter() - t0, 1)}
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
