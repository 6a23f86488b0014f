"""The map frame and the map's shape against the simulator's truth: the pose graph's stated frame error and
relative covariances (``stages/posegraph/map_frame.py``) next to the true ones, and the bound the GNSS allows.

    .venv/bin/python -m bench.bench_map_frame -w ROOT/workflow-*.yaml [--sim SIM] [--set KEY=VALUE ...]

Solves the pose graph in process on a root's committed inputs (the workflow's plan picks them; without survey
anchoring, as a drive without a survey cloud is built), with ``--set`` overriding posegraph params, then for the
map drives together:
- the true frame error: the travel-weighted least-squares frame change (shift at the reference point, rotation)
  that takes the truth onto the estimate, against the stated ``cov_frame`` (its NEES, 3 dof);
- the shape: the horizontal error left after that fit (RMS, max) against the stated relative covariances (NEES,
  2 dof; 2 when honest), and what the map's corners see of it (the pose errors 30 m ahead of each pose);
- the bound: the Cramer-Rao bound of the frame from GNSS fixes alone over a *perfect* shape, under the simulator's
  bias model (first-order Gauss-Markov of ``--bias-tau-s`` 90 s, the constant of ``stages/simulate/gnss.py``, per
  axis the drive's measured GNSS error RMS / sqrt 2, white 0.05 m), at the drive's own fix epochs; and one sample of
  it, the true shape rigidly fitted to the GNSS fixes.
"""
from __future__ import annotations

import argparse
import logging
import tempfile
from pathlib import Path

import numpy as np


def gnss_frame_bound(t_s: np.ndarray, en_m: np.ndarray, weights: np.ndarray, sigma_axis_m: float, tau_s: float,
                     white_m: float, reference_en_m: np.ndarray) -> np.ndarray:
    """(3,3) Cramer-Rao bound of (shift e, shift n, rotation) from fixes at ``t_s`` of a known shape ``en_m``
    whose errors are a Gauss-Markov bias (``sigma_axis_m``, ``tau_s``, per axis independent) plus white noise."""
    from stages.posegraph.map_frame import frame_basis

    dt = np.abs(t_s[:, None] - t_s[None, :])
    C = sigma_axis_m**2 * np.exp(-dt / tau_s) + white_m**2 * np.eye(len(t_s))
    Ci = np.linalg.inv(C)
    G = frame_basis(en_m, reference_en_m)[:, :2, :]  # (N,2,3): the fixes measure position only
    info = np.einsum("ia,ij,jb->ab", G[:, 0, :], Ci, G[:, 0, :]) + np.einsum("ia,ij,jb->ab", G[:, 1, :], Ci,
                                                                             G[:, 1, :])
    return np.linalg.inv(info)


def frame_error(est_en: np.ndarray, true_en: np.ndarray, yaw_err: np.ndarray, weights: np.ndarray,
                reference_en_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(g (3,), residual (N,3)): the weighted least-squares frame change of the errors and what it leaves."""
    from stages.posegraph.map_frame import _fit_operator, frame_basis

    e = np.column_stack([est_en - true_en, yaw_err])
    G = frame_basis(true_en, reference_en_m)
    M = _fit_operator(G, weights)
    g = np.einsum("nak,na->k", M, e)
    return g, e - np.einsum("nak,k->na", G, g)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-w", "--workflow", type=Path, required=True)
    ap.add_argument("--root", type=Path, default=None)
    ap.add_argument("--sim", type=Path, default=None, help="the simulator's folder (default: the root's)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="posegraph param override")
    ap.add_argument("--bias-tau-s", type=float, default=90.0)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)

    from bench.bench_posegraph import _overrides, truth_poses
    from bench.roots import simulator_dir
    from pipeline.api import stage_context
    from pipeline.plan import make_plan
    from pipeline.workflow import load_workflow
    from stages.common.geometry import fit_rigid_2d, wrap_angle_rad
    from stages.posegraph.compute import frame_of_map, read_drive_inputs, scan_loader
    from stages.posegraph.config import PosegraphConfig
    from stages.posegraph.factors.graph import marginal_cov_xy_yaw
    from stages.posegraph.solve import solve_map

    wf = load_workflow(args.workflow, param_overrides={"posegraph": _overrides(args.set)})
    root = wf.root_dir(args.root)
    plan = make_plan(wf, root)
    ctx = stage_context(plan, "posegraph", Path(tempfile.mkdtemp(prefix="bench-frame-")))
    cfg = PosegraphConfig.from_params(ctx.params)
    drives, _ = read_drive_inputs(ctx)
    sim = args.sim or simulator_dir(root)
    sol = solve_map(drives, scan_loader(ctx), cfg)
    cov = marginal_cov_xy_yaw(sol.problem, sol.poses).reshape(-1, 3, 3)
    split = frame_of_map(sol, drives, cov)
    truth = np.concatenate([truth_poses(sim, d.name, d.stamps_ns) for d in drives])
    est = sol.poses
    group = np.repeat(np.arange(len(drives)), [d.n for d in drives])
    from stages.posegraph.map_frame import travel_weights

    w = travel_weights(truth[:, :2, 3], group)
    yaw = lambda T: np.arctan2(T[:, 1, 0], T[:, 0, 0])  # noqa: E731
    g, resid = frame_error(est[:, :2, 3], truth[:, :2, 3], wrap_angle_rad(yaw(est) - yaw(truth)), w,
                           split.reference_en_m)
    cf = split.cov_frame
    nees_frame = float(g @ np.linalg.solve(cf, g))
    print(f"root {root}; map drives {[d.name for d in drives]}, {len(est)} poses; loops accepted "
          f"{sum(r.accepted for r in sol.loops)}")
    print(f"frame at ({split.reference_en_m[0]:.1f}, {split.reference_en_m[1]:.1f}) m: true shift "
          f"({g[0]:+.3f}, {g[1]:+.3f}) m, rotation {np.degrees(g[2]):+.3f} deg; stated std "
          f"({np.sqrt(cf[0, 0]):.3f}, {np.sqrt(cf[1, 1]):.3f}) m, {np.degrees(np.sqrt(cf[2, 2])):.3f} deg, scale "
          f"{split.scale_std:.2e}; NEES (3 dof) {nees_frame:.2f}")
    h = np.linalg.norm(resid[:, :2], axis=1)
    rel = split.cov_relative
    nees = np.einsum("na,nab,nb->n", resid[:, :2], np.linalg.inv(rel[:, :2, :2]), resid[:, :2])
    print(f"shape (error after the frame fit): horizontal RMS {np.sqrt(np.mean(h**2)):.3f} m, max {h.max():.3f} m, "
          f"heading RMS {np.degrees(np.sqrt(np.mean(resid[:, 2]**2))):.3f} deg; stated relative RMS "
          f"{np.sqrt(np.mean(np.trace(rel[:, :2, :2], axis1=1, axis2=2))):.3f} m; NEES (2 dof) mean {nees.mean():.2f}, "
          f"{np.mean(nees < 5.991):.2f} under its 95 % quantile; absolute stated RMS "
          f"{np.sqrt(np.mean(cov[:, 0, 0] + cov[:, 1, 1])):.3f} m")
    for d, a, b in zip(drives, np.cumsum([0] + [x.n for x in drives])[:-1], np.cumsum([x.n for x in drives])):
        v = d.gnss_valid
        gx = d.gnss_T[:, :2, 3]
        tx = truth[a:b, :2, 3]
        R, t = fit_rigid_2d(tx[v], gx[v])
        err_g = np.linalg.norm(gx[v] - tx[v], axis=1)
        sigma_axis = float(np.sqrt(np.mean(err_g**2) / 2))
        t_s = d.stamps_ns * 1e-9
        fix = np.flatnonzero(v)[::10] if v.sum() > 10 else np.flatnonzero(v)
        ref = np.average(tx, axis=0, weights=w[a:b])
        bound = gnss_frame_bound(t_s[fix], tx[fix], w[a:b][fix], sigma_axis, args.bias_tau_s, 0.05, ref)
        off = np.linalg.norm(R @ ref + t - ref)
        print(f"{d.name}: {t_s[-1] - t_s[0]:.0f} s; GNSS error RMS {np.sqrt(np.mean(err_g**2)):.3f} m; bound (CRB of "
              f"a perfect shape under the bias model, tau {args.bias_tau_s:.0f} s): shift std "
              f"{np.sqrt(bound[0, 0]):.3f} / {np.sqrt(bound[1, 1]):.3f} m, rotation "
              f"{np.degrees(np.sqrt(bound[2, 2])):.3f} deg; one sample (true shape fitted to the fixes): shift "
              f"{off:.3f} m, rotation "
              f"{np.degrees(np.arctan2(R[1, 0], R[0, 0])):+.3f} deg")


if __name__ == "__main__":
    main()
