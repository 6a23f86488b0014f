"""Cost of adding one drive to a map (``cornermap rebuild``) against a one-drive build, from the run summaries.

    .venv/bin/python -m bench.bench_rebuild --preset tiny --drives 3 [--sim DIR] [--json out.json] [--gate]
    .venv/bin/python -m bench.bench_rebuild --preset demo --drives 4
    .venv/bin/python -m bench.bench_rebuild --preset tiny --drives 3 --s3   # roots and inboxes in a local S3 bucket

Simulates ``--drives`` K drives (or takes them from ``--sim``), then in fresh roots:
  A. a map of the first K-1 drives (``maps create`` + ``rebuild`` from an inbox holding them);
  B. a one-drive map of drive K alone (its per-drive work: ingest, odometry, corners);
  C. drive K added to map A (``rebuild``): the old drives' per-drive work is reused.
Reported: per-stage wall seconds of A, B, C, partitions reused in C and the ratio
``C / (per-drive work of B + joint steps of C)`` (issue target <= 1.3). The gate is off unless ``--gate``
(its evaluation is timed apart). Wall times depend on the machine's load: state it with the numbers. CPU seconds
of each rebuild (this process and its pool processes; ``A_cpu_s``, ``B_cpu_s``, ``C_cpu_s``) are measured as
``bench.bench_build`` does. ``--s3``: the roots are ``s3://bench/...`` and the inboxes ``s3://bench/inbox-*`` on moto's
S3 server started here (``bench_build.s3_root``; its own CPU is left out and reported apart, ``s3_server_cpu_s``);
drives are uploaded with a READY object (the upload is not counted).
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
    subprocess.run([sys.executable, "-m", "mapservice", "simulate", "--preset", preset, "--seed", str(seed),
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


def deliver_s3(sim: Path, names: list[str], inbox: str) -> str:
    """``deliver`` into a bucket inbox: each drive's files under ``INBOX/NAME/``, then its READY object."""
    from pipeline.storage import Store

    store = Store.open(inbox)

    def upload(folder: Path, name: str) -> None:
        store.upload_files([(p, store.root / name / p.relative_to(folder).as_posix())
                            for p in sorted(folder.rglob("*")) if p.is_file()])

    if (sim / "survey").is_dir() and not store.exists(store.root / "survey"):
        upload(sim / "survey", "survey")
    for n in names:
        upload(sim / n, n)
        time.sleep(1.1)  # S3 stamps are whole seconds: READY after the last object
        store.put_bytes(store.root / n / "READY", b"")
    return inbox


def _rebuild(root, inbox, gate: bool, server=None) -> tuple[dict, float, list[str], float]:
    """(summary, wall s, lines, CPU s of this process tree less the S3 server's)."""
    from bench.bench_build import _cpu_of, tree_cpu_s
    from mapservice.rebuild import RebuildParams, rebuild

    t0, cpu0 = time.perf_counter(), tree_cpu_s() - _cpu_of(server)
    res = rebuild(root, "city", inbox, RebuildParams(gate=gate, min_free_gib=0.5, quiet_period_s=0.0))  # copied now
    return res.summary, time.perf_counter() - t0, res.lines, tree_cpu_s() - _cpu_of(server) - cpu0


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--drives", type=int, default=3, help="K: a map of K-1 drives, then drive K is added")
    ap.add_argument("--sim", type=Path, help="simulated drives to reuse (drive_0 .. drive_{K-1})")
    ap.add_argument("--work", type=Path, help="work folder (default: a temporary one, deleted)")
    ap.add_argument("--gate", action="store_true", help="run the regression gate in C")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--s3", action="store_true", help="roots and inboxes on a local S3 server (moto, started here)")
    a = ap.parse_args(argv)
    from bench.bench_build import s3_root

    with s3_root(a.s3) as server:
        return _bench(a, server)


def _bench(a, server) -> dict:
    from bench.bench_build import _cpu_of
    from mapservice.maps import create_map

    work = a.work or Path(tempfile.mkdtemp(prefix="bench-rebuild-"))
    server_cpu0 = _cpu_of(server)
    try:
        sim = simulated(a.sim, work, a.preset, a.seed, a.drives)
        names = [f"drive_{k}" for k in range(a.drives)]
        old, new = names[:-1], names[-1]
        if server is not None:
            stamp = time.time_ns()
            root_a, root_b = f"s3://bench/A-{stamp}", f"s3://bench/B-{stamp}"
            inbox_a, inbox_b = f"s3://bench/inbox-A-{stamp}", f"s3://bench/inbox-B-{stamp}"
            put = deliver_s3
        else:
            root_a, root_b, inbox_a, inbox_b, put = work / "A", work / "B", work / "inbox_A", work / "inbox_B", deliver
        create_map(root_a, "city", ORIGIN)
        sum_a, _, _, cpu_a = _rebuild(root_a, put(sim, old, inbox_a), gate=False, server=server)
        create_map(root_b, "city", ORIGIN)
        sum_b, _, _, cpu_b = _rebuild(root_b, put(sim, [new], inbox_b), gate=False, server=server)
        put(sim, [new], inbox_a)
        sum_c, wall_c, lines_c, cpu_c = _rebuild(root_a, inbox_a, gate=a.gate, server=server)
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
               "C_lines": lines_c, "root_on": "s3" if server is not None else "local disk",
               "A_cpu_s": round(cpu_a, 1), "B_cpu_s": round(cpu_b, 1), "C_cpu_s": round(cpu_c, 1),
               "s3_server_cpu_s": round(_cpu_of(server) - server_cpu0, 1) if server is not None else None}
        print(json.dumps(out, indent=1))
        if a.json:
            a.json.write_text(json.dumps(out, indent=1))
        return out
    finally:
        if a.work is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
