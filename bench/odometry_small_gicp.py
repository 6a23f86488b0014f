"""The odometry stage with small_gicp's GICP in place of Open3D's, against the simulator's truth (ICP only).

    .venv/bin/python -m pip install small_gicp          # not a dependency of cornermap
    .venv/bin/python -m bench.odometry_small_gicp --sim ~/.cache/cornermap-bench/sim-gangnam-seed1 --scans 1500

Runs ``bench.odometry_engines.odometry_ours`` (the stage's chunks, wheel deskew and guides, gate, span edges) twice:
with ``registration.register_clouds`` (Open3D) and with small_gicp registering the same prepared clouds' points
(small_gicp estimates its own covariances, regularised to planes: its Python API cannot take ours), the information
still our point-to-plane Hessian at the result. Prints per-edge and end errors against the truth, the edges the gate
flags and the time. One thread each (``OMP_NUM_THREADS=1`` and Open3D's bound)."""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def small_gicp_register(source, target, T_init, *, method="gicp", max_corr_m=1.0, max_iterations=30,
                        point_sigma_m=0.05, min_sigma_m=0.005, min_sigma_rad=0.0002, relative_tolerance=1e-6,
                        _cache: dict = {}):  # noqa: B006 - one cache per process: clouds keyed by their id
    """``register_clouds``'s contract on small_gicp: fitness, RMSE and the Hessian from a nearest-neighbour search at
    the result (Open3D gives its correspondences)."""
    import small_gicp as sg

    from stages.common import registration as reg

    def cloud(c):
        if id(c) not in _cache:
            pc = sg.PointCloud(np.asarray(c.points))
            tree = sg.KdTree(pc, num_threads=1)
            sg.estimate_covariances(pc, tree, 20, num_threads=1)
            _cache[id(c)] = (pc, tree, c)  # c kept: its id stays its own
        return _cache[id(c)]

    (src, _, _), (tgt, tree, _) = cloud(source), cloud(target)
    r = sg.align(tgt, src, tree, np.asarray(T_init, float), registration_type="GICP",
                 max_correspondence_distance=max_corr_m, num_threads=1, max_iterations=max_iterations)
    T = np.asarray(r.T_target_source, float)
    moved = np.asarray(source.points) @ T[:3, :3].T + T[:3, 3]
    dist, idx = reg.one_batch_tree(np.asarray(target.points)).query(moved, distance_upper_bound=max_corr_m)
    ok = np.isfinite(dist)
    H = reg.point_to_plane_hessian(source, target, T, max_corr_m, point_sigma_m,
                                   np.column_stack([np.flatnonzero(ok), idx[ok]]))
    fitness = float(ok.mean()) if len(ok) else 0.0
    rmse = float(np.sqrt(np.mean(dist[ok] ** 2))) if ok.any() else float("inf")
    return reg.RegistrationResult(T, fitness, rmse, reg.floor_information(H, min_sigma_m, min_sigma_rad),
                                  fitness > 0, H)


def run(sim: Path, n: int, engine: str) -> str:
    import stages.odometry.core as core
    from bench.odometry_engines import sim_odometry

    if engine == "small_gicp":
        core.register_clouds = small_gicp_register
    out, e, total = sim_odometry(sim, "drive_0", n)
    return (f"| {engine} | {e['edges']} | {e['edge_xy_rms_mm']:.1f} | {e['edge_yaw_rms_deg']:.4f} | "
            f"{e['end_xy_m']:.2f} | {e['end_heading_deg']:.2f} | {out.n_flagged} | {out.seconds:.1f} | {total:.1f} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sim", type=Path, required=True, help="a simulated drive folder (cornermap simulate --out)")
    ap.add_argument("--scans", type=int, default=1500)
    ap.add_argument("--engine", choices=["open3d", "small_gicp"], default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.engine:  # one engine in this process (a fresh interpreter per engine)
        os.environ["OMP_NUM_THREADS"] = "1"
        import open3d as o3d

        o3d.utility.set_max_threads(1)
        print(run(args.sim, args.scans, args.engine))
        return 0
    try:
        import small_gicp  # noqa: F401
    except ImportError:
        print("small_gicp is not installed: .venv/bin/python -m pip install small_gicp", file=sys.stderr)
        return 1
    import subprocess

    print("| engine | edges | edge xy RMS mm | edge yaw RMS deg | end xy m | end heading deg | flagged | "
          "registration s | total s |\n|---|---|---|---|---|---|---|---|---|")
    for engine in ("open3d", "small_gicp"):
        subprocess.run([sys.executable, str(Path(__file__).resolve()), "--sim", str(args.sim), "--scans",
                        str(args.scans), "--engine", engine], check=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
