"""Localization accuracy per simulated city seed: simulate -> build -> evaluate through the engine, one workflow
per seed, then per-seed and worst-case rows (EKF and MCL): against the truth fitted onto the map's corners (the
verdict's judge), the pose graph's poses of the drive, and the truth as written. The EKF rows count the epochs from
its first map-corner association on; each seed's line gives its start-up and its all-epoch figures.

    .venv/bin/python -m bench.bench_seeds --preset tiny --seeds 11 12 13 14 15 --root /work/scratch-x/seeds

Each seed runs ``workflows/<preset>.yaml`` with ``params.simulate.seed`` changed, under ``ROOT/<preset>-<seed>``
(the engine skips stages whose fingerprints are committed, so a second run only redoes what changed).
``--fresh-evaluate`` drops the committed evaluate outputs first (after a code change that does not change the
evaluate params). Which seeds are calibration and which validation seeds: docs/evaluation.md.

``--no-survey`` builds the same cities without a survey cloud: the simulator runs first into
``ROOT/<preset>-<seed>/sim`` (``stages.simulate.core.simulate``, the preset's defaults plus ``--sim-set``
overrides), the ``survey:`` section of every drive file is deleted, and the workflow reads those drive files (no
simulate stage; the truth and the drive folders stay in ``sim/``, where ``bench.roots.simulator_dir`` finds them):

    .venv/bin/python -m bench.bench_seeds --preset tiny --seeds 201 202 --root /work/scratch-x/seeds --no-survey
"""
from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import time
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
EKF_COLS = [("rms_2d_m", "RMS m", 3), ("p99_2d_m", "p99 m", 3), ("max_2d_m", "max m", 3),
            ("heading_rms_deg", "hdg deg", 3), ("nees_mean", "NEES", 2), ("nees_share_below_q95", "<chi2", 2)]
MCL_COLS = [("mean_abs_x_m", "|x| m", 3), ("mean_abs_y_m", "|y| m", 3), ("mean_abs_heading_deg", "|hdg| deg", 3)]
# metrics.json entries: the truth fitted onto the map's corners (the verdict's judge), the pose graph's poses of the
# drive, the truth as written.
FRAMES = ("truth_in_map", "map_relative", "absolute")
# Worst = largest, except the share of epochs under the chi-square quantile (smallest); NEES: farthest from 3.
WORST_MIN = {"nees_share_below_q95"}


def simulate_without_survey(preset: str, seed: int, sim_dir: Path, overrides: dict | None = None) -> list[Path]:
    """The simulator's output for (preset, seed) in ``sim_dir`` (simulated once: reused when its
    ``simulation.json`` is there), every drive file's ``survey:`` section deleted; returns the drive files."""
    from stages.simulate.core import simulate
    from stages.simulate.presets import get_preset

    if not (sim_dir / "simulation.json").is_file():
        simulate(get_preset(preset, **(overrides or {})), seed, sim_dir)
    drives = sorted(sim_dir.glob("drive_*/drive.yaml"), key=lambda p: int(p.parent.name.split("_")[1]))
    for path in drives:
        text = path.read_text()
        doc = yaml.safe_load(text)
        if doc.pop("survey", None) is not None:
            header = "".join(line + "\n" for line in text.splitlines() if line.startswith("#"))
            path.write_text(header + "# survey: deleted (bench_seeds --no-survey)\n"
                            + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=110))
    return drives


def without_simulate(spec: dict, sim_dir: Path) -> dict:
    """A workflow of the seed's preset that reads the drive files in ``sim_dir`` instead of simulating."""
    spec["stages"] = [s for s in spec["stages"] if s != "simulate"]
    spec["params"].pop("simulate", None)
    for d in spec["drives"]:
        for key in ("path", "reference"):
            if d.get(key):
                d[key] = d[key].replace("${raw_drives}", str(sim_dir))
    return spec


def write_workflow(preset: str, seed: int, run_dir: Path, methods: list[str] | None,
                   ekf_motion: str | None = None, evaluate_params: dict | None = None,
                   no_survey: bool = False, sim_overrides: dict | None = None) -> Path:
    spec = yaml.safe_load((REPO / "workflows" / f"{preset}.yaml").read_text())
    spec["root"] = str(run_dir)
    spec["name"] = f"{preset}-{seed}"
    spec["params"].setdefault("simulate", {})["seed"] = seed
    if methods:
        spec["params"].setdefault("evaluate", {})["methods"] = methods
    if ekf_motion:
        spec["params"].setdefault("evaluate", {}).setdefault("ekf", {})["motion"] = ekf_motion
    if evaluate_params:
        from bench.params_args import merged

        spec["params"]["evaluate"] = merged(spec["params"].get("evaluate", {}), evaluate_params)
    if sim_overrides and not no_survey:
        spec["params"]["simulate"]["preset_overrides"] = dict(sim_overrides)
    if no_survey:
        simulate_without_survey(preset, seed, run_dir / "sim", sim_overrides)
        spec = without_simulate(spec, run_dir / "sim")
    path = run_dir / f"workflow-{hashlib.sha256(yaml.safe_dump(spec).encode()).hexdigest()[:8]}.yaml"  # stable name
    run_dir.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


def latest_metrics(run_dir: Path) -> dict:
    from bench.roots import latest

    files = sorted(latest(run_dir, "eval_report").glob("artifacts/*/metrics.json"), key=lambda p: p.stat().st_mtime)
    if not files:
        raise SystemExit(f"{run_dir}: no eval_report/*/metrics.json after the run")
    return json.loads(files[-1].read_text())


def frame_metrics(doc: dict, method: str, frame: str) -> dict:
    m = doc.get("methods", {}).get(method, {})
    return dict(m.get(frame) or {})


def fmt(v, nd: int) -> str:
    return "nan" if v is None or not np.isfinite(v) else f"{v:.{nd}f}"


def print_table(title: str, rows: dict[int, dict], cols) -> None:
    print(f"\n{title}")
    print("| seed | " + " | ".join(c[1] for c in cols) + " |")
    print("|---" * (len(cols) + 1) + "|")
    for seed, r in rows.items():
        print(f"| {seed} | " + " | ".join(fmt(r.get(k, np.nan), nd) for k, _, nd in cols) + " |")
    worst = []
    for k, _, nd in cols:
        vals = np.array([r.get(k, np.nan) for r in rows.values()], dtype=float)
        vals = vals[np.isfinite(vals)]
        if not len(vals):
            worst.append("nan")
        elif k in WORST_MIN:
            worst.append(fmt(vals.min(), nd))
        elif k == "nees_mean":
            worst.append(fmt(vals[np.argmax(np.abs(vals - 3.0))], nd))
        else:
            worst.append(fmt(vals.max(), nd))
    print("| worst | " + " | ".join(worst) + " |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="tiny", choices=sorted(p.stem for p in (REPO / "workflows").glob("*.yaml")
                                                               if p.stem != "map_rebuild"))
    ap.add_argument("--seeds", type=int, nargs="+", required=True)
    ap.add_argument("--root", type=Path, required=True, help="scratch folder for the per-seed runs")
    ap.add_argument("--fresh-evaluate", action="store_true", help="recompute the evaluate stage")
    ap.add_argument("--methods", nargs="+", choices=["ekf", "mcl"], default=None)
    ap.add_argument("--ekf-motion", choices=["wheel_bias", "icp"], default=None,
                    help="the EKF motion model (default: the evaluate params' default)")
    ap.add_argument("--set", nargs="+", default=[], metavar="NAME=VALUE",
                    help="evaluate params for calibration runs (only on calibration seeds), by their place in the "
                         "sections, e.g. ekf.map.consider=false")
    ap.add_argument("--no-survey", action="store_true",
                    help="delete the survey: section of every simulated drive file before building")
    ap.add_argument("--sim-set", nargs="+", default=[], metavar="KEY=VALUE",
                    help="simulator preset fields (as `cornermap simulate --set`), e.g. gnss_target_rms_m=1.5")
    ap.add_argument("--only", nargs="+", default=None, metavar="STAGE",
                    help="run only these stages (e.g. the stages before the pose graph while its code changes); "
                         "no tables")
    args = ap.parse_args()

    from bench.params_args import nested
    from pipeline.api import execute_workflow
    from pipeline.errors import CornermapError
    from stages.simulate.cli import parse_overrides

    rows = {f: {"ekf": {}, "mcl": {}} for f in FRAMES}
    for seed in args.seeds:
        run_dir = (args.root / f"{args.preset}-{seed}").resolve()
        wf = write_workflow(args.preset, seed, run_dir, args.methods, args.ekf_motion,
                            nested({k: yaml.safe_load(v) for k, v in (a.split("=", 1) for a in args.set)}),
                            no_survey=args.no_survey, sim_overrides=parse_overrides(args.sim_set))
        if args.fresh_evaluate:
            for ds in ("eval_epochs", "eval_report"):
                shutil.rmtree(run_dir / "datasets" / ds, ignore_errors=True)
        t0 = time.perf_counter()
        try:
            execute_workflow(wf, root=None, scheduler=None, only=args.only, dry_run=False, quiet=True)
        except CornermapError as exc:  # a build that publishes no map is a result too: reported, not skipped
            print(f"seed {seed}: FAILED after {time.perf_counter() - t0:.0f} s: {str(exc).splitlines()[0]} "
                  f"{' '.join(str(exc).splitlines()[1:2])}", flush=True)
            continue
        if args.only:
            print(f"seed {seed}: {' '.join(args.only)} done in {time.perf_counter() - t0:.0f} s, {run_dir}", flush=True)
            continue
        doc = latest_metrics(run_dir)
        print(f"seed {seed}: {time.perf_counter() - t0:.0f} s, {run_dir}", flush=True)
        for frame in rows:
            for method in ("ekf", "mcl"):
                rows[frame][method][seed] = frame_metrics(doc, method, frame)
        ekf = rows["truth_in_map"]["ekf"][seed] or rows["map_relative"]["ekf"][seed]
        print(f"  EKF start-up {fmt(ekf.get('startup_s'), 1)} s ({(ekf.get('localized_from_epoch'))} epochs; "
              f"its RMS / max {fmt((ekf.get('startup') or {}).get('rms_2d_m'), 3)} / "
              f"{fmt((ekf.get('startup') or {}).get('max_2d_m'), 3)} m); all epochs, judge: "
              + " ".join(f"{k}={fmt((ekf.get('all_epochs') or {}).get(k), 3)}"
                         for k in ("rms_2d_m", "p99_2d_m", "max_2d_m", "heading_rms_deg", "nees_mean")), flush=True)
        for frame in rows:  # one line per seed as it finishes (the tables follow at the end)
            e, m = rows[frame]["ekf"][seed], rows[frame]["mcl"][seed]
            print(f"  {frame}: EKF " + " ".join(f"{lab}={fmt(e.get(k, np.nan), nd)}" for k, lab, nd in EKF_COLS)
                  + " | MCL " + " ".join(f"{lab}={fmt(m.get(k, np.nan), nd)}" for k, lab, nd in MCL_COLS), flush=True)
    for frame in rows:
        print_table(f"EKF, {frame} ({args.preset})", rows[frame]["ekf"], EKF_COLS)
        print_table(f"MCL, {frame} ({args.preset})", rows[frame]["mcl"], MCL_COLS)


if __name__ == "__main__":
    main()
