"""The odometry's guided registrations: start (raw wheel guide or corrected by the previous pair) and convergence
tolerance, against the simulator's truth (ICP only, no GNSS/INS).

    .venv/bin/python -m bench.bench_odometry_guess --sim ~/.cache/cornermap-bench/sim-gangnam-seed2 --scans 1000

Runs ``bench.odometry_engines.odometry_ours`` (the stage's chunks, wheel deskew and guides, gate, span edges) once
per row, each in a fresh interpreter on one thread (``OMP_NUM_THREADS=1`` and Open3D's bound): ``guided_relative_
tolerance`` over ``--tolerances``, from the corrected guide (the stage's ``register_pairs``) and, with ``--raw``, from
the raw wheel guide (``core.guide_correction`` replaced by one that never corrects). Prints per-edge errors and the
chain's end error against the truth, the edges the gate flags, the registrations' mean GICP iterations (each guided
registration run again with 1, 2, ... iterations until it returns the same transform; not timed) and the odometry's
time. Open3D stops when fitness and inlier RMSE change less than the tolerance between iterations; a loose tolerance
stops while the estimate still creeps towards the optimum, so its start's error shows in the chain's heading."""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _iterations(register, sample: list) -> float:
    """Mean iterations of the sampled registrations: the fewest ``max_iterations`` that give the same transform."""
    counts = []
    for src, tgt, T, kw in sample:
        full = register(src, tgt, T, **kw).T_target_source
        for k in range(1, kw["max_iterations"] + 1):
            if np.array_equal(register(src, tgt, T, **{**kw, "max_iterations": k}).T_target_source, full):
                break
        counts.append(k)
    return float(np.mean(counts)) if counts else float("nan")


def run(sim: Path, drive: str, n: int, tolerance: float, raw: bool) -> str:
    import stages.odometry.core as core
    from bench.odometry_engines import sim_odometry

    if raw:
        core.guide_correction = lambda *a, **k: None
    register, sample, calls = core.register_clouds, [], [0]

    def recorded(src, tgt, T, **kw):  # every 10th registration kept for the iteration count
        calls[0] += 1
        if calls[0] % 10 == 0:
            sample.append((src, tgt, np.array(T, float), kw))
        return register(src, tgt, T, **kw)
    core.register_clouds = recorded
    out, e, total = sim_odometry(sim, drive, n, **{"icp.guided_relative_tolerance": tolerance})
    iters = _iterations(register, sample[:150])
    return (f"| {sim.name} | {'raw' if raw else 'corrected'} | {tolerance:g} | {e['edges']} | "
            f"{e['edge_xy_rms_mm']:.2f} | {e['edge_yaw_rms_deg']:.4f} | {e['end_xy_m']:.3f} | "
            f"{e['end_heading_deg']:.3f} | {out.n_flagged} | {iters:.2f} | {out.seconds:.1f} | {total:.1f} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sim", type=Path, required=True, help="a simulated drive folder (cornermap simulate --out)")
    ap.add_argument("--drive", default="drive_0")
    ap.add_argument("--scans", type=int, default=1000)
    ap.add_argument("--tolerances", type=float, nargs="+", default=[1e-4, 1e-3, 3e-3])
    ap.add_argument("--raw", action="store_true", help="also each tolerance from the raw wheel guide")
    ap.add_argument("--one", nargs=2, default=None, help=argparse.SUPPRESS)  # tolerance, raw|corrected
    args = ap.parse_args()
    if not (args.sim / "truth").is_dir():
        print(f"bench_odometry_guess: {args.sim} is not a simulated drive folder (no truth/); hint: cornermap "
              "simulate --out DIR", file=sys.stderr)
        return 1
    if args.one:  # one row in this process
        import open3d as o3d

        o3d.utility.set_max_threads(1)
        print(run(args.sim, args.drive, args.scans, float(args.one[0]), args.one[1] == "raw"), flush=True)
        return 0
    print("| sim | start | tolerance | edges | edge xy RMS mm | edge yaw RMS deg | end xy m | end heading deg | "
          "flagged | GICP iterations | odometry s | total s |\n|---|---|---|---|---|---|---|---|---|---|---|---|",
          flush=True)
    for raw in ([False, True] if args.raw else [False]):
        for tol in args.tolerances:
            subprocess.run([sys.executable, str(Path(__file__).resolve()), "--sim", str(args.sim), "--drive",
                            args.drive, "--scans", str(args.scans), "--one", repr(tol),
                            "raw" if raw else "corrected"], check=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
