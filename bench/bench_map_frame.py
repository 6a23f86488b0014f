"""The map frame and the map's shape against the simulator's truth: the pose graph's stated frame error and
relative covariances (``stages/posegraph/map_frame.py``) next to the true ones, and the bound the GNSS allows.

    .venv/bin/python -m bench.bench_map_frame -w ROOT/workflow-*.yaml [--sim SIM] [--set KEY=VALUE ...]
    .venv/bin/python -m bench.bench_map_frame --root ROOT            # the root's committed poses, no solve

With ``-w`` the pose graph is solved in process on the root's committed inputs (the workflow's plan picks them;
without survey anchoring, as a drive without a survey cloud is built), ``--set`` overriding posegraph params; with
``--root`` alone the newest committed ``poses_optimized`` (its covariances and ``map_frame`` metadata) and
``poses_gnss`` are read as they are (a root whose scans were deleted still answers). Then, for the map drives:
- the true frame error: the travel-weighted least-squares frame change (shift at the stated reference point,
  rotation) that takes the truth onto the estimate, against the stated covariance (its NEES, 3 dof);
- the shape: the horizontal error left after that fit (RMS, max) against the stated relative covariances (NEES,
  2 dof; 2 when honest);
- the bound: the Cramer-Rao bound of the frame from GNSS fixes alone over a *perfect* shape, under the simulator's
  bias model (first-order Gauss-Markov of ``--bias-tau-s`` 90 s, the constant of ``stages/simulate/gnss.py``, per
  axis the drive's measured GNSS error RMS / sqrt 2, white 0.05 m), at one fix per second of the drive; and one
  sample of it, the true shape rigidly fitted to the GNSS fixes.
"""
from __future__ import annotations

import argparse
import json
import logging
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass
class MapDrives:
    names: list[str]
    est: np.ndarray  # (N,4,4) T_map_vehicle of the map drives
    cov_relative: np.ndarray  # (N,3,3) stated, relative to the frame
    cov_frame: np.ndarray  # (3,3)
    reference_en_m: np.ndarray  # (2,)
    group: np.ndarray  # (N,) drive index
    stamps_ns: np.ndarray  # (N,)
    gnss_T: np.ndarray  # (N,4,4)
    gnss_valid: np.ndarray  # (N,)
    loops: str = ""
    scale_std: float = float("nan")  # the frame's stated scale std (a 4-dof similarity fit)


def gnss_frame_bound(t_s: np.ndarray, en_m: np.ndarray, sigma_axis_m: float, tau_s: float, white_m: float,
                     reference_en_m: np.ndarray) -> np.ndarray:
    """(3,3) Cramer-Rao bound of (shift e, shift n, rotation) from fixes at ``t_s`` of a known shape ``en_m``
    whose errors are a Gauss-Markov bias (``sigma_axis_m``, ``tau_s``, per axis independent) plus white noise."""
    from stages.posegraph.map_frame import frame_basis

    dt = np.abs(t_s[:, None] - t_s[None, :])
    Ci = np.linalg.inv(sigma_axis_m**2 * np.exp(-dt / tau_s) + white_m**2 * np.eye(len(t_s)))
    G = frame_basis(en_m, reference_en_m)[:, :2, :]  # (N,2,3): the fixes measure position only
    info = sum(np.einsum("ia,ij,jb->ab", G[:, a, :], Ci, G[:, a, :]) for a in (0, 1))
    return np.linalg.inv(info)


def frame_error(est_en: np.ndarray, true_en: np.ndarray, yaw_err: np.ndarray, weights: np.ndarray,
                reference_en_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(g (3,), residual (N,3)): the weighted least-squares frame change of the errors and what it leaves."""
    from stages.posegraph.map_frame import _fit_operator, frame_basis

    e = np.column_stack([est_en - true_en, yaw_err])
    G = frame_basis(true_en, reference_en_m)
    g = np.einsum("nak,na->k", _fit_operator(G, weights), e)
    return g, e - np.einsum("nak,k->na", G, g)


def replace_fixes(drives, sim: Path, mode: str, white_m: float = 0.05, window_s: float = 15.0, seed: int = 0) -> None:
    """Diagnosis: the drives' GNSS positions (in place) replaced by ``truth`` (the true position + white noise of
    ``white_m``: no bias, no multipath) or ``slow`` (the true position + the fixes' own error under a running median
    of ``window_s``: the slowly varying bias kept, multipath jumps and white noise removed)."""
    from bench.bench_posegraph import truth_poses

    rng = np.random.default_rng(seed)
    for d in drives:
        tx = truth_poses(sim, d.name, d.stamps_ns)[:, :3, 3]
        v = d.gnss_valid
        err = d.gnss_T[:, :3, 3] - tx
        if mode == "truth":
            new = tx + rng.normal(size=tx.shape) * white_m
        elif mode == "slow":
            from scipy.ndimage import median_filter

            t_s = d.stamps_ns * 1e-9
            n_win = max(1, int(round(window_s / max(np.median(np.diff(t_s)), 1e-3))))
            smooth = err.copy()
            smooth[v] = median_filter(err[v], size=(n_win, 1), mode="nearest")
            new = tx + smooth
        else:
            raise ValueError(f"--fixes {mode!r}: expected asis | truth | slow")
        d.gnss_T = d.gnss_T.copy()
        d.gnss_T[v, :3, 3] = new[v]


def consecutive_scale_against_spans(d, min_chord_m: float = 5.0) -> float | None:
    """Least-squares ratio of the consecutive edges composed over each accepted span to the span's chord (planar),
    over the spans whose consecutive edges were all accepted; None without 10 such spans."""
    sp = d.spans
    if sp is None:
        return None
    num = den = 0.0
    used = 0
    for i, j, T in zip(sp.i, sp.j, sp.T_i_j):
        if not d.edge_ok[i + 1:j + 1].all():
            continue
        C = np.eye(4)
        for k in range(i + 1, j + 1):
            C = C @ d.edge_T[k]
        cc, cs = C[:2, 3], np.asarray(T[:2, 3], float)
        if np.linalg.norm(cs) < min_chord_m:
            continue
        num += float(cc @ cs)
        den += float(cs @ cs)
        used += 1
    return num / den if used >= 10 and den > 0 else None


def solved(workflow: Path, root: Path | None, overrides: list[str], fixes: str = "asis", sim: Path | None = None,
           loops_cache: Path | None = None, wheel_scale: str = "stage",
           icp_scale_from_spans: bool = False) -> tuple[MapDrives, Path]:
    """The map drives solved in process (no survey anchoring) with their frame split. ``fixes``: see
    ``replace_fixes``; ``loops_cache``: the accepted loops of a first run are stored there and reused as they are
    by later runs (no candidate search, no verification: the diagnosis varies the GNSS, not the loops)."""
    from bench.bench_posegraph import _overrides
    from pipeline.api import stage_context
    from pipeline.plan import make_plan
    from pipeline.workflow import load_workflow
    from stages.posegraph.compute import frame_of_map, read_drive_inputs, scan_loader
    from stages.posegraph.factors.graph import marginal_cov_xy_yaw
    from stages.posegraph.solve import solve_map

    wf = load_workflow(workflow, param_overrides={"posegraph": _overrides(overrides)})
    root = wf.root_dir(root)
    ctx = stage_context(make_plan(wf, root), "posegraph", Path(tempfile.mkdtemp(prefix="bench-frame-")))
    drives, _ = read_drive_inputs(ctx)
    if fixes != "asis":
        from bench.roots import simulator_dir

        replace_fixes(drives, sim or simulator_dir(root), fixes)
    if wheel_scale == "consecutive":  # the calibration before the span edges' scale (diagnosis)
        import copy

        from stages.posegraph.factors.wheel import calibrate_wheel

        for d in drives:
            if d.wheel_T is None or d.wheel_calibration is None:
                continue
            raw = copy.copy(d)
            raw.wheel_T = d.wheel_T.copy()
            raw.wheel_T[:, :2, 3] /= d.wheel_calibration.scale
            s_old = calibrate_wheel(raw, from_spans=False).scale
            d.wheel_T = raw.wheel_T
            d.wheel_T[:, :2, 3] *= s_old
            print(f"{d.name}: wheel scale {s_old:.6f} from the consecutive edges (the stage's: "
                  f"{d.wheel_calibration.scale:.6f} from the {d.wheel_calibration.scale_source})")
    if icp_scale_from_spans:  # diagnosis: the consecutive edges' along-track scale corrected on the span edges
        for d in drives:
            r = consecutive_scale_against_spans(d)
            if r is not None:
                d.edge_T = d.edge_T.copy()
                d.edge_T[:, :3, 3] /= r
                print(f"{d.name}: consecutive edges {(r - 1) * 1e6:+.0f} ppm against the span edges; divided out")
    cfg = ctx.params
    if loops_cache is not None and loops_cache.is_file():
        import pickle

        cached = pickle.loads(loops_cache.read_bytes())
        for r in cached:
            r.accepted = True
        no_search = cfg.model_copy(update={"loops": cfg.loops.model_copy(update={"radius_m": 0.0})})
        sol = solve_map(drives, scan_loader(ctx), no_search, extra_loops=cached)
    else:
        sol = solve_map(drives, scan_loader(ctx), cfg)
        if loops_cache is not None:
            import pickle

            loops_cache.write_bytes(pickle.dumps([r for r in sol.loops if r.accepted]))
    split = frame_of_map(sol, drives, marginal_cov_xy_yaw(sol.problem, sol.poses).reshape(-1, 3, 3))
    cat = np.concatenate
    return MapDrives([d.name for d in drives], sol.poses, split.cov_relative, split.cov_frame, split.reference_en_m,
                     np.repeat(np.arange(len(drives)), [d.n for d in drives]), cat([d.stamps_ns for d in drives]),
                     cat([d.gnss_T for d in drives]), cat([d.gnss_valid for d in drives]),
                     f"; loops accepted {sum(r.accepted for r in sol.loops)}", split.scale_std), root


def committed(root: Path) -> MapDrives:
    """The map drives' newest committed poses, their stated covariances and frame, and their GNSS/INS poses."""
    import pyarrow.compute as pc

    from bench.roots import latest, read
    from stages.common.records import Trajectory

    manifest = json.loads((latest(root, "poses_optimized") / "_manifest.json").read_text())
    frame = (manifest.get("extra") or {}).get("map_frame")
    if not frame:
        raise SystemExit(f"{root}: the committed poses_optimized states no map_frame (built before it existed)")
    names = list(manifest["settings"].get("map_drives") or sorted(manifest["drives"]))
    opt, gnss = read(root, "poses_optimized"), read(root, "poses_gnss")
    parts = []
    for k, name in enumerate(names):
        rows = opt.filter(pc.equal(opt["drive"], name)).sort_by("scan_id")
        cov = np.asarray(rows["cov_xy_yaw"].combine_chunks().flatten().to_numpy(), float).reshape(-1, 3, 3)
        g = gnss.filter(pc.equal(gnss["drive"], name)).sort_by("scan_id")
        keep = np.isin(g["scan_id"].to_numpy(), rows["scan_id"].to_numpy())
        parts.append((Trajectory.from_table(rows, name).T, cov, np.full(rows.num_rows, k), rows["stamp_ns"].to_numpy(),
                      Trajectory.from_table(g, name).T[keep], g["valid"].to_numpy(zero_copy_only=False)[keep]))
    cat = lambda i: np.concatenate([p[i] for p in parts])  # noqa: E731
    return MapDrives(names, cat(0), cat(1), np.asarray(frame["cov_shift_rotation"], float),
                     np.asarray(frame["reference_en_m"], float), cat(2), cat(3), cat(4), cat(5), "",
                     float(frame.get("std_scale", np.nan)))


def report(m: MapDrives, sim: Path, bias_tau_s: float, label: str) -> None:
    from bench.bench_posegraph import truth_poses
    from stages.common.geometry import fit_rigid_2d, wrap_angle_rad
    from stages.posegraph.map_frame import travel_weights

    truth = np.concatenate([truth_poses(sim, name, m.stamps_ns[m.group == k]) for k, name in enumerate(m.names)])
    yaw = lambda T: np.arctan2(T[:, 1, 0], T[:, 0, 0])  # noqa: E731
    w = travel_weights(m.est[:, :2, 3], m.group)
    g, resid = frame_error(m.est[:, :2, 3], truth[:, :2, 3], wrap_angle_rad(yaw(m.est) - yaw(truth)), w,
                           m.reference_en_m)
    cf, rel = m.cov_frame, m.cov_relative
    h = np.linalg.norm(resid[:, :2], axis=1)
    nees = np.einsum("na,nab,nb->n", resid[:, :2], np.linalg.inv(rel[:, :2, :2]), resid[:, :2])
    print(f"{label}; map drives {m.names}, {len(m.est)} poses{m.loops}")
    print(f"frame at ({m.reference_en_m[0]:.1f}, {m.reference_en_m[1]:.1f}) m: true shift ({g[0]:+.3f}, "
          f"{g[1]:+.3f}) m, rotation {np.degrees(g[2]):+.3f} deg; stated std ({np.sqrt(cf[0, 0]):.3f}, "
          f"{np.sqrt(cf[1, 1]):.3f}) m, "
          f"{np.degrees(np.sqrt(cf[2, 2])):.3f} deg; NEES (3 dof) {g @ np.linalg.solve(cf, g):.2f}")
    print(f"shape (error after the frame fit): horizontal RMS {np.sqrt(np.mean(h**2)):.3f} m, max {h.max():.3f} m, "
          f"heading RMS {np.degrees(np.sqrt(np.mean(resid[:, 2]**2))):.3f} deg; stated relative RMS "
          f"{np.sqrt(np.mean(np.trace(rel[:, :2, :2], axis1=1, axis2=2))):.3f} m; NEES (2 dof) mean {nees.mean():.2f}, "
          f"{np.mean(nees < 5.991):.2f} under its 95 % quantile")
    from stages.posegraph.map_frame import _fit_operator, frame_basis

    G4 = frame_basis(truth[:, :2, 3], m.reference_en_m, scale=True)
    e = np.column_stack([m.est[:, :2, 3] - truth[:, :2, 3], wrap_angle_rad(yaw(m.est) - yaw(truth))])
    g4 = np.einsum("nak,na->k", _fit_operator(G4, w), e)
    h4 = np.linalg.norm((e - np.einsum("nak,k->na", G4, g4))[:, :2], axis=1)
    fwd = np.column_stack([np.cos(yaw(truth)), np.sin(yaw(truth))])
    along, cross = np.sum(resid[:, :2] * fwd, axis=1), fwd[:, 0] * resid[:, 1] - fwd[:, 1] * resid[:, 0]
    print(f"shape after a similarity fit (+ scale {g4[3] * 1e6:+.0f} ppm, stated std {m.scale_std * 1e6:.0f} ppm): "
          f"horizontal RMS "
          f"{np.sqrt(np.mean(h4**2)):.3f} m, max {h4.max():.3f} m; "
          f"the rigid fit's residual along / across the road RMS "
          f"{np.sqrt(np.mean(along**2)):.3f} / {np.sqrt(np.mean(cross**2)):.3f} m")
    for k, name in enumerate(m.names):
        sel = m.group == k
        v, gx, tx = m.gnss_valid[sel], m.gnss_T[sel][:, :2, 3], truth[sel][:, :2, 3]
        t_s = m.stamps_ns[sel] * 1e-9
        if v.sum() < 3:
            print(f"{name}: {t_s[-1] - t_s[0]:.0f} s; no GNSS (placed by its prior trajectory / start pose)")
            continue
        err = np.linalg.norm(gx[v] - tx[v], axis=1)
        fix = np.flatnonzero(v)[::10] if v.sum() > 10 else np.flatnonzero(v)  # one fix per second at 10 Hz
        bound = gnss_frame_bound(t_s[fix], tx[fix], float(np.sqrt(np.mean(err**2) / 2)), bias_tau_s, 0.05,
                                 m.reference_en_m)
        R, t = fit_rigid_2d(tx[v], gx[v])
        ref = m.reference_en_m
        print(f"{name}: {t_s[-1] - t_s[0]:.0f} s; GNSS error RMS {np.sqrt(np.mean(err**2)):.3f} m; bound (CRB of a "
              f"perfect shape under the bias model, tau {bias_tau_s:.0f} s): shift std {np.sqrt(bound[0, 0]):.3f} / "
              f"{np.sqrt(bound[1, 1]):.3f} m, rotation {np.degrees(np.sqrt(bound[2, 2])):.3f} deg; one sample (true "
              f"shape fitted to the fixes): shift {np.linalg.norm(R @ ref + t - ref):.3f} m, rotation "
              f"{np.degrees(np.arctan2(R[1, 0], R[0, 0])):+.3f} deg")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-w", "--workflow", type=Path, default=None, help="solve in process with this workflow's plan")
    ap.add_argument("--root", type=Path, default=None)
    ap.add_argument("--sim", type=Path, default=None, help="the simulator's folder (default: the root's)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="posegraph param override")
    ap.add_argument("--bias-tau-s", type=float, default=90.0)
    ap.add_argument("--fixes", choices=["asis", "truth", "slow"], default="asis",
                    help="diagnosis (with -w): the GNSS positions as they are, the truth + 0.05 m white noise, or the "
                         "truth + the fixes' error under a 15 s running median (bias without multipath)")
    ap.add_argument("--wheel-scale", choices=["stage", "consecutive"], default="stage",
                    help="with -w: the wheel scale as the stage calibrates it, or from the consecutive ICP edges "
                         "(the calibration before the span edges' scale)")
    ap.add_argument("--icp-scale-from-spans", action="store_true",
                    help="with -w (diagnosis): divide the consecutive edges' translations by their ratio to the span "
                         "edges")
    ap.add_argument("--loops-cache", type=Path, default=None,
                    help="with -w: store the accepted loops here, or reuse them when the file exists")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    from bench.roots import simulator_dir

    if args.workflow is None and args.root is None:
        ap.error("give -w WORKFLOW (solve in process) or --root ROOT (its committed poses)")
    if args.workflow is not None:
        drives, root = solved(args.workflow, args.root, args.set, args.fixes, args.sim, args.loops_cache,
                              args.wheel_scale, args.icp_scale_from_spans)
        label = f"root {root}, solved in process"
    else:
        root = args.root
        drives, label = committed(root), f"root {root}, committed poses"
    report(drives, args.sim or simulator_dir(root), args.bias_tau_s, label)


if __name__ == "__main__":
    main()
