"""Loop measurements against the simulator's truth: each loop of the map drive verified again from the truth's
relative pose and from the estimate's, registered whole (the stage's default) and on the structure with height,
roll and pitch from the two road planes (``verify_once`` with ``ground_split``), and as
``loops.verify.ground_split: true`` verifies it (the structure's result where it moves the whole clouds' less than
0.3 m), from the estimate.

    .venv/bin/python -m bench.bench_loop_bias -w BUILD/bench_build.yaml --sim SIM [--params P.yaml] [--drive drive_0]

``BUILD``: a ``bench_build --keep`` root with the pose graph committed (``--params``: the file its run was made with);
``SIM``: the simulated folder with ``truth/``. Prints per loop the truth's along-track offset, each measurement's
error along and across, and the RMS and mean of the errors: a registration that is pulled towards zero offset
shows a mean along-track error of the opposite sign to the offsets. The benches are not installed with the
product: run them from the checkout, or with ``PYTHONPATH=CHECKOUT`` from elsewhere."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-w", "--workflow", type=Path, required=True)
    ap.add_argument("--sim", type=Path, required=True)
    ap.add_argument("--params", type=Path, default=None)
    ap.add_argument("--drive", default="drive_0")
    ap.add_argument("--max-loops", type=int, default=60, help="the first N loops of the drive onto itself")
    args = ap.parse_args()

    from types import SimpleNamespace

    from bench.bench_posegraph import truth_poses
    from pipeline.api import load_param_file
    from pipeline.plan import make_plan
    from pipeline.reader import StoreInputReader
    from pipeline.workflow import load_workflow
    from stages.common.geometry import se3_inverse
    from stages.common.records import Trajectory
    from stages.posegraph.compute import ScanLoader, read_drive_inputs
    from stages.posegraph.loops.clouds import vehicle_clouds
    from stages.posegraph.loops.verify import verify_loop, verify_once

    wf = load_workflow(args.workflow, param_overrides=load_param_file(args.params))
    plan = make_plan(wf, wf.root_dir(None))
    sp = plan.stages["posegraph"]
    if not sp.committed:
        raise SystemExit(f"{plan.root}: the pose graph of this plan is not committed; run it first (--params?)")
    out = StoreInputReader(plan.root, {k: (ds, sp.fingerprint) for k, ds in sp.decl.outputs.items()},
                           {k: None for k in sp.decl.outputs})
    ins = StoreInputReader(plan.root, dict(sp.inputs), {k: None for k in sp.inputs})
    opt = Trajectory.from_table(out.read("poses_optimized"), args.drive)
    T_est, T_true = opt.T, truth_poses(args.sim, args.drive, opt.stamp_ns)
    params = sp.decl.params(**sp.params)
    # the drive as the stage read it (its wheel odometry and span edges only where its params use them)
    map_drives, ref_drives = read_drive_inputs(SimpleNamespace(inputs=ins, params=params, settings=sp.settings))
    d = next((x for x in map_drives + ref_drives if x.name == args.drive), None)
    if d is None:
        raise SystemExit(f"no drive {args.drive!r} in this run's pose graph")
    rows = [r for r in out.read("loop_closures").to_pylist()
            if r["drive_a"] == r["drive_b"] == args.drive][:args.max_loops]
    if not rows:
        raise SystemExit(f"no loop of {args.drive} onto itself in this run")
    index = {int(s): k for k, s in enumerate(opt.scan_id)}
    pairs = [(index[r["scan_a"]], index[r["scan_b"]]) for r in rows]
    cfg = params.loops.verify
    clouds = vehicle_clouds([d], np.array([0, d.n]), np.array(sorted({k for p in pairs for k in p})),
                            ScanLoader(ins), cfg.voxel_m)
    print(f"{args.drive}: {len(pairs)} loops onto itself ({sum(r['accepted'] for r in rows)} accepted in the run)")
    print("| scans | true offset along m | whole, from truth: along / across cm | whole, from estimate | "
          "structure + road, from truth | structure + road, from estimate | loops.verify.ground_split, from estimate |"
          "\n|---|---|---|---|---|---|---|")
    errs: dict[str, list] = {}
    for (i, j), r in zip(pairs, rows):
        truth = se3_inverse(T_true[i]) @ T_true[j]
        cells = []
        estimate = se3_inverse(T_est[i]) @ T_est[j]
        runs = [("whole", "truth", lambda p: verify_once(clouds[i], clouds[j], p, cfg, False), truth),
                ("whole", "estimate", lambda p: verify_once(clouds[i], clouds[j], p, cfg, False), estimate),
                ("structure + road", "truth", lambda p: verify_once(clouds[i], clouds[j], p, cfg, True), truth),
                ("structure + road", "estimate", lambda p: verify_once(clouds[i], clouds[j], p, cfg, True), estimate),
                ("loops.verify.ground_split", "estimate",
                 lambda p: verify_loop(clouds[i], clouds[j], p, cfg.updated({"ground_split": True})), estimate)]
        along = truth[:2, 3] / max(np.linalg.norm(truth[:2, 3]), 1e-9)  # the direction of the offset
        for name, start, verify, prior in runs:
            v = verify(prior)
            e = v.T_i_j[:2, 3] - truth[:2, 3]
            e_al, e_ac = float(e @ along), float(e @ np.array([-along[1], along[0]]))
            errs.setdefault(f"{name}, from {start}", []).append((e_al, e_ac, np.linalg.norm(truth[:2, 3])))
            cells.append(f"{100 * e_al:+.1f} / {100 * e_ac:+.1f}{'' if v.accepted else ' (rejected)'}")
        print(f"| {r['scan_a']}-{r['scan_b']} | {np.linalg.norm(truth[:2, 3]):.2f} | " + " | ".join(cells) + " |")
    print()
    for name, v in errs.items():
        a = np.array(v)
        near = a[:, 2] < 5.0
        print(f"{name}: along-offset error RMS {100 * np.sqrt(np.mean(a[:, 0] ** 2)):.1f} cm, mean "
              f"{100 * a[:, 0].mean():+.1f} cm (offsets under 5 m: mean {100 * a[near, 0].mean():+.1f} cm over "
              f"{int(near.sum())}); across RMS {100 * np.sqrt(np.mean(a[:, 1] ** 2)):.1f} cm")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
