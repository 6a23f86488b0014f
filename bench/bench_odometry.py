"""Odometry bench: our scan-to-scan odometry against kiss-icp (and against ground truth where there is one).

    .venv/bin/python -m bench.bench_odometry --kitti ../shared/data/kitti_raw_0048_city
    .venv/bin/cornermap simulate --preset tiny --seed 7 --out /tmp/bench_odo/tiny --drives 1
    .venv/bin/python -m bench.bench_odometry --sim /tmp/bench_odo/tiny --drive drive_0 --scans 250

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
import csv
import itertools
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

REPO = Path(__file__).resolve().parents[1]
KITTI_DEFAULT = REPO.parent / "shared" / "data" / "kitti_raw_0048_city"
KITTI_LIDAR_HEIGHT_M = 1.73  # KITTI's Velodyne above the ground; vehicle frame on the ground below it
CHUNK_SCANS = 100  # the ingest stage's default chunk; chunk c re-reads the last scan of chunk c-1


@dataclass(frozen=True)
class ScanFile:
    scan_id: int
    stamp_ns: int
    path: Path


@dataclass(frozen=True)
class Run:
    """One engine's trajectory: ``poses[k]`` is T_first_vehicle (vehicle frame of its first pose) at the start
    of scan ``k + pose_shift``."""

    engine: str
    threads: int
    poses: np.ndarray  # (N,4,4)
    seconds: float  # registration only
    n_registered: int
    n_flagged: int  # edges our gate did not accept (chained anyway: ICP-only)
    pose_shift: int


def kiss_available() -> bool:
    try:
        import kiss_icp.kiss_icp  # noqa: F401
    except ImportError:
        return False
    return True


# ---------------------------------------------------------------- sources
def kitti_files(folder: Path) -> list[ScanFile]:
    paths = sorted(folder.glob("*.pcd"))
    if not paths:
        raise FileNotFoundError(f"{folder}: no *.pcd scans; hint: pass --kitti DIR")
    return [ScanFile(i, i * 100_000_000, p) for i, p in enumerate(paths)]  # KITTI raw: 10 Hz


def kitti_extrinsic() -> np.ndarray:
    T = np.eye(4)
    T[2, 3] = KITTI_LIDAR_HEIGHT_M
    return T


def _gps_ns(week: str, seconds: str) -> int:
    whole, _, frac = seconds.partition(".")
    return (int(week) * 604800 + int(whole)) * 1_000_000_000 + int((frac + "000000000")[:9])


def sim_files(sim: Path, drive: str, n_max: int | None) -> list[ScanFile]:
    with open(sim / drive / "scans" / "stamps.csv") as fh:
        rows = list(csv.DictReader(fh))
    files = [ScanFile(int(r["scan_id"]), _gps_ns(r["gps_week"], r["gps_seconds"]),
                      sim / drive / "scans" / f"{int(r['scan_id']):06d}.pcd") for r in rows]
    return files[:n_max] if n_max else files


def sim_extrinsic(sim: Path) -> np.ndarray:
    return np.asarray(json.loads((sim / "simulation.json").read_text())["T_vehicle_lidar"], dtype=float)


def sim_track(sim: Path, drive: str):
    from stages.common.wheel_deskew import OdometryTrack

    with open(sim / drive / "wheel_gyro.csv") as fh:
        rows = list(csv.DictReader(fh))
    return OdometryTrack(np.array([_gps_ns(r["gps_week"], r["gps_seconds"]) for r in rows], dtype=np.int64),
                         np.array([float(r["wheel_speed_mps"]) for r in rows]),
                         np.array([float(r["yaw_rate_radps"]) for r in rows]))


def read_scan(f: ScanFile):
    from stages.ingest.pcd import read_pcd
    from stages.odometry.core import Scan

    cols = read_pcd(f.path).columns
    xyz = np.column_stack([cols[c].astype(np.float64) for c in ("x", "y", "z")])
    keep = np.any(xyz != 0, axis=1) & np.all(np.isfinite(xyz), axis=1)  # KITTI's trailing (0,0,0) record
    t = cols["time"].astype(np.float64)[keep] if "time" in cols else None
    return Scan(f.scan_id, f.stamp_ns, xyz[keep], t if t is not None and np.any(t != 0) else None)


def chunked(files: list[ScanFile], size: int) -> Iterator[list]:
    for a in range(0, len(files), size):
        yield [read_scan(f) for f in files[a:a + size]]


# ---------------------------------------------------------------- engines
def chain(increments: Iterable[np.ndarray]) -> np.ndarray:
    poses = [np.eye(4)]
    for T in increments:
        poses.append(poses[-1] @ T)
    return np.array(poses)


def odometry_ours(chunks: Iterable[list], T_vehicle_lidar: np.ndarray, track=None, threads: int = 0,
                  engine: str = "ours", **overrides) -> Run:
    """Our odometry stage's algorithm, chunk by chunk as the stage runs it, without GNSS/INS (ICP-only);
    wheel deskew and wheel guides where ``track`` is given and the params say deskew='odometry'."""
    from stages.odometry.compute import deskew_with_wheel_odometry, wheel_guides
    from stages.odometry.core import estimate_edges
    from stages.odometry.params import OdometryParams

    p = OdometryParams(**overrides)
    cfg = p.edge_config()
    edges, seconds, prev = [], 0.0, None
    for chunk in chunks:
        scans = ([prev] if prev is not None else []) + chunk
        t0 = time.perf_counter()
        guides = wheel_guides(scans, track)
        if p.deskew == "odometry":
            scans, _ = deskew_with_wheel_odometry(scans, track, T_vehicle_lidar)
        edges += estimate_edges(scans, T_vehicle_lidar, {}, cfg, guide_increments=guides or None)
        seconds += time.perf_counter() - t0  # span edges (p.span_scans) are part of the stage's cost
        prev = chunk[-1]
    edges = [e for e in edges if e.span == 1]  # the dead-reckoning chain
    ids = [e.scan_id for e in edges]
    if ids and ids != list(range(ids[0], ids[0] + len(ids))):
        raise ValueError(f"{engine}: edges are not consecutive (scan ids {ids[:5]}...); hint: a scan is missing")
    return Run(engine, threads, chain(e.T_prev_curr for e in edges), seconds, len(edges),
               sum(not e.accepted for e in edges), 0)


def kiss_config(threads: int, deskew: bool):
    from kiss_icp.config import load_config

    cfg = load_config(None)  # kiss-icp's defaults, voxel size resolved from max_range as its pipeline does
    cfg.data.deskew = deskew
    cfg.registration.max_num_threads = threads
    return cfg


def odometry_kiss(scans: Iterable, T_vehicle_lidar: np.ndarray, threads: int = 1) -> Run:
    """kiss-icp (its defaults) over the scans; per-point time when the first scan has it (deskew on)."""
    from kiss_icp.kiss_icp import KissICP

    from stages.common.geometry import se3_inverse

    it = iter(scans)
    first = next(it)
    deskew = first.time_offset_s is not None
    odom = KissICP(kiss_config(threads, deskew))
    poses, seconds = [], 0.0
    for s in itertools.chain([first], it):
        t = s.time_offset_s if deskew and s.time_offset_s is not None else np.zeros(len(s.points_lidar_m))
        pts = np.ascontiguousarray(s.points_lidar_m, dtype=np.float64)
        t0 = time.perf_counter()
        odom.register_frame(pts, np.ascontiguousarray(t, dtype=np.float64))
        seconds += time.perf_counter() - t0
        poses.append(odom.last_pose.copy())
    P = T_vehicle_lidar @ np.array(poses) @ se3_inverse(T_vehicle_lidar)
    P = se3_inverse(P[0]) @ P
    return Run("kiss-icp", threads, P, seconds, len(poses), 0, 1 if deskew else 0)


# ---------------------------------------------------------------- metrics
def inverse_poses(T: np.ndarray) -> np.ndarray:
    """Batch inverse of (N,4,4) rigid transforms."""
    out = np.tile(np.eye(4), (len(T), 1, 1))
    Rt = np.transpose(T[:, :3, :3], (0, 2, 1))
    out[:, :3, :3] = Rt
    out[:, :3, 3] = -np.einsum("nij,nj->ni", Rt, T[:, :3, 3])
    return out


def yaw_rad(T: np.ndarray) -> np.ndarray:
    return np.arctan2(T[..., 1, 0], T[..., 0, 0])


def rotation_deg(T: np.ndarray) -> np.ndarray:
    c = (np.trace(T[..., :3, :3], axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.rad2deg(np.arccos(np.clip(c, -1.0, 1.0)))


def steps(P: np.ndarray) -> np.ndarray:
    return inverse_poses(P[:-1]) @ P[1:]


def on_common_scans(runs: list[Run], n_scans: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """Scan indices every run has a pose for (at that scan's start) and each run's poses there, rebased on the
    first common scan."""
    idx = [np.arange(len(r.poses)) + r.pose_shift for r in runs]
    common = np.arange(n_scans)
    for i in idx:
        common = np.intersect1d(common, i)
    out = []
    for r, i in zip(runs, idx):
        P = r.poses[np.searchsorted(i, common)]
        out.append(inverse_poses(P[:1])[0] @ P)
    return common, out


def compare_trajectories(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    """Per-step difference (translation mm, rotation deg) and the position difference after chaining; both
    trajectories on the same scans and rebased on the same first scan."""
    D = inverse_poses(steps(a)) @ steps(b)
    dt_mm = 1000 * np.linalg.norm(D[:, :3, 3], axis=1)
    dr_deg = rotation_deg(D)
    dyaw_deg = np.rad2deg(yaw_rad(D))
    dpos_mm = 1000 * np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=1)
    return {"steps": len(D), "dt_rms_mm": float(np.sqrt(np.mean(dt_mm ** 2))), "dt_max_mm": float(dt_mm.max()),
            "dr_rms_deg": float(np.sqrt(np.mean(dr_deg ** 2))), "dr_max_deg": float(dr_deg.max()),
            "dyaw_rms_deg": float(np.sqrt(np.mean(dyaw_deg ** 2))),
            "dpos_max_mm": float(dpos_mm.max()), "dpos_end_mm": float(dpos_mm[-1])}


def errors_vs_truth(est: np.ndarray, truth: np.ndarray, segment_m: float = 100.0) -> dict[str, float]:
    """ICP-only errors of a trajectory against truth on the same scans (both (N,4,4); est in any frame, started
    at the truth's first pose): per-edge xy / yaw RMS, end position error and its share of the (horizontal)
    distance, the RMS relative error over ``segment_m`` of path in %, and the heading error at the end."""
    est_w = truth[0] @ inverse_poses(est[:1])[0] @ est
    E = inverse_poses(steps(truth)) @ steps(est_w)
    cum = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(truth[:, :2, 3], axis=0), axis=1))]
    end_m = float(np.linalg.norm(est_w[-1, :2, 3] - truth[-1, :2, 3]))
    rpe = []
    for i in range(len(truth)):
        j = int(np.searchsorted(cum, cum[i] + segment_m))
        if j >= len(truth):
            break
        rel_t = inverse_poses(truth[[i]])[0] @ truth[j]
        rel_e = inverse_poses(est_w[[i]])[0] @ est_w[j]
        rpe.append(100 * np.linalg.norm((np.linalg.inv(rel_t) @ rel_e)[:2, 3]) / (cum[j] - cum[i]))
    heading = np.rad2deg(np.angle(np.exp(1j * (yaw_rad(est_w[-1]) - yaw_rad(truth[-1])))))
    return {"edges": len(E), "distance_m": float(cum[-1]),
            "edge_xy_rms_mm": float(1000 * np.sqrt(np.mean(np.sum(E[:, :2, 3] ** 2, axis=1)))),
            "edge_yaw_rms_deg": float(np.rad2deg(np.sqrt(np.mean(yaw_rad(E) ** 2)))),
            "end_xy_m": end_m, "drift_pct": 100 * end_m / cum[-1] if cum[-1] > 0 else float("nan"),
            "rpe_rms_pct": float(np.sqrt(np.mean(np.square(rpe)))) if rpe else float("nan"),
            "end_heading_deg": float(heading)}


def truth_at_scans(path: Path, files: list[ScanFile]) -> np.ndarray:
    """Truth pose at each scan's start (nearest truth sample; refused when more than 5 ms away)."""
    from stages.common.geometry import read_tum

    t, T = read_tum(path)
    s = np.array([f.stamp_ns for f in files]) * 1e-9
    i = np.clip(np.searchsorted(t, s), 1, len(t) - 1)
    i = np.where(np.abs(t[i - 1] - s) < np.abs(t[i] - s), i - 1, i)
    worst = float(np.max(np.abs(t[i] - s)))
    if worst > 0.005:
        raise ValueError(f"{path}: no truth sample within 5 ms of every scan start (worst {worst:.3f} s); "
                         "hint: truth and stamps.csv must share the GPS time base")
    return T[i]


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
    results = run_all({"mode": "kitti", "dir": str(folder), **opts}, _engines(kiss_available()), threads)
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
        from stages.common.geometry import read_tum

        T = read_tum(truth)[1][:n]
        for r, _ in results:
            idx, (P,) = on_common_scans([r], n)
            e = errors_vs_truth(P, T[idx])
            print(f"truth {truth.name}: {r.engine} ({r.threads} thr): end xy error {e['end_xy_m']:.3f} m "
                  f"({_fmt(e['drift_pct'], 2)} % of {e['distance_m']:.1f} m)")


def report_sim(sim: Path, drive: str, n_max: int | None, threads: list[int], opts: dict) -> None:
    base = {"mode": "sim", "dir": str(sim), "drive": drive, "scans": n_max, **opts}
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
    """KEY=VALUE strings -> dict (JSON values where they parse, else strings); validated by OdometryParams."""
    from stages.odometry.params import OdometryParams

    out = {}
    for kv in pairs:
        key, sep, value = kv.partition("=")
        if not sep:
            raise SystemExit(f"--set {kv!r}: expected KEY=VALUE, e.g. --set voxel_m=0.5")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    OdometryParams(**out)  # unknown keys and bad values fail here, before any run
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
                    help="override one of our OdometryParams (repeatable), e.g. --set voxel_m=0.5")
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
