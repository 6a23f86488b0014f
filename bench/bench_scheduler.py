"""Threads vs processes vs sync for the CPU-heavy stages, on the tiny city.

    .venv/bin/python -m bench.bench_scheduler [--workflow workflows/tiny.yaml] [--stages odometry corners]

Runs the workflow once (to commit the inputs), then times each listed stage alone on each scheduler, into a
fresh copy of the committed inputs, and prints seconds per stage. Numbers depend on the machine: say which.
"""
from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workflow", type=Path, default=Path("workflows/tiny.yaml"))
    ap.add_argument("--stages", nargs="+", default=["odometry", "corners", "markings"])
    ap.add_argument("--schedulers", nargs="+", default=["sync", "threads", "processes"])
    ap.add_argument("--root", type=Path, default=None)
    args = ap.parse_args()

    from pipeline.api import execute_workflow
    from pipeline.plan import make_plan
    from pipeline.store import dataset_dir
    from pipeline.workflow import load_workflow

    base = args.root or Path(tempfile.mkdtemp(prefix="bench-sched-"))
    execute_workflow(args.workflow, root=base, scheduler="processes", only=None, dry_run=False, quiet=True)
    plan = make_plan(load_workflow(args.workflow), base)
    print(f"machine: {os.cpu_count()} cores; workflow {args.workflow}; root {base}")
    print(f"{'stage':10s} " + " ".join(f"{s:>10s}" for s in args.schedulers))
    for stage in args.stages:
        sp = plan.stages[stage]
        row = []
        for sched in args.schedulers:
            for ds in sp.outputs.values():  # drop this stage's outputs so it runs again
                shutil.rmtree(dataset_dir(base, ds, sp.fingerprint), ignore_errors=True)
            t0 = time.perf_counter()
            execute_workflow(args.workflow, root=base, scheduler=sched, only=[stage], dry_run=False, quiet=True)
            row.append(time.perf_counter() - t0)
        print(f"{stage:10s} " + " ".join(f"{t:10.1f}" for t in row))


if __name__ == "__main__":
    main()
