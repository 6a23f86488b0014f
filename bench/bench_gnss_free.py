"""Maps from drives without GNSS against the simulator's truth: per seed and variant, the map frame's true error
(shift at its reference point, rotation) against the stated one, the map-relative error (what a rigid frame fit
leaves: the shape) against the stated relative std, and the loop closures between the two drives, which run the loop
in opposite directions.

    .venv/bin/python -m bench.bench_gnss_free --work DIR --seeds 331 332 333 334 [--variants start local]

Per seed: ``cornermap simulate --preset tiny --drives 2 --set survey=0 --set gnss=0 --set prior=local`` (drive 0
counter-clockwise, drive 1 clockwise: every street is revisited in the opposite direction), then per variant a
``cornermap build`` of both drives with ``--origin`` at the simulator's origin (so the truth is in the map's ENU frame):
``local`` as simulated (a SLAM-like local prior, 0.2 m / 0.1 deg Gauss-Markov error, plus the start pose, 0.3 deg /
0.05 m), ``start`` with the prior section removed (odometry and loops from the start pose alone). Child processes,
run from DIR; roots are kept (delete DIR afterwards).
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

SIM_ORIGIN = "37.4979,127.0276,57.0"  # the tiny preset's


def cornermap(args: list[str], cwd: Path, allow: tuple[int, ...] = ()) -> str:
    """Run a cornermap command; its last error line when it exits with a code in ``allow`` (else it must pass)."""
    run = subprocess.run([sys.executable, "-m", "mapservice", *args], cwd=cwd, capture_output=True, text=True)
    if run.returncode in allow:
        return " ".join(ln.strip() for ln in run.stderr.strip().splitlines()[-2:])
    if run.returncode != 0:
        raise SystemExit(f"cornermap {' '.join(args[:3])} failed (exit {run.returncode}): {run.stderr.strip()}")
    return ""


def prepare(work: Path, seed: int, variant: str) -> list[Path]:
    sim = work / f"sim{seed}"
    if not (sim / "simulation.json").is_file():
        cornermap(["simulate", "--preset", "tiny", "--seed", str(seed), "--drives", "2", "--out", str(sim), "-q",
                   "--set", "survey=0", "--set", "gnss=0", "--set", "prior=local"], work)
    out = []
    for d in sorted(sim.glob("drive_*/drive.yaml")):
        doc = yaml.safe_load(d.read_text())
        if variant == "start":
            doc.pop("prior", None)
        target = d.with_name(f"drive_{variant}.yaml")
        target.write_text(yaml.safe_dump(doc, sort_keys=False))
        out.append(target)
    return out


def measure(root: Path, sim: Path) -> dict:
    import pyarrow.compute as pc

    from bench.bench_map_frame import committed, frame_error
    from bench.bench_posegraph import truth_poses
    from bench.roots import read
    from stages.common.geometry import wrap_angle_rad
    from stages.posegraph.map_frame import travel_weights

    m = committed(root)
    truth = np.concatenate([truth_poses(sim, n, m.stamps_ns[m.group == k])
                            for k, n in enumerate(m.names)])
    yaw = lambda T: np.arctan2(T[:, 1, 0], T[:, 0, 0])  # noqa: E731
    w = travel_weights(m.est[:, :2, 3], m.group)
    g, resid = frame_error(m.est[:, :2, 3], truth[:, :2, 3], wrap_angle_rad(yaw(m.est) - yaw(truth)), w,
                           m.reference_en_m)
    h = np.linalg.norm(resid[:, :2], axis=1)
    absolute = np.linalg.norm(m.est[:, :2, 3] - truth[:, :2, 3], axis=1)
    cf, rel = m.cov_frame, m.cov_relative
    loops = read(root, "loop_closures")
    acc = loops.filter(pc.and_(loops["accepted"], pc.not_equal(loops["drive_a"], loops["drive_b"])))
    opposite = int(np.sum(np.abs(acc["dyaw_rad"].to_numpy()) > np.pi / 2))
    return {"frame_shift_m": round(float(np.hypot(g[0], g[1])), 3), "frame_rot_deg": round(float(np.degrees(g[2])), 3),
            "stated_shift_m": round(float(np.sqrt(cf[0, 0] + cf[1, 1])), 3),
            "stated_rot_deg": round(float(np.degrees(np.sqrt(cf[2, 2]))), 3),
            "frame_nees_3dof": round(float(g @ np.linalg.solve(cf, g)), 2),
            "shape_rms_m": round(float(np.sqrt(np.mean(h ** 2))), 3), "shape_max_m": round(float(h.max()), 3),
            "stated_relative_rms_m": round(float(np.sqrt(np.mean(np.trace(rel[:, :2, :2], axis1=1, axis2=2)))), 3),
            "absolute_rms_m": round(float(np.sqrt(np.mean(absolute ** 2))), 3),
            "absolute_max_m": round(float(absolute.max()), 3),
            "loops_between_drives": acc.num_rows, "loops_opposite_direction": opposite, "poses": len(m.est)}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--seeds", type=int, nargs="+", required=True)
    ap.add_argument("--variants", nargs="+", default=["start", "local"], choices=["start", "local"])
    args = ap.parse_args(argv)
    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    for seed in args.seeds:
        for variant in args.variants:
            drives = prepare(work, seed, variant)
            root = work / f"root{seed}_{variant}"
            t0 = time.perf_counter()
            refused = ""
            if not (root / "maps" / "m").is_dir() or not any((root / "maps" / "m").glob("v*")):
                # a quality gate may refuse to publish (exit 3): the pose graph's poses are committed all the same
                refused = cornermap(["build", *sum((["--drive", str(d)] for d in drives), []), "--map", "m",
                                     "--root", str(root), "--origin", SIM_ORIGIN, "--workers", "1", "-q"], work,
                                    allow=(3,))
            row = {"seed": seed, "variant": variant, **measure(root, work / f"sim{seed}"),
                   "build_s": round(time.perf_counter() - t0, 1), **({"not_published": refused} if refused else {})}
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
