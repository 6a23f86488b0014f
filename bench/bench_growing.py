"""A city that grows: N nightly ``cornermap rebuild``s, each adding the night's drive of the ``growing`` preset.

    .venv/bin/python -m bench.bench_growing --drives 20 --seed 591 [--changes-from K] [--sim DIR] [--work DIR] \
        [--ref-drive R] [--json out.json] [--csv out.csv] [--figure docs/figures/growing_nights.png] [--no-refs]

Simulates ``--drives`` N drives of the ``growing`` preset (``stages/simulate/presets.py``: a 5 x 3 grid of small
blocks, drive k loops around its own window of one block row and two block columns, the first 12 drives sweeping
the grid west to east, later ones revisiting; ``--changes`` from drive ``--changes-from``: a building demolished,
one built, a crosswalk moved along that drive's window), or takes them from ``--sim``. Makes a map (``maps create``,
``--tile-size-m``) and on night k delivers drive k-1 to the inbox and runs ``python -m mapservice rebuild --no-gate``
as a child process (the incremental default; ``bench.bench_incremental.rebuild_night``), with the tiles stage's
quality gates off (``--params``: ``tiles: {gates_enabled: false}``; ``--tiles-gates`` keeps them).

Per night (one JSON object in ``nights``, one CSV row):
- ``cpu_s``: user + system seconds of the rebuild's whole process tree (``RUSAGE_CHILDREN``); ``wall_s``;
- tiles: of the new version, ``tiles_touched`` (tiles within ``--reach-m`` of the night's drive's true path: what
  its scans can see), ``tiles_republished`` (added or with changed files against the parent version),
  ``republished_untouched`` (republished, not touched, not a neighbour of a touched one: should be 0),
  ``download_tile_bytes`` (tile files whose sha256 the parent does not hold at that path: what a localizer
  downloads), ``touched_tile_bytes`` (the touched tiles' bytes in the new version), ``map_tile_bytes`` (the whole
  map's), and ``download_ratio`` = download / touched (issue target <= 1.2);
- corners against the truth (``bench.bench_incremental.corner_accuracy``, absolute, no frame offset): ``rms_m``
  and ``precision`` (of the map's corners, the share within 0.3 m of a truth corner; the truth is the city as
  first simulated: corners of a building built by the changes count as false), ``n_corners``.
Reference costs of one drive R (``--ref-drive``, default the last; skip with ``--no-refs``), run right after night
R+1 so that a run stopped early keeps them: R's one-drive build, and R added to a one-drive map of the earlier drive
of its window (drive R-12, else drive 0); the ratios of night R+1's CPU (R added to the R-drive map) to them:
``ref_over_added_to_one`` (target <= 1.25) and ``ref_over_one_drive_build`` (target <= 1.5). The JSON, CSV and
figure are rewritten after every night. The targets are reported, never asserted. CPU seconds depend on the machine
and its load (``machine``; each night's 1-minute load before and after, ``load_1min``).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench.bench_incremental import _machine, corner_accuracy, rebuild_night, tile_changes
from bench.bench_rebuild import ORIGIN

WINDOWS = 12  # the growing preset's windows (3 block rows x 4 column positions): drive k and k + 12 share one
CSV_FIELDS = (
    "night",
    "drive",
    "cpu_s",
    "wall_s",
    "posegraph_cpu_s",
    "n_tiles",
    "tiles_touched",
    "tiles_republished",
    "republished_untouched",
    "download_tile_bytes",
    "touched_tile_bytes",
    "map_tile_bytes",
    "download_ratio",
    "n_corners",
    "precision",
    "rms_m",
)


def simulate(out: Path, seed: int, drives: int, changes_from: int | None) -> Path:
    cmd = [
        sys.executable,
        "-m",
        "mapservice",
        "simulate",
        "--preset",
        "growing",
        "--seed",
        str(seed),
        "--drives",
        str(drives),
        "--out",
        str(out),
        "-q",
    ]
    if changes_from is not None:
        cmd += ["--changes", "--changes-from-drive", str(changes_from)]
    subprocess.run(cmd, check=True, capture_output=True)
    return out


def _link_or_copy(src: str, dst: str) -> None:
    """A hard link (a 20-drive simulation is ~6 GB: the inbox must not double it), else a copy."""
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def deliver(sim: Path, name: str, inbox: Path) -> None:
    """Drive ``name`` into the inbox (hard-linked files) with a READY file; the survey folders (``survey/``,
    ``survey_changed/``) once, as the drive files name them (../survey*/survey.las)."""
    inbox.mkdir(parents=True, exist_ok=True)
    for sub in ("survey", "survey_changed"):
        if (sim / sub).is_dir() and not (inbox / sub).exists():
            shutil.copytree(sim / sub, inbox / sub, copy_function=_link_or_copy)
    shutil.copytree(sim / name, inbox / name, copy_function=_link_or_copy)
    (inbox / name / "READY").touch()


def touched_tiles(sim: Path, drive: str, tile_size_m: float, reach_m: float) -> set[tuple[int, int]]:
    """Tiles (i, j) whose square lies within ``reach_m`` of the drive's true path (``stages.common.tiling``)."""
    from stages.common.tiling import tile_bounds, tile_key_of

    xy = np.loadtxt(sim / "truth" / f"{drive}_poses_tum.txt", usecols=(1, 2), comments="#")[::10]
    i, j = tile_key_of(xy[:, 0], xy[:, 1], tile_size_m)
    span = int(np.ceil(reach_m / tile_size_m))
    out = set()
    for ti in range(int(i.min()) - span, int(i.max()) + span + 1):
        for tj in range(int(j.min()) - span, int(j.max()) + span + 1):
            west, south, east, north = tile_bounds(ti, tj, tile_size_m)
            dx = np.maximum(np.maximum(west - xy[:, 0], xy[:, 0] - east), 0.0)
            dy = np.maximum(np.maximum(south - xy[:, 1], xy[:, 1] - north), 0.0)
            if np.hypot(dx, dy).min() <= reach_m:
                out.add((ti, tj))
    return out


def tile_bytes(vdir: Path) -> dict[tuple[int, int], int]:
    """Bytes of each tile's files in a version (its manifest: a tile's ``files`` {name: sha256} under its ``dir``)."""
    man = json.loads((vdir / "manifest.json").read_text())
    return {
        (t["i"], t["j"]): sum(man["files"].get(f"{t['dir']}/{name}", {}).get("bytes", 0) for name in t["files"])
        for t in man["tiles"]
    }


def republished(vdir: Path, parent: Path | None) -> set[tuple[int, int]]:
    man = json.loads((vdir / "manifest.json").read_text())
    old = json.loads((parent / "manifest.json").read_text()) if parent is not None else {"tiles": []}
    old_tiles = {(t["i"], t["j"]): t["files"] for t in old["tiles"]}
    return {(t["i"], t["j"]) for t in man["tiles"] if old_tiles.get((t["i"], t["j"])) != t["files"]}


def night_row(night: dict) -> dict:
    t, c = night["tiles"], night["corners"]
    return {
        "night": night["night"],
        "drive": night["drive"],
        "cpu_s": night["cpu_s"],
        "wall_s": night["wall_s"],
        "posegraph_cpu_s": night["stage_cpu_s"].get("posegraph"),
        "n_tiles": t["n_tiles"],
        "tiles_touched": t["tiles_touched"],
        "tiles_republished": t["tiles_republished"],
        "republished_untouched": t["republished_untouched"],
        "download_tile_bytes": t["download_tile_bytes"],
        "touched_tile_bytes": t["touched_tile_bytes"],
        "map_tile_bytes": t["tile_bytes"],
        "download_ratio": t["download_ratio"],
        "n_corners": c["n_corners"],
        "precision": c["precision"],
        "rms_m": c["rms_m"],
    }


def figure(rows: list[dict], out: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = [r["night"] for r in rows]
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.6))
    a.bar(n, [r["cpu_s"] for r in rows], color="#4c72b0", label="rebuild (process tree)")
    a.plot(n, [r["posegraph_cpu_s"] or 0 for r in rows], "o-", color="#dd8452", ms=3, label="pose graph stage")
    a.set_xlabel("night (drives in the map)")
    a.set_ylabel("CPU s")
    a.set_title("CPU per night")
    a.legend(fontsize=8)
    b.plot(n, [1000 * (r["rms_m"] or np.nan) for r in rows], "o-", color="#55a868", ms=3, label="corner RMS (mm)")
    b.set_xlabel("night (drives in the map)")
    b.set_ylabel("absolute corner RMS, mm")
    b2 = b.twinx()
    b2.plot(n, [r["precision"] for r in rows], "s--", color="#c44e52", ms=3, label="precision")
    b2.set_ylabel("precision")
    b2.set_ylim(0.9, 1.005)
    b.set_ylim(bottom=0)
    b.legend(b.get_lines() + b2.get_lines(), ["corner RMS (mm)", "precision"], fontsize=8, loc="lower right")
    for ax in (a, b):
        ax.xaxis.get_major_locator().set_params(integer=True)
    b.set_title("map against the truth per night")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=591)
    ap.add_argument("--drives", type=int, default=20, help="N nights, one drive each")
    ap.add_argument(
        "--changes-from", type=int, help="first drive that sees the changed city (default 3N/4; -1: no changes)"
    )
    ap.add_argument("--sim", type=Path, help="a growing simulation to reuse (drive_0 .. drive_{N-1})")
    ap.add_argument("--work", type=Path, help="work folder (default: a temporary one, deleted)")
    ap.add_argument("--tile-size-m", type=float, default=50.0)
    ap.add_argument("--reach-m", type=float, default=40.0, help="a tile is touched within this of the drive's path")
    ap.add_argument("--no-refs", action="store_true", help="skip the reference builds")
    ap.add_argument(
        "--ref-drive",
        type=int,
        help="the drive whose reference builds are run right after the night that adds it (default: the last)",
    )
    ap.add_argument(
        "--tiles-gates",
        action="store_true",
        help="keep the tiles stage's quality gates (off by default: "
        "at 50 m most tiles of a one-window map hold no corner and the gate refuses the version)",
    )
    ap.add_argument("--json", type=Path)
    ap.add_argument("--csv", type=Path)
    ap.add_argument("--figure", type=Path)
    ap.add_argument("--markdown", type=Path, help="the per-night table as Markdown (docs/maintenance.md)")
    ap.add_argument(
        "--joint",
        action="store_true",
        help="after the nights, the joint solve of the same drives (`maps reoptimize --region-max-poses 0`, "
        "= rebuild --full's solve) published as the next version; its corners against the truth",
    )
    ap.add_argument(
        "--eval-drive",
        type=int,
        help="a drive of --sim that is not in the map (e.g. N): `cornermap evaluate --method ekf` against its truth "
        "on the last night's version and (--joint) on the joint version",
    )
    ap.add_argument(
        "--post-only",
        action="store_true",
        help="skip the nights: --work holds them and --json their results; run --joint / --eval-drive only",
    )
    ap.add_argument(
        "--joint-only",
        action="store_true",
        help="no nights: the N drives built in one rebuild on a fresh map in --work (their joint solve; can run "
        "beside a nights run on another --work), then --eval-drive on it; written to --json",
    )
    a = ap.parse_args(argv)
    if a.post_only and not (a.work and a.json and a.json.is_file()):
        ap.error("--post-only needs --work and the --json of the nights")
    from mapservice.maps import create_map

    ref = a.drives - 1 if a.ref_drive is None else min(a.ref_drive, a.drives - 1)
    changes_from = (a.drives * 3) // 4 if a.changes_from is None else a.changes_from
    changes_from = None if changes_from < 1 or changes_from >= a.drives else changes_from
    work = a.work or Path(tempfile.mkdtemp(prefix="bench-growing-"))
    work.mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()[0]
    try:
        sim = a.sim or simulate(work / "sim", a.seed, a.drives, changes_from)
        sim_doc = json.loads((sim / "simulation.json").read_text())
        root, inbox = work / "root", work / "inbox"
        params = None
        if not a.tiles_gates:
            params = work / "params.yaml"
            params.write_text("tiles: {gates_enabled: false}\n")
        mdir = root / "maps" / "city"
        if a.joint_only:
            return joint_build(a, sim, work, params, load_before)
        if a.post_only:
            out = json.loads(a.json.read_text())
            rows = [night_row(n) for n in out["nights"]]
            after_nights(a, out, rows, sim, work, params, load_before)
            return out
        create_map(root, "city", ORIGIN, tile_size_m=a.tile_size_m)
        out = {
            "preset": sim_doc.get("preset"),
            "seed": sim_doc.get("seed"),
            "drives": a.drives,
            "changes_from_drive": (sim_doc.get("changes") or {}).get("from_drive"),
            "tile_size_m": a.tile_size_m,
            "reach_m": a.reach_m,
            "mode": "incremental, --no-gate",
            "tiles_gates": a.tiles_gates,
            "nights": [],
        }
        nights, rows = out["nights"], []
        for k in range(a.drives):
            drive = f"drive_{k}"
            deliver(sim, drive, inbox)
            load0 = os.getloadavg()[0]
            night = rebuild_night(root, inbox, False, params)
            night["load_1min"] = [round(load0, 1), round(os.getloadavg()[0], 1)]
            vdir = mdir / night["version"]
            parent = mdir / f"v{int(night['version'][1:]) - 1:04d}" if k else None
            tiles = tile_changes(vdir, parent)
            touched = touched_tiles(sim, drive, a.tile_size_m, a.reach_m)
            near = {(i + di, j + dj) for i, j in touched for di in (-1, 0, 1) for dj in (-1, 0, 1)}
            rep = republished(vdir, parent)
            sizes = tile_bytes(vdir)
            touched_bytes = sum(sizes.get(t, 0) for t in touched)
            tiles.update(
                tiles_touched=len(touched & set(sizes)),
                tiles_republished=len(rep),
                republished_untouched=len(rep - near),
                touched_tile_bytes=touched_bytes,
                download_ratio=round(tiles["download_tile_bytes"] / touched_bytes, 3) if touched_bytes else None,
            )
            night["tiles"] = tiles
            acc = corner_accuracy(vdir, sim)
            night["corners"] = {key: v for key, v in acc.items() if key not in ("ids", "en")}
            night["drift"] = version_drift(root, vdir) if k else None  # now: a rebuild keeps the last versions only
            night["posegraph"] = posegraph_record(root, vdir) if k else {}
            night["night"], night["drive"] = k + 1, drive
            night["sees_changed_city"] = changes_from is not None and k >= changes_from
            nights.append(night)
            rows.append(night_row(night))
            print(json.dumps(rows[-1]), flush=True)
            _save(a, out, rows, load_before)  # after every night: a run stopped early keeps what it measured
            if k == ref and not a.no_refs:
                reference_builds(a, out, sim, work, params, ref)
                _save(a, out, rows, load_before)
        _save(a, out, rows, load_before)
        after_nights(a, out, rows, sim, work, params, load_before)
        keys = (
            "ref_over_added_to_one",
            "ref_over_one_drive_build",
            "download_ratio_max",
            "republished_untouched_total",
        )
        print(json.dumps({k: out.get(k) for k in keys}))
        return out
    finally:
        if a.work is None:
            shutil.rmtree(work, ignore_errors=True)


def after_nights(a, out: dict, rows: list[dict], sim: Path, work: Path, params: Path | None, load0: float) -> None:
    """--eval-drive on the last night's version, then --joint (published as the next version), then --eval-drive on
    it; the JSON is rewritten after each."""
    from pipeline.versioned import read_latest, version_name

    root, mdir = work / "root", work / "root" / "maps" / "city"
    last = out["nights"][-1]["version"] if out["nights"] else version_name(read_latest(mdir))
    for night in out["nights"]:  # a rebuild keeps the last versions only: an older night's are gone (None)
        vdir = mdir / night["version"]
        if night.get("drift") is None and (vdir / "manifest.json").is_file():
            night["drift"] = version_drift(root, vdir)
        if not night.get("posegraph") and (vdir / "manifest.json").is_file():
            night["posegraph"] = posegraph_record(root, vdir)
    _save(a, out, rows, load0)
    if a.eval_drive is not None:
        out.setdefault("eval", {})["nights"] = evaluate_drive(root, last, sim, a.eval_drive, work / "eval-nights")
        print(json.dumps({"eval_nights": out["eval"]["nights"]}), flush=True)
        _save(a, out, rows, load0)
    if a.joint:
        from bench.bench_reoptimize import reoptimize_run

        run = reoptimize_run(root, 1, 0, params)  # one joint solve (--region-max-poses 0) of every map drive
        acc = corner_accuracy(mdir / run["version"], sim)
        run["corners"] = {key: v for key, v in acc.items() if key not in ("ids", "en")}
        run["load_1min_after"] = round(os.getloadavg()[0], 1)
        out["joint"] = run
        c_inc, c_joint = out["nights"][-1]["corners"]["rms_m"], run["corners"]["rms_m"]
        if c_inc is not None and c_joint is not None:
            out["rms_last_over_joint"] = round(c_inc / c_joint, 3)
            out["rms_last_minus_joint_mm"] = round(1000 * (c_inc - c_joint), 1)
        print(json.dumps({"joint": run}), flush=True)
        _save(a, out, rows, load0)
        if a.eval_drive is not None:
            out["eval"]["joint"] = evaluate_drive(root, run["version"], sim, a.eval_drive, work / "eval-joint")
            print(json.dumps({"eval_joint": out["eval"]["joint"]}), flush=True)
            _save(a, out, rows, load0)


def joint_build(a, sim: Path, work: Path, params: Path | None, load0: float) -> dict:
    """``--joint-only``: drives 0..N-1 delivered at once to a fresh map, one ``rebuild`` (a first version: the joint
    solve, as ``cornermap build``), its corners against the truth; then ``--eval-drive`` on it."""
    from mapservice.maps import create_map

    root, inbox = work / "root", work / "inbox"
    if not (root / "maps" / "city").is_dir():
        create_map(root, "city", ORIGIN, tile_size_m=a.tile_size_m)
    for k in range(a.drives):
        if not (inbox / f"drive_{k}").is_dir():
            deliver(sim, f"drive_{k}", inbox)
    for k in range(a.drives):  # a hard link changes its inode's ctime: READY is written again after every link
        (inbox / f"drive_{k}" / "READY").touch()
    load_start = os.getloadavg()[0]
    run = rebuild_night(root, inbox, True, params)  # --full: the joint solve even when a LATEST exists
    run["load_1min"] = [round(load_start, 1), round(os.getloadavg()[0], 1)]
    acc = corner_accuracy(root / "maps" / "city" / run["version"], sim)
    run["corners"] = {key: v for key, v in acc.items() if key not in ("ids", "en")}
    out = {"seed": json.loads((sim / "simulation.json").read_text()).get("seed"), "drives": a.drives,
           "mode": "joint: every drive in one rebuild on a fresh map", "joint": run,
           "machine": {**_machine(), "load_1min_before": load0}}
    print(json.dumps({"joint": run}), flush=True)
    if a.json:
        a.json.write_text(json.dumps(out, indent=1))
    if a.eval_drive is not None:
        out["eval"] = {"joint": evaluate_drive(root, run["version"], sim, a.eval_drive, work / "eval-joint")}
        print(json.dumps({"eval_joint": out["eval"]["joint"]}), flush=True)
        if a.json:
            a.json.write_text(json.dumps(out, indent=1))
    return out


def version_drift(root: Path, vdir: Path) -> dict | None:
    """The drift statistic a version's incremental solve wrote (``poses_optimized`` metadata, as ``maps show``): the
    frame test and, per region with loops, loops / chi2 / dof / threshold; None for a first or joint solve."""
    from pipeline.store import dataset_dir, read_manifest

    fp = json.loads((vdir / "manifest.json").read_text())["inputs"]["poses"]["fingerprint"]
    m = read_manifest(dataset_dir(root, "poses_optimized", fp)) or {}
    d = ((m.get("extra") or {}).get("incremental") or {}).get("drift")
    if not isinstance(d, dict):
        return None
    f = d.get("frame") or {}
    return {
        "frame_chi2": f.get("chi2"),
        "frame_threshold": f.get("threshold"),
        "advised": d.get("advised"),
        "regions": [
            {k: r.get(k) for k in ("region", "loops", "chi2", "dof", "threshold")}
            for r in d.get("regions", [])
            if r.get("loops")
        ],
    }


def posegraph_record(root: Path, vdir: Path) -> dict:
    """The incremental solve's own figures from the version's pose-graph report (``incremental``: wall seconds of
    pass 1, survey anchoring, loops, passes 2-3; held poses, map poses the loops reached, window poses)."""
    from pipeline.store import dataset_dir

    fp = json.loads((vdir / "manifest.json").read_text())["inputs"]["poses"]["fingerprint"]
    path = dataset_dir(root, "posegraph_report", fp) / "artifacts" / "all" / "posegraph_report.json"
    inc = (json.loads(path.read_text()).get("incremental") or {}) if path.is_file() else {}
    return {k: (round(v, 2) if isinstance(v, float) else v) for k, v in inc.items() if not isinstance(v, (dict, list))}


EVAL_KEYS = ("rms_2d_m", "p99_2d_m", "max_2d_m", "heading_rms_deg", "nees_mean", "startup_s", "epochs")


def evaluate_drive(root: Path, version: str, sim: Path, k: int, out_dir: Path) -> dict:
    """``cornermap evaluate --method ekf`` of drive ``k`` of ``sim`` on ``version``, against its true trajectory (a
    child process; exit 3 = a missed target or no coverage is a result). The EKF's figures per reference frame
    (``truth_in_map``, ``absolute``), the verdict, CPU and wall seconds."""
    import resource
    import time

    drive = sim / f"drive_{k}" / "drive.yaml"
    ref = sim / "truth" / f"drive_{k}_poses_tum.txt"
    cmd = [sys.executable, "-m", "mapservice", "evaluate", "--root", str(root), "--map", "city", "--map-version",
           version, "--drive", str(drive), "--reference", str(ref), "--method", "ekf", "--out", str(out_dir),
           "--json", "-q"]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if res.returncode not in (0, 3) or not res.stdout.strip():
        raise SystemExit(f"evaluate exited {res.returncode}: {res.stderr.strip()[-2000:]}")
    doc = json.loads(res.stdout)
    ekf = (doc.get("methods") or {}).get("ekf") or {}
    verdict = doc.get("verdict") or {}
    return {
        "drive": f"drive_{k}",
        "map_version": version,
        "exit_code": res.returncode,
        "cpu_s": round((after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), 2),
        "wall_s": round(wall, 2),
        "status": verdict.get("status"),
        "judged_against": (verdict.get("judged_against") or {}).get("ekf"),
        "missed": verdict.get("missed"),
        "coverage": verdict.get("coverage"),
        **{
            frame: {key: (ekf.get(frame) or {}).get(key) for key in EVAL_KEYS}
            for frame in ("truth_in_map", "absolute")
        },
    }


def reference_builds(a, out: dict, sim: Path, work: Path, params: Path | None, ref: int) -> None:
    """Drive ``ref`` as a one-drive build and added to a one-drive map of the earlier drive of its window (drive
    ref - 12, else drive 0); the ratios of night ref+1 (drive ``ref`` added to the grown map) to both."""
    from mapservice.maps import create_map

    base = ref - WINDOWS if ref >= WINDOWS else 0
    refs = out["refs"] = {"base_drive": f"drive_{base}", "drive": f"drive_{ref}"}
    grown = out["nights"][ref]["cpu_s"]
    r1, i1 = work / "ref_one", work / "ref_one_inbox"
    create_map(r1, "city", ORIGIN, tile_size_m=a.tile_size_m)
    deliver(sim, f"drive_{ref}", i1)
    refs["one_drive_build"] = rebuild_night(r1, i1, False, params)
    out["ref_over_one_drive_build"] = round(grown / refs["one_drive_build"]["cpu_s"], 3)
    r2, i2 = work / "ref_add", work / "ref_add_inbox"
    create_map(r2, "city", ORIGIN, tile_size_m=a.tile_size_m)
    deliver(sim, f"drive_{base}", i2)
    refs["base_one_drive_map"] = rebuild_night(r2, i2, False, params)
    deliver(sim, f"drive_{ref}", i2)
    refs["added_to_one_drive_map"] = rebuild_night(r2, i2, False, params)
    out["ref_over_added_to_one"] = round(grown / refs["added_to_one_drive_map"]["cpu_s"], 3)


def _save(a, out: dict, rows: list[dict], load_before: float) -> None:
    """The summary figures, then the JSON, the CSV and the figure as they stand."""
    ratios = [r["download_ratio"] for r in rows[1:] if r["download_ratio"] is not None]
    out["download_ratio_max"] = max(ratios) if ratios else None
    out["republished_untouched_total"] = sum(r["republished_untouched"] for r in rows[1:])
    out["machine"] = {**_machine(), "load_1min_before": load_before}
    if a.json:
        a.json.write_text(json.dumps(out, indent=1))
    if a.csv:
        _write_csv(a.csv, rows)
    if a.markdown:
        a.markdown.write_text(markdown_table(out, rows))
    if a.figure:
        m = out["machine"]
        loads = [v for n in out["nights"] for v in n.get("load_1min", [])] or [0.0]
        figure(
            rows,
            a.figure,
            f"growing preset, seed {out['seed']}, {len(rows)} nights, rebuild --no-gate; {m['cpu']}, "
            f"{m['cores']} cores shared with other sessions, load {min(loads):.1f}-{max(loads):.1f}",
        )


def markdown_table(out: dict, rows: list[dict]) -> str:
    lines = [
        "| night | drive | CPU s | wall s | pose graph CPU s | load | tiles: map, touched, republished (untouched) "
        "| download kB / touched tiles' kB / map kB | corners | precision | RMS mm |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r, n in zip(rows, out["nights"]):
        load = "-".join(f"{v:.0f}" for v in n.get("load_1min", []))
        changed = " (changed city)" if n.get("sees_changed_city") else ""
        lines.append(
            f"| {r['night']} | {r['drive']}{changed} | {r['cpu_s']:.1f} | {r['wall_s']:.0f} | "
            f"{r['posegraph_cpu_s'] or 0:.1f} | {load} | {r['n_tiles']}, {r['tiles_touched']}, "
            f"{r['tiles_republished']} ({r['republished_untouched']}) | {r['download_tile_bytes'] / 1e3:.0f} / "
            f"{r['touched_tile_bytes'] / 1e3:.0f} / {r['map_tile_bytes'] / 1e3:.0f} | {r['n_corners']} | "
            f"{r['precision']} | {1000 * r['rms_m']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def _write_csv(path: Path, rows: list[dict]) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=CSV_FIELDS)
        w.writeheader()
        w.writerows(rows)


if __name__ == "__main__":
    main()
