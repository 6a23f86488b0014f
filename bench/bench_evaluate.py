"""Benchmark of the localizers: EKF epochs/s (ICP excluded), MCL epochs/s at 1000 particles, road-feature
extraction ms/scan, and accuracy on the synthetic road with a 30 s GNSS outage.

    .venv/bin/python -m bench.bench_evaluate [--epochs 1200] [--particles 1000]
"""
from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--epochs", type=int, default=1200)
    ap.add_argument("--particles", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=21)
    ap.add_argument("--figures", default=None, help="write the report's figures as eval_synthetic_*.png here")
    args = ap.parse_args()

    from fixtures.evaluate import ground_ring_scan, paint_markings, synthetic_drive
    from stages.common.road_features import extract_road_features
    from stages.evaluate.localize_ekf import run_ekf
    from stages.evaluate.localize_mcl import run_mcl
    from stages.evaluate.outputs import metrics_document, metrics_table_text
    from stages.evaluate.params import EvaluateParams
    from stages.evaluate.run import evaluate_drive

    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores (shared), "
          f"python {platform.python_version()}")
    rng = np.random.default_rng(args.seed)
    d, cmap, fetch, truth, stamps = synthetic_drive(args.epochs, rng, outage_s=(20.0, 30.0))
    p = EvaluateParams(mcl={"n_particles": args.particles})
    q0, P0 = d.gnss_q[0], np.diag([0.36, 0.36, np.deg2rad(0.5) ** 2])
    n_corners = len(d.corners.epoch)

    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        run_ekf(d.icp_increments, d.corners, cmap, q0, P0, 0, p.ekf)
        best = min(best, time.perf_counter() - t0)
    print(f"EKF: {args.epochs} epochs, {n_corners} extracted corners ({n_corners / args.epochs:.1f}/epoch), "
          f"{len(cmap.en_m)} map corners: {args.epochs / best:.0f} epochs/s (best of 3; target >= 1000)")

    t0 = time.perf_counter()
    run_mcl(d.odo_increments, d.feature_epoch, d.features_vehicle_m, fetch, q0, 0, np.random.default_rng(0),
            p.mcl, likelihood=p.markings)
    dt = time.perf_counter() - t0
    print(f"MCL: {args.particles} particles, <= {p.markings.max_features} features/epoch: "
          f"{args.epochs / dt:.0f} epochs/s (features precomputed; target >= 50)")

    mask, origin = paint_markings(300.0, 40.0, 0.1, road_y_m=20.0, crosswalks_x_m=(150.0,))
    T = np.eye(4)
    T[2, 3] = 1.8
    scans = [ground_ring_scan(np.array([100.0 + 5 * k, 18.0, 0.0]), mask, origin, 0.1, rng, n_rings=32,
                              lowest_deg=-30.0, azimuth_step_deg=0.16) for k in range(10)]
    t0 = time.perf_counter()
    n_feat = [len(extract_road_features(*s, T)) for s in scans]
    dt = (time.perf_counter() - t0) / len(scans)
    print(f"road features: {len(scans[0][0])} ground points/scan (32 rings, 0.16 deg): {1e3 * dt:.1f} ms/scan, "
          f"{np.mean(n_feat):.0f} features/scan")

    t0 = time.perf_counter()
    ev = evaluate_drive(d, cmap, fetch, {"truth": (stamps, truth)}, p)
    print(f"accuracy on the synthetic road ({args.epochs} epochs, 30 s GNSS outage at 20 s; "
          f"{time.perf_counter() - t0:.1f} s):")
    print(metrics_table_text(metrics_document(ev, "synthetic", {})))
    if args.figures:
        save_figures(ev, cmap, args.figures)


def save_figures(ev, cmap, out_dir: str) -> None:
    import base64
    from pathlib import Path

    from stages.evaluate import report

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    figs = {"trajectories": report.figure_trajectories(ev, cmap), "errors": report.figure_errors_over_time(ev),
            "cdf": report.figure_cdf(ev), "corners_per_epoch": report.figure_corners_per_epoch(ev),
            "ellipses": report.figure_ellipses(ev, cmap)}
    for name, b64 in figs.items():
        (out / f"eval_synthetic_{name}.png").write_bytes(base64.b64decode(b64))
        print(f"figure: {out / f'eval_synthetic_{name}.png'}")


if __name__ == "__main__":
    main()
