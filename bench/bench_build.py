"""Whole-map build benchmark: raw simulated drives -> published map tiles, per stage wall / CPU, peak RSS of
every process (pool workers and spawned processes included), scans per second end to end.

    .venv/bin/python -m bench.bench_build --preset demo [--seed 1] [--scheduler local] [--json out.json]
    .venv/bin/python -m bench.bench_build --preset gangnam --drives drive_0
    .venv/bin/python -m bench.bench_build --preset gangnam --drives drive_0 --max-scans 1000   # memory vs length
    .venv/bin/python -m bench.bench_build --preset kitti --max-scans 154                       # real HDL-64E scans
    .venv/bin/python -m bench.bench_build --preset demo --cluster-workers 2    # on a dask LocalCluster of 2 workers
    .venv/bin/python -m bench.bench_build --preset demo --params P.yaml        # other settings, the same code
    .venv/bin/python -m bench.bench_build --preset tiny --s3                   # the root on a local S3 server

The simulation is made once per preset and seed and cached (``--cache``, default ``~/.cache/cornermap-bench``);
simulate and evaluation are not timed. Every run builds into a fresh root (deleted afterwards unless ``--keep``).
The CPU line sums user + system time over the whole process tree (the engine, its pools, a LocalCluster's processes)
during the build; divided by the usable cores it is the floor no schedule can beat with this CPU: a wall target below
it needs less CPU, not more overlap. Stage figures come from the run summary: when its first partition started and
its last ended (seconds from the run's start; stages overlap), wall from first submit to commit, and CPU of its
partition tasks (their threads and the pools they started). RSS is sampled every 0.2 s over the process tree.

``--cluster-workers N`` starts a dask ``LocalCluster`` of N single-threaded worker processes (as a user's cluster:
nannies, their environment, a scheduler in a process of its own) before the clock starts and builds on it
(``--scheduler`` its address); its workers descend from this process, so their memory is in the RSS figures. The
speed-up of 2 workers against 1 is the ratio of two such runs' walls.

``--s3`` builds into ``s3://bench/root`` on moto's S3 server (``fixtures/s3server.py``) started here on 127.0.0.1, the
tasks' local copies in the run's folder (``CORNERMAP_SCRATCH``). The server's own CPU and memory are left out of the
figures (a real bucket runs elsewhere) and reported apart (``s3_server_cpu_s``, ``s3_server_peak_rss_mb``).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import yaml

if __package__ in (None, ""):  # run by its path from another folder: the checkout's bench and fixtures modules
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

ORIGIN = {"lat_deg": 37.4979, "lon_deg": 127.0276, "h_m": 57.0}  # the simulator's origin (workflows/demo.yaml)
BUILD_STAGES = ["ingest", "odometry", "posegraph", "corners", "cornermap", "markings", "tiles"]


class RssSampler(threading.Thread):
    """Peak resident memory per process of this process tree (pid -> (name, peak bytes))."""

    def __init__(self, period_s: float = 0.2):
        super().__init__(daemon=True)
        import psutil

        self._root = psutil.Process()
        self.period_s = period_s
        self.peaks: dict[int, tuple[str, int]] = {}
        self._halt = threading.Event()

    def run(self) -> None:
        import psutil

        while not self._halt.is_set():
            for proc in [self._root] + self._root.children(recursive=True):
                try:
                    rss = proc.memory_info().rss
                    name = " ".join(proc.cmdline()[:3])[-60:]
                except (psutil.NoSuchProcess, psutil.AccessDenied):
                    continue
                if rss > self.peaks.get(proc.pid, ("", 0))[1]:
                    self.peaks[proc.pid] = (name, rss)
            self._halt.wait(self.period_s)

    def stop(self) -> None:
        self._halt.set()
        self.join()


def _cpu_of(proc) -> float:
    """CPU seconds of one process (0 for None or a process gone)."""
    if proc is None:
        return 0.0
    try:
        t = proc.cpu_times()
    except Exception:  # noqa: BLE001 - psutil.NoSuchProcess and alike
        return 0.0
    return t.user + t.system


def tree_cpu_s() -> float:
    """CPU seconds (user + system) used so far by this process, its live descendants, and every descendant that one
    of them reaped (psutil's ``children_*`` times of each): pool processes, spawned workers and a LocalCluster's
    processes included. A live process's ``children_*`` hold only reaped ones, so nothing counts twice."""
    import psutil

    root = psutil.Process()
    total = 0.0
    for proc in [root] + root.children(recursive=True):
        try:
            t = proc.cpu_times()
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
        total += t.user + t.system + t.children_user + t.children_system
    return total


def simulated(cache: Path, preset: str, seed: int, max_scans: int | None = None) -> Path:
    """The simulated drives of (preset, seed), the first ``max_scans`` scans of each drive if given (a shorter drive
    of the same city: the memory-against-length comparison)."""
    out = cache / (f"sim-{preset}-seed{seed}" + (f"-max{max_scans}" if max_scans else ""))
    if not (out / "simulation.json").is_file():
        tmp = out.with_name(out.name + ".tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        cap = ["--max-scans", str(max_scans)] if max_scans else []
        subprocess.run([sys.executable, "-m", "mapservice", "simulate", "--preset", preset, "--seed", str(seed),
                        "--out", str(tmp), "--quiet", *cap], check=True)
        tmp.replace(out)
    return out


KITTI = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kitti_raw_0048_city"


def kitti_drive(cache: Path, n_scans: int | None) -> Path:
    """A folder holding ``drive_0/drive.yaml``: ``n_scans`` links to the shared KITTI scans (cyclically) and an
    OXTS-style CSV along a straight path without noise (``fixtures.kitti``), the drive file drafted from them."""
    from fixtures.kitti import kitti_drive_folder
    from stages.ingest.drive_init import draft_drive_file

    files = sorted(KITTI.glob("*.pcd"))
    if not files:
        raise SystemExit(f"no KITTI scans under {KITTI}: the shared data must sit beside the checkout")
    out = cache / f"kitti-hdl64e-{n_scans or len(files)}"
    links = sorted((out / "drive_0" / "velodyne_points").glob("*.pcd"))
    if (out / "drive_0" / "drive.yaml").is_file() and links and all(p.exists() for p in links):
        return out
    shutil.rmtree(out, ignore_errors=True)  # links into a checkout's ../shared that is gone: made again
    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    folder = kitti_drive_folder(tmp / "drive_0", KITTI.resolve(), ORIGIN, n_scans=n_scans, noise_m=0.0)
    (folder / "drive.yaml").write_text("\n".join(draft_drive_file(folder).lines) + "\n")
    tmp.replace(out)
    return out


def write_workflow(folder: Path, sim: Path, drives: list[str], root: Path, scheduler: str) -> Path:
    entries = [{"name": d, "path": str(sim / d / "drive.yaml"), "role": "map" if n == 0 else "eval"}
               for n, d in enumerate(drives)]
    doc = {"name": "bench_build", "root": str(root), "map_name": "bench", "scheduler": scheduler,
           "enu_origin": ORIGIN, "drives": entries, "stages": BUILD_STAGES}
    path = folder / "bench_build.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def count_scans(sim: Path, drives: list[str]) -> int:
    return sum(sum(1 for _ in (sim / d).glob("*/*.pcd")) for d in drives)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="demo", choices=["tiny", "demo", "gangnam", "kitti"])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--drives", nargs="+", default=None, help="drives to build (default: drive_0 drive_1)")
    ap.add_argument("--scheduler", default="local", help="local | sync | tcp://HOST:PORT")
    ap.add_argument("--workers", type=int, default=None, help="local pool size (default: the machine's cores)")
    ap.add_argument("--max-scans", type=int, default=None,
                    help="build only the first N scans of each drive (peak memory against drive length)")
    ap.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "cornermap-bench")
    ap.add_argument("--json", type=Path, default=None, help="write the figures here")
    ap.add_argument("--keep", action="store_true", help="keep the build root")
    ap.add_argument("--cluster-workers", type=int, default=None,
                    help="build on a dask LocalCluster of this many single-threaded worker processes")
    ap.add_argument("--s3", action="store_true", help="the root on a local S3 server (moto, started here)")
    ap.add_argument("--params", type=Path, default=None,
                    help="a params file over the stages' defaults (as `cornermap run --params`): two settings on "
                         "the same code side by side")
    args = ap.parse_args(argv)
    with s3_root(args.s3) as server, local_cluster(args.cluster_workers) as address:
        args.s3_server = server
        if address:
            args.scheduler = address
        return _bench(args)


@contextlib.contextmanager
def s3_root(enabled: bool):
    """With ``enabled``: moto's S3 server on 127.0.0.1 with the bucket ``bench``, the AWS environment pointing at it
    for the block; yields the server's ``psutil.Process`` (its CPU and memory are reported apart), else None."""
    if not enabled:
        yield None
        return
    import os

    import psutil

    from fixtures.s3server import make_bucket, s3_server

    before = {p.pid for p in psutil.Process().children()}
    with s3_server() as env:
        os.environ.update(env)
        make_bucket(env, "bench")
        server = next(p for p in psutil.Process().children() if p.pid not in before)
        yield server


@contextlib.contextmanager
def local_cluster(n_workers: int | None):
    """A LocalCluster of ``n_workers`` single-threaded worker processes for the block (its address), or None. The
    cluster (scheduler, nannies) lives in a process of its own, as a user's cluster does: its scheduler shared this
    process's interpreter with the run's client and flow (demo, 2 workers: 185.3 s so, 161.7 s started apart)."""
    if not n_workers:
        yield None
        return
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    address, stop = ctx.Queue(), ctx.Event()
    proc = ctx.Process(target=_serve_cluster, args=(n_workers, address, stop), name="bench-cluster")
    proc.start()
    try:
        yield address.get(timeout=120)
    finally:
        stop.set()
        proc.join(timeout=60)
        if proc.is_alive():
            proc.terminate()


def _serve_cluster(n_workers: int, address, stop) -> None:
    from distributed import LocalCluster

    with LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        address.put(cluster.scheduler_address)
        stop.wait()


def _bench(args) -> int:

    from pipeline.api import execute_workflow
    from pipeline.errors import CornermapError

    if args.preset == "kitti":
        sim, drives = kitti_drive(args.cache, args.max_scans), ["drive_0"]
    else:
        sim = simulated(args.cache, args.preset, args.seed, args.max_scans)
        drives = args.drives or ["drive_0", "drive_1"]
    work = Path(tempfile.mkdtemp(prefix="bench-build-"))
    wf = write_workflow(work, sim, drives, work / "root", args.scheduler)
    server = getattr(args, "s3_server", None)
    root = None
    if server is not None:
        import os

        os.environ["CORNERMAP_SCRATCH"] = str(work / "scratch")  # the tasks' local copies of the bucket's root
        root = f"s3://bench/root-{time.time_ns()}"
    sampler = RssSampler()
    sampler.start()
    server_cpu0 = _cpu_of(server)
    cpu0 = tree_cpu_s()
    t0 = time.perf_counter()
    try:
        try:
            result = execute_workflow(wf, root=root, scheduler=args.scheduler, only=None, dry_run=False, quiet=True,
                                      params_file=args.params, workers=args.workers)
        except CornermapError as exc:  # a quality gate or a bad input: the product's one-line message and exit code
            print(f"error: {exc}", file=sys.stderr)
            return exc.exit_code
        wall = time.perf_counter() - t0
        server_cpu = _cpu_of(server) - server_cpu0
        cpu = tree_cpu_s() - cpu0 - server_cpu
        keep = ("wall_s", "cpu_s", "started_s", "ended_s", "peak_rss_mb")
        stages = {k: {c: v.get(c) for c in keep} for k, v in result["summary"].items()}
    finally:
        sampler.stop()
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    n_scans = count_scans(sim, drives)
    from pipeline.parallel import default_workers

    cores = default_workers()  # the usable cores
    peaks = sorted(sampler.peaks.values(), key=lambda x: -x[1])
    server_peak = next((rss for name, rss in peaks if "moto" in name), 0)
    peaks = [(name, rss) for name, rss in peaks if "moto" not in name]
    doc = {"preset": args.preset, "seed": args.seed, "max_scans": args.max_scans, "drives": drives, "scans": n_scans,
           "scheduler": args.scheduler,
           "workers": args.workers, "cluster_workers": args.cluster_workers,
           "params": str(args.params) if args.params else None, "root_on": "s3" if server else "local disk",
           "s3_server_cpu_s": round(server_cpu, 1) if server else None,
           "s3_server_peak_rss_mb": round(server_peak / 2**20) if server else None,
           "wall_s": round(wall, 1), "scans_per_s": round(n_scans / wall, 1),
           "cpu_s": round(cpu, 1), "cores": cores, "cpu_floor_s": round(cpu / cores, 1),
           "busy_share": round(cpu / (cores * wall), 3), "stages": stages,
           "peak_rss_mb_max": round(peaks[0][1] / 2**20) if peaks else None,
           "peak_rss_mb_by_process": [(name, round(rss / 2**20)) for name, rss in peaks[:8]]}
    print(f"{args.preset} seed {args.seed}, {', '.join(drives)} (root on {doc['root_on']}): {n_scans} scans, "
          f"{wall:.1f} s wall, "
          f"{n_scans / wall:.1f} scans/s end to end, peak RSS {doc['peak_rss_mb_max']} MB (largest process)")
    print(f"CPU {cpu:.1f} s over the process tree on {cores} cores: floor {cpu / cores:.1f} s (the wall of this CPU "
          f"with every core busy), cores busy {100 * doc['busy_share']:.0f} % of the wall")
    print("| stage | from s | to s | wall s | CPU s | task peak RSS MB |\n|---|---|---|---|---|---|")
    for k, v in stages.items():
        print(f"| {k} | {v.get('started_s')} | {v.get('ended_s')} | {v['wall_s']} | {v['cpu_s']} | "
              f"{v.get('peak_rss_mb')} |")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
