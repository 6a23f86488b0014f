"""Scattered scan reads from a committed ``scans_raw``: the engine's ``read_in`` (row groups pruned on their
``scan_id`` statistics) against a pyarrow dataset read with an ``is_in`` filter (prunes nothing), on the same keys.

The pose graph and the drive-scan markings read a few scans spread over a whole drive (loop candidates, a tile's
passes) this way. Run the workflow's ingest first (``cornermap run WF --only ingest`` or the whole workflow).

    .venv/bin/python -m bench.bench_scattered_reads -w workflows/gangnam.yaml [--root runs/gangnam] \\
        [--drive drive_0] [--count 62] [--seed 0] [--repeat 3]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-w", "--workflow", type=Path, required=True)
    ap.add_argument("--root", type=Path, default=None, help="default: the workflow's root")
    ap.add_argument("--drive", default=None, help="default: the first drive of the workflow")
    ap.add_argument("--count", type=int, default=62, help="scans to read, drawn at random over the drive")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=3, help="timed runs of each reader (best one printed)")
    args = ap.parse_args()

    import pyarrow.compute as pc

    from bench.bench_posegraph_eval import committed
    from pipeline.declare import PartitionKey
    from pipeline.plan import make_plan
    from pipeline.workflow import load_workflow

    wf = load_workflow(args.workflow)
    plan = make_plan(wf, wf.root_dir(args.root))
    scans = committed(plan, "ingest", "scans", "scans_raw")
    drive = args.drive or sorted(p.drive for p in scans.partitions("scans"))[0]
    part = PartitionKey(drive=drive)
    all_ids = np.unique(scans.read("scans", partition=part, columns=["scan_id"])["scan_id"].to_numpy())
    ids = np.sort(np.random.default_rng(args.seed).choice(all_ids, min(args.count, len(all_ids)), replace=False))
    cols = ["scan_id", "x_m", "y_m", "z_m", "intensity", "time_offset_s"]

    def pruned():
        return scans.read_in("scans", "scan_id", ids.tolist(), partition=part, columns=cols)

    def filtered():
        return scans.read("scans", partition=part, columns=cols, filters=pc.field("scan_id").isin(ids.tolist()))

    best, rows = {}, {}
    for name, fn in (("read_in (row groups pruned)", pruned), ("dataset read, is_in filter", filtered)):
        times = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            table = fn()
            times.append(time.perf_counter() - t0)
        best[name], rows[name] = min(times), table.num_rows
    same = len(set(rows.values())) == 1
    print(f"root {plan.root}; drive {drive}: {len(ids)} of {len(all_ids)} scans")
    for name in best:
        print(f"  {name}: {best[name]:.3f} s (best of {args.repeat}), {rows[name]} points")
    print(f"  same rows from both readers: {same}")
    if not same:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
