"""Published maps on S3 against the same on local disk: publish (``tiles push``), list, verify every version, and load
every tile (``open_map``) of one map, each command run as a process; CPU seconds of the cornermap processes (the S3
server's own CPU is left out: a real bucket runs elsewhere) and their peak RSS.

    .venv/bin/python -m bench.bench_store --root ROOT --map NAME [--repeat 3] [--json out.json]
    .venv/bin/python -m bench.bench_store --backends     # s3fs against pyarrow.fs on the same server (the choice)

ROOT is a local root holding a published map (e.g. the tiny build: ``cornermap run tiny --root runs/tiny``). The S3
side is moto's server on 127.0.0.1 (``fixtures/s3server.py``), started here. Local "publish" is a copy of the map's
folder into a fresh local root (``tiles push --to FOLDER``), so both sides run the same code path.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

LOAD = ("import sys; from mapformat.loader import open_map; r = open_map(sys.argv[1]); "
        "n = sum(r.tile_corners(*k).num_rows for k in r.tile_keys()); "
        "m = sum(int(r.tile_marking(*k) is not None) for k in r.tile_keys()); print(n, m)")


def run_measured(cmd: list[str], env: dict[str, str]) -> tuple[float, float, float]:
    """(wall s, this process's children's cumulative CPU s after the command ended, peak RSS MB of any process of
    the command's tree)."""
    import psutil

    t0 = time.perf_counter()
    proc = psutil.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    peak = 0
    while proc.poll() is None:
        try:
            peak = max(peak, max(p.memory_info().rss for p in [proc] + proc.children(recursive=True)))
        except psutil.Error:
            pass
        time.sleep(0.02)
    out, err = proc.communicate()
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} exited {proc.returncode}: {err.decode()[-2000:]}")
    wall = time.perf_counter() - t0
    import resource

    ru = resource.getrusage(resource.RUSAGE_CHILDREN)  # cumulative: the caller takes differences
    return wall, ru.ru_utime + ru.ru_stime, peak / 2**20


def steps(root: str, src: Path, name: str) -> dict[str, list[str]]:
    cm = str(Path(sys.executable).parent / "cornermap")
    return {
        "publish": [cm, "tiles", "push", "--root", str(src), "--map", name, "--to", root, "-q"],
        "ls": [cm, "tiles", "ls", "--root", root, "--map", name],
        "verify --all": [cm, "tiles", "verify", "--all", "--root", root, "--map", name],
        "load all tiles": [sys.executable, "-c", LOAD, f"{root}/maps/{name}"],
    }


def measure(root: str, src: Path, name: str, env: dict[str, str]) -> dict[str, dict[str, float]]:
    import resource

    out = {}
    for step, cmd in steps(root, src, name).items():
        ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        wall, cpu1, peak = run_measured(cmd, env)
        out[step] = {"wall_s": round(wall, 3), "cpu_s": round(cpu1 - (ru0.ru_utime + ru0.ru_stime), 3),
                     "peak_rss_mb": round(peak, 1)}
    return out


def compare_backends(repeat: int = 3) -> None:
    """s3fs against pyarrow.fs: 100 small PUTs, a 64 MB PUT and GET, best wall of ``repeat`` (with its CPU)."""
    import pyarrow.fs as pafs
    import s3fs

    from fixtures.s3server import make_bucket, s3_server

    with s3_server() as env:
        os.environ.update(env)
        make_bucket(env, "bkt")
        data = os.urandom(64 * 2**20)
        fs = s3fs.S3FileSystem()
        host = env["AWS_ENDPOINT_URL"].split("://", 1)[1]
        pa = pafs.S3FileSystem(endpoint_override=host, scheme="http", access_key=env["AWS_ACCESS_KEY_ID"],
                               secret_key=env["AWS_SECRET_ACCESS_KEY"], region=env["AWS_DEFAULT_REGION"])

        def best(f) -> str:
            runs = []
            for _ in range(repeat):
                c, w = time.process_time(), time.perf_counter()
                f()
                runs.append((time.perf_counter() - w, time.process_time() - c))
            w, c = min(runs)
            return f"{w:.2f} s wall, {c:.2f} CPU s"

        def pa_put(key: str, body: bytes) -> None:
            with pa.open_output_stream(key) as fh:
                fh.write(body)

        def pa_get(key: str) -> None:
            with pa.open_input_stream(key) as fh:
                fh.read()

        print("| operation | s3fs | pyarrow.fs |\n|---|---|---|")
        print(f"| 100 small PUTs (300 B) | {best(lambda: [fs.pipe_file(f'bkt/s{i}', b'x' * 300) for i in range(100)])}"
              f" | {best(lambda: [pa_put(f'bkt/p{i}', b'x' * 300) for i in range(100)])} |")
        print(f"| PUT 64 MB | {best(lambda: fs.pipe_file('bkt/big', data))} | "
              f"{best(lambda: pa_put('bkt/big2', data))} |")
        print(f"| GET 64 MB | {best(lambda: fs.cat_file('bkt/big'))} | {best(lambda: pa_get('bkt/big2'))} |")


def main(argv: list[str] | None = None) -> int:
    from fixtures.s3server import make_bucket, s3_server

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backends", action="store_true", help="only compare s3fs and pyarrow.fs")
    ap.add_argument("--root", type=Path, help="a local root holding the published map")
    ap.add_argument("--map", dest="name")
    ap.add_argument("--repeat", type=int, default=3, help="runs per side; the best CPU of each step is reported")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.backends:
        compare_backends(args.repeat)
        return 0
    if args.root is None or args.name is None:
        ap.error("--root and --map are required (or --backends)")
    repo = Path(__file__).resolve().parents[1]
    results: dict[str, dict[str, dict[str, float]]] = {"local": {}, "s3": {}}
    with s3_server() as s3env, tempfile.TemporaryDirectory(prefix="store-bench-") as tmp:
        env = {**os.environ, **s3env, "PYTHONPATH": str(repo), "CORNERMAP_PROGRESS": "0"}
        for i in range(args.repeat):
            for side in ("local", "s3"):
                if side == "s3":
                    bucket = f"bench-{i}-{os.getpid()}"
                    make_bucket(s3env, bucket)
                    root = f"s3://{bucket}/root"
                else:
                    root = str(Path(tmp) / f"local-{i}")
                for step, fig in measure(root, args.root, args.name, env).items():
                    best = results[side].get(step)
                    if best is None or fig["cpu_s"] < best["cpu_s"]:
                        results[side][step] = fig
    print("| step | local CPU s | S3 CPU s | S3/local | local wall s | S3 wall s | local peak MB | S3 peak MB |")
    print("|---|---|---|---|---|---|---|---|")
    for step in results["local"]:
        a, b = results["local"][step], results["s3"][step]
        print(f"| {step} | {a['cpu_s']:.2f} | {b['cpu_s']:.2f} | {b['cpu_s'] / max(a['cpu_s'], 1e-9):.2f} | "
              f"{a['wall_s']:.2f} | {b['wall_s']:.2f} | {a['peak_rss_mb']:.0f} | {b['peak_rss_mb']:.0f} |")
    tot = {s: sum(v["cpu_s"] for v in results[s].values()) for s in results}
    print(f"total CPU: local {tot['local']:.2f} s, S3 {tot['s3']:.2f} s, ratio {tot['s3'] / tot['local']:.2f}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
