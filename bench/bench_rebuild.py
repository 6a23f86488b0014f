"""Cost of adding one drive to a map (``cornermap rebuild``) against a one-drive build, from the run summaries.

    .venv/bin/python -m bench.bench_rebuild --preset tiny --drives 3 [--sim DIR] [--json out.json] [--gate]
    .venv/bin/python -m bench.bench_rebuild --preset demo --drives 4

Simulates ``--drives`` K drives (or takes them from ``--sim``), then in fresh roots:
  A. a map of the first K-1 drives (``maps create`` + ``rebuild`` from an inbox holding them);
  B. a one-drive map of drive K alone (its per-drive work: ingest, odometry, corners);
  C. drive K added to map A (``rebuild``): the old drives' per-drive work is reused.
Reported: per-stage wall seconds of A, B, C, partitions reused in C and the ratio
``C / (per-drive work of B + joint steps of C)`` (issue target <= 1.3). The gate is off unless ``--gate``
(its evaluation is timed apart). Wall times depend on the machine's load: state it with the numbers.
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ORIGIN = {"lat_deg": 37.4979, "lon_deg": 127.0276, "h_m": 57.0}  # the simulator's origin
PER_DRIVE = ("ingest", "odometry", "corners")
JOINT = ("posegraph", "cornermap", "markings", "tiles")


def _stage_walls(summary: dict) -> dict[str, float]:
    return {s: float(v.get("wall_s", 0.0)) for s, v in summary.items()}


def simulated(sim: Path | None, work: Path, preset: str, seed: int, drives: int) -> Path:
    """``sim`` when given (simulated drives to reuse), else ``drives`` drives of (preset, seed) simulated into
    WORK/sim by the CLI."""
    if sim is not None:
        return sim
    out = work / "sim"
    subprocess.run([sys.executable, "-m", "pipeline", "simulate", "--preset", preset, "--seed", str(seed),
                    "--drives", str(drives), "--out", str(out)], check=True, capture_output=True)
    return out


def deliver(sim: Path, names: list[str], inbox: Path, ready: bool = False) -> Path:
    """Copy the drive folders ``names`` of a simulation into ``inbox`` (with the shared ``survey/`` once: drive files
    name ../survey/survey.las); ``ready``: each with its READY file (the inbox's delivery protocol)."""
    inbox.mkdir(parents=True, exist_ok=True)
    if (sim / "survey").is_dir() and not (inbox / "survey").exists():
        shutil.copytree(sim / "survey", inbox / "survey")
    for n in names:
        shutil.copytree(sim / n, inbox / n)  # copy2 keeps modification times: same drive fingerprints
        if ready:
            (inbox / n / "READY").touch()
    return inbox


def _rebuild(root: Path, inbox: Path, gate: bool) -> tuple[dict, float, list[str]]:
    from pipeline.rebuild import RebuildParams, rebuild

    t0 = time.perf_counter()
    res = rebuild(root, "city", inbox, RebuildParams(gate=gate, min_free_gib=0.5, quiet_period_s=0.0))  # copied now
    return res.summary, time.perf_counter() - t0, res.lines


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--drives", type=int, default=3, help="K: a map of K-1 drives, then drive K is added")
    ap.add_argument("--sim", type=Path, help="simulated drives to reuse (drive_0 .. drive_{K-1})")
    ap.add_argument("--work", type=Path, help="work folder (default: a temporary one, deleted)")
    ap.add_argument("--gate", action="store_true", help="run the regression gate in C")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    from pipeline.maps import create_map

    work = a.work or Path(tempfile.mkdtemp(prefix="bench-rebuild-"))
    try:
        sim = simulated(a.sim, work, a.preset, a.seed, a.drives)
        names = [f"drive_{k}" for k in range(a.drives)]
        old, new = names[:-1], names[-1]
        create_map(work / "A", "city", ORIGIN)
        sum_a, _, _ = _rebuild(work / "A", deliver(sim, old, work / "inbox_A"), gate=False)
        create_map(work / "B", "city", ORIGIN)
        sum_b, _, _ = _rebuild(work / "B", deliver(sim, [new], work / "inbox_B"), gate=False)
        deliver(sim, [new], work / "inbox_A")
        sum_c, wall_c, lines_c = _rebuild(work / "A", work / "inbox_A", gate=a.gate)
        wa, wb, wc = _stage_walls(sum_a), _stage_walls(sum_b), _stage_walls(sum_c)
        per_drive_b = sum(wb.get(s, 0.0) for s in PER_DRIVE)
        joint_c = sum(wc.get(s, 0.0) for s in JOINT)
        build_c = sum(wc.values())
        out = {"preset": a.preset, "seed": a.seed, "drives": a.drives,
               "A_stage_wall_s": wa, "B_stage_wall_s": wb, "C_stage_wall_s": wc,
               "C_partitions": {s: [v.get("partitions"), v.get("partitions_reused")] for s, v in sum_c.items()},
               "A_build_s": round(sum(wa.values()), 1), "B_build_s": round(sum(wb.values()), 1),
               "C_build_s": round(build_c, 1), "C_per_drive_s": round(sum(wc.get(s, 0.0) for s in PER_DRIVE), 1),
               "B_per_drive_s": round(per_drive_b, 1), "C_joint_s": round(joint_c, 1),
               "ratio_C_over_B_per_drive_plus_C_joint": round(build_c / max(per_drive_b + joint_c, 1e-9), 3),
               "C_rebuild_wall_s": round(wall_c, 1), "gate_s": round(wall_c - build_c, 1) if a.gate else None,
               "C_lines": lines_c}
        print(json.dumps(out, indent=1))
        if a.json:
            a.json.write_text(json.dumps(out, indent=1))
        return out
    finally:
        if a.work is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
