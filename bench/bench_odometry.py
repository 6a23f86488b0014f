"""Odometry bench: our scan-to-scan odometry against kiss-icp (and against ground truth where there is one).

    .venv/bin/python -m bench.bench_odometry --kitti ../shared/data/kitti_raw_0048_city
    .venv/bin/cornermap simulate --preset tiny --seed 7 --out runs/bench_odo/tiny --drives 1
    .venv/bin/python -m bench.bench_odometry --sim runs/bench_odo/tiny --drive drive_0 --scans 250

Mode --kitti: the 22 real HDL-64E scans (no per-point time, no poses): both trajectories, their per-step
difference and the largest position difference after chaining. Mode --sim: a simulated HDL-32E drive with
per-point time, wheel odometry and truth: per-edge errors, ICP-only drift and heading error at the end.

Each (engine, threads) measurement runs in its own subprocess: kiss-icp fixes its TBB thread count once per
process (a static ``tbb::global_control``) and OpenMP (open3d) reads OMP_NUM_THREADS at load. Timings cover
registration only (scan reading excluded); ours includes the wheel deskew, range crop, voxelisation and ground
split; kiss-icp includes its own deskew, voxelisation and local-map update. No GNSS/INS is used: ICP-only.

kiss-icp deskews each sweep to its END, so with per-point time its pose k is the pose at the start of scan
k+1; trajectories are compared on the scan starts both cover (truth at scan start).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench.odometry_engines import (
    Run,
    compare_trajectories,
    errors_vs_truth,
    kiss_available,
    odometry_kiss,
    odometry_ours,
    on_common_scans,
    truth_at_scans,
    yaw_rad,
)
from bench.odometry_sources import (
    CHUNK_SCANS,
    KITTI_DEFAULT,
    KITTI_LIDAR_HEIGHT_M,
    chunked,
    kitti_extrinsic,
    kitti_files,
    read_scan,
    sim_extrinsic,
    sim_files,
    sim_track,
)

REPO = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------- measurements in subprocesses
def measure(spec: dict) -> tuple[Run, int]:
    """One (engine, threads) run on a source, best time of ``repeat`` runs; returns the run and the number of
    scans. ``set`` holds overrides of our OdometryParams (our rows only)."""
    folder = Path(spec["dir"])
    if spec["mode"] == "kitti":
        files, T_vl, track = kitti_files(folder), kitti_extrinsic(), None
    else:
        files, T_vl = sim_files(folder, spec["drive"], spec.get("scans")), sim_extrinsic(folder)
        track = sim_track(folder, spec["drive"])
    threads, engine, overrides = int(spec["threads"]), spec["engine"], spec.get("set", {})
    best = None
    for _ in range(max(1, int(spec.get("repeat", 1)))):
        if engine == "kiss-icp":
            run = odometry_kiss((read_scan(f) for f in files), T_vl, threads)
        elif engine == "ours lidar-only":
            run = odometry_ours(chunked(files, CHUNK_SCANS), T_vl, None, threads, engine,
                                **{**overrides, "deskew": "own_sweep"})
        else:
            run = odometry_ours(chunked(files, CHUNK_SCANS), T_vl, track, threads, engine, **overrides)
        best = run if best is None or run.seconds < best.seconds else best
    return best, len(files)


def _worker(spec_json: str) -> None:
    spec = json.loads(spec_json)
    run, n = measure(spec)
    np.savez(spec["out"], poses=run.poses, seconds=run.seconds, n_registered=run.n_registered,
             n_flagged=run.n_flagged, pose_shift=run.pose_shift, n_scans=n)


def measure_in_subprocess(spec: dict, tmp: Path) -> tuple[Run, int]:
    """Run ``measure`` in a fresh interpreter with ``threads`` for OpenMP/BLAS (and kiss-icp's TBB)."""
    out = tmp / f"{spec['engine'].replace(' ', '_')}_{spec['threads']}.npz"
    env = dict(os.environ)
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        env[var] = str(spec["threads"])
    subprocess.run([sys.executable, "-m", "bench.bench_odometry", "--worker", json.dumps({**spec, "out": str(out)})],
                   cwd=REPO, env=env, check=True)
    z = np.load(out)
    run = Run(spec["engine"], int(spec["threads"]), z["poses"], float(z["seconds"]), int(z["n_registered"]),
              int(z["n_flagged"]), int(z["pose_shift"]))
    return run, int(z["n_scans"])


# ---------------------------------------------------------------- report
def _fmt(x: float, nd: int) -> str:
    return "n/a" if not np.isfinite(x) else f"{x:.{nd}f}"


def machine_line() -> str:
    import open3d

    kiss = "not installed"
    if kiss_available():
        from importlib.metadata import version
        kiss = version("kiss-icp")
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    return (f"machine: {platform.system()} {platform.machine()}, os.cpu_count()={os.cpu_count()} (shared with other "
            f"jobs: timings are indicative), load average {load}; python {platform.python_version()}, "
            f"open3d {open3d.__version__}, kiss-icp {kiss}")


def comparison_table(pairs: list[tuple[str, dict]]) -> list[str]:
    head = ["pair", "steps", "step dt RMS (mm)", "step dt max (mm)", "step drot RMS (deg)", "step drot max (deg)",
            "step dyaw RMS (deg)", "max dpos after chaining (mm)", "end dpos (mm)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, c in pairs:
        cells = [name, str(c["steps"]), f"{c['dt_rms_mm']:.1f}", f"{c['dt_max_mm']:.1f}", f"{c['dr_rms_deg']:.3f}",
                 f"{c['dr_max_deg']:.3f}", f"{c['dyaw_rms_deg']:.3f}", f"{c['dpos_max_mm']:.1f}",
                 f"{c['dpos_end_mm']:.1f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def run_all(base: dict, engines: list[str], threads: list[int]) -> list[tuple[Run, int]]:
    """Every (engine, threads) measurement, one subprocess after the other (never two at once)."""
    out = []
    with tempfile.TemporaryDirectory(prefix="bench_odometry_") as tmp:
        for engine in engines:
            for t in threads if engine != "ours lidar-only" else threads[:1]:
                out.append(measure_in_subprocess({**base, "engine": engine, "threads": t}, Path(tmp)))
    return out


def _engines(with_kiss: bool, extra: list[str] = ()) -> list[str]:
    if not with_kiss:
        print("kiss-icp: not installed in this environment (bench-only, not a project dependency) -- skipping its "
              "rows and the comparison")
    return ["ours", *extra] + (["kiss-icp"] if with_kiss else [])


def _settings(opts: dict) -> str:
    ours = ", ".join(f"{k}={v}" for k, v in opts["set"].items()) or "stage defaults"
    return f"ours: OdometryParams {ours}; timing: best of {opts['repeat']}"


def report_kitti(folder: Path, threads: list[int], opts: dict) -> None:
    spec = {"mode": "kitti", "dir": str(Path(folder).resolve()), **opts}
    results = run_all(spec, _engines(kiss_available()), threads)
    n = results[0][1]
    print(f"\n## KITTI {folder.name}: {n} real HDL-64E scans, no per-point time (no deskew), lidar "
          f"{KITTI_LIDAR_HEIGHT_M} m above the vehicle origin, ICP-only ({_settings(opts)})\n")
    print("| engine | threads | poses | flagged | end x, y, z (m) | end yaw (deg) | path (m) | reg. time (s) "
          "| scans/s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r, _ in results:
        p = r.poses[-1, :3, 3]
        path = float(np.sum(np.linalg.norm(np.diff(r.poses[:, :3, 3], axis=0), axis=1)))
        print(f"| {r.engine} | {r.threads} | {len(r.poses)} | {r.n_flagged} | {p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f} "
              f"| {np.rad2deg(yaw_rad(r.poses[-1])):.3f} | {path:.2f} | {r.seconds:.2f} | {n / r.seconds:.1f} |")
    runs = {(r.engine, r.threads): r for r, _ in results}
    t0 = threads[0]
    if ("kiss-icp", t0) in runs:
        _, (a, b) = on_common_scans([runs[("ours", t0)], runs[("kiss-icp", t0)]], n)
        print()
        c = compare_trajectories(a, b)
        print("\n".join(comparison_table([(f"ours vs kiss-icp ({t0} thread runs)", c)])))
        print(f"\nagreement with kiss-icp (issue 5: within a few centimetres): max position difference "
              f"{c['dpos_max_mm'] / 10:.1f} cm over {np.linalg.norm(b[-1, :3, 3]):.1f} m")
    truth = next((folder / f for f in ("poses_tum.txt",) if (folder / f).exists()), None)
    if truth is None:
        print(f"\nground truth: none in {folder} (its README: no poses, no GNSS) -- no absolute comparison")
    else:
        from stages.common.records import Trajectory

        T = Trajectory.from_tum(truth).T[:n]
        for r, _ in results:
            idx, (P,) = on_common_scans([r], n)
            e = errors_vs_truth(P, T[idx])
            print(f"truth {truth.name}: {r.engine} ({r.threads} thr): end xy error {e['end_xy_m']:.3f} m "
                  f"({_fmt(e['drift_pct'], 2)} % of {e['distance_m']:.1f} m)")


def report_sim(sim: Path, drive: str, n_max: int | None, threads: list[int], opts: dict) -> None:
    base = {"mode": "sim", "dir": str(Path(sim).resolve()), "drive": drive, "scans": n_max, **opts}
    results = run_all(base, _engines(kiss_available(), ["ours lidar-only"]), threads)
    n = results[0][1]
    truth = truth_at_scans(sim / "truth" / f"{drive}_poses_tum.txt", sim_files(sim, drive, n_max))
    idx, rebased = on_common_scans([r for r, _ in results], n)
    T = truth[idx]
    print(f"\n## Simulated {sim.name}/{drive}: {n} HDL-32E scans with per-point time, ICP-only (no GNSS/INS), "
          f"compared on scan starts {idx[0]}..{idx[-1]} ({len(idx) - 1} edges, "
          f"{errors_vs_truth(T, T)['distance_m']:.1f} m; truth at scan start; {_settings(opts)})\n")
    print("| engine | threads | flagged | edge xy RMS (mm) | edge yaw RMS (deg) | end xy err (m) | drift (% of dist) "
          "| RPE 100 m RMS (%) | end heading err (deg) | reg. time (s) | scans/s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for (r, _), P in zip(results, rebased):
        e = errors_vs_truth(P, T)
        print(f"| {r.engine} | {r.threads} | {r.n_flagged} | {e['edge_xy_rms_mm']:.1f} | {e['edge_yaw_rms_deg']:.3f} "
              f"| {e['end_xy_m']:.3f} | {_fmt(e['drift_pct'], 2)} | {_fmt(e['rpe_rms_pct'], 2)} "
              f"| {e['end_heading_deg']:.2f} | {r.seconds:.2f} | {n / r.seconds:.1f} |")
    print("\nours = stage defaults (wheel-odometry deskew + wheel guides for the initial guess and the gate); "
          "ours lidar-only = deskew own_sweep, no wheel odometry (2 registrations per edge); kiss-icp = its "
          "defaults with per-point time (deskew to the end of the sweep: its pose k is compared at scan k+1); "
          "flagged = edges our gate does not accept (off the wheel guide), chained anyway: ICP-only.")
    runs = {(r.engine, r.threads): P for (r, _), P in zip(results, rebased)}
    t0 = threads[0]
    if ("kiss-icp", t0) in runs:
        print()
        print("\n".join(comparison_table([(f"{e} vs kiss-icp ({t0} thread runs)",
                                           compare_trajectories(runs[(e, t0)], runs[("kiss-icp", t0)]))
                                          for e in ("ours", "ours lidar-only")])))
    print()
    for line in acceptance_lines(results, rebased, T):
        print(line)


def acceptance_lines(results: list[tuple[Run, int]], rebased: list[np.ndarray], truth: np.ndarray) -> list[str]:
    """Issue 5's targets against this run's numbers: ICP-only drift <= 0.5 % and no worse than kiss-icp's,
    >= 50 scans/s and ahead of kiss-icp at the same thread count."""
    drift = {(r.engine, r.threads): errors_vs_truth(P, truth)["drift_pct"] for (r, _), P in zip(results, rebased)}
    rate = {(r.engine, r.threads): n / r.seconds for r, n in results}
    ok = lambda c: "PASS" if c else "FAIL"  # noqa: E731
    out = []
    for (engine, t), d in drift.items():
        if engine != "ours":
            continue
        kd, kr = drift.get(("kiss-icp", t)), rate.get(("kiss-icp", t))
        vs_kiss = "" if kd is None else f"; <= kiss-icp's {kd:.2f} %: {ok(d <= kd)}"
        ahead = "" if kr is None else f"; ahead of kiss-icp's {kr:.1f}: {ok(rate[(engine, t)] > kr)}"
        cores = os.cpu_count() or 1
        # the 50 scans/s target is the machine's; the stage runs one single-threaded process per core, so a run
        # on fewer threads than cores gives the per-core rate and the machine figure comes from the stage itself
        machine = (f"throughput {rate[(engine, t)]:.1f} scans/s >= 50: {ok(rate[(engine, t)] >= 50)}" if t >= cores
                   else f"throughput {rate[(engine, t)]:.1f} scans/s per core (target 50 on the {cores}-core "
                   "machine: measured by `cornermap odometry run`, one process per core)")
        out.append(f"acceptance ({t} thread): ours ICP-only drift {d:.2f} % <= 0.5 %: {ok(d <= 0.5)}{vs_kiss}; "
                   f"{machine}{ahead}")
    return out


def _overrides(pairs: list[str]) -> dict:
    """KEY=VALUE strings -> dict (JSON values where they parse, else strings; a dotted KEY names a section's key);
    validated by OdometryParams."""
    from pipeline.declare import nested
    from stages.odometry.params import OdometryParams

    out = {}
    for kv in pairs:
        key, sep, value = kv.partition("=")
        if not sep:
            raise SystemExit(f"--set {kv!r}: expected KEY=VALUE, e.g. --set prepare.voxel_m=0.5")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    out = nested(out)
    OdometryParams.model_validate(out)  # unknown keys and bad values fail here, before any run
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kitti", type=Path, nargs="?", const=KITTI_DEFAULT, default=None,
                    help=f"folder of the KITTI PCD scans (default {KITTI_DEFAULT}); a poses_tum.txt there (one "
                    "T_world_vehicle row per scan, in order) adds a comparison with ground truth")
    ap.add_argument("--sim", type=Path, default=None, help="simulated output folder (cornermap simulate --out)")
    ap.add_argument("--drive", default="drive_0")
    ap.add_argument("--scans", type=int, default=None, help="first N scans of the simulated drive (default all)")
    ap.add_argument("--threads", default="1,2", help="thread counts to time, comma-separated (first: comparisons)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override one of our OdometryParams (repeatable), e.g. --set prepare.voxel_m=0.5")
    ap.add_argument("--repeat", type=int, default=1, help="time each measurement N times, report the best")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        _worker(args.worker)
        return
    threads = [int(t) for t in args.threads.split(",")]
    opts = {"set": _overrides(args.set), "repeat": args.repeat}
    if args.sim is None and args.kitti is None:
        args.kitti = KITTI_DEFAULT
    print("scans/s: registration only, scan reading excluded (each engine in its own process, thread count via "
          "OMP/BLAS env and kiss-icp max_num_threads)")
    if args.kitti is not None:
        report_kitti(args.kitti, threads, opts)
    if args.sim is not None:
        report_sim(args.sim, args.drive, args.scans, threads, opts)
    print("\n" + machine_line())


if __name__ == "__main__":
    main()
