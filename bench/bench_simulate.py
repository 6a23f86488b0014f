"""Generation speed of ``cornermap simulate``: scans per second per core, and the whole-preset wall time.

    .venv/bin/python -m bench.bench_simulate                      # demo city, 200 scans per drive
    .venv/bin/python -m bench.bench_simulate --preset gangnam --full   # the whole gangnam preset
"""
from __future__ import annotations

import argparse
import os
import resource
import shutil
import tempfile
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="demo")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scans", type=int, default=200, help="scans per drive unless --full")
    ap.add_argument("--full", action="store_true", help="generate the whole preset")
    ap.add_argument("--out", type=Path, default=None, help="keep the output here (default: a temp dir)")
    args = ap.parse_args()

    from stages.simulate.core import simulate

    out = args.out or Path(tempfile.mkdtemp(prefix="bench_sim_"))
    cpu0 = resource.getrusage(resource.RUSAGE_SELF)
    t0 = time.perf_counter()
    summary = simulate(args.preset, args.seed, out, scan_limit=None if args.full else args.scans)
    wall = time.perf_counter() - t0
    cpu1 = resource.getrusage(resource.RUSAGE_SELF)
    cpu = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    n = sum(summary.n_scans.values())
    print(f"machine: {os.cpu_count()} cores (shared); preset {args.preset} seed {args.seed}")
    print(f"scans: {n} ({summary.n_scans}); wall {wall:.1f} s; cpu {cpu:.1f} s")
    print(f"speed: {n / wall:.1f} scans/s wall, {n / cpu:.1f} scans/s per core (cpu time, includes city, "
          f"survey and truth)")
    for name, st in summary.gnss_stats.items():
        print(f"{name} GNSS: {st}")
    if args.out is None:
        shutil.rmtree(out, ignore_errors=True)


if __name__ == "__main__":
    main()
