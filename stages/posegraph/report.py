"""The posegraph report: JSON (loops, GNSS residuals, largest edge residuals, timings) and PNG plots."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from stages.posegraph.factors.gnss import gnss_residuals_enu
from stages.posegraph.factors.graph import between_residuals


def _drive_of(offsets: np.ndarray, i: int) -> int:
    return int(np.searchsorted(offsets, i, side="right") - 1)


def summarize_solution(drives, sol, top_k: int = 10) -> dict:
    offsets = np.cumsum([0] + [d.n for d in drives])
    res_gnss = gnss_residuals_enu(sol.poses, sol.problem.positions)
    odo = [b for b in sol.problem.betweens if b.kind not in ("loop", "prior")]  # ICP edges, wheel factors, bridges
    res_odo = between_residuals(odo, sol.poses) if odo else np.zeros(0)
    worst = np.argsort(res_odo)[::-1][:top_k]
    edges = []
    for n in worst:
        b = odo[n]
        o = _drive_of(offsets, b.j)
        edges.append({"drive": drives[o].name, "scan_id": int(drives[o].scan_ids[b.j - offsets[o]]),
                      "kind": b.kind, "whitened_residual": float(res_odo[n])})
    h = np.linalg.norm(res_gnss[:, :2], axis=1) if len(res_gnss) else np.zeros(0)
    return {
        "n_poses": int(sol.problem.n_poses), "n_gnss_factors": len(sol.problem.positions),
        "n_bridges": sum(b.kind == "bridge" for b in sol.problem.betweens),
        "n_wheel_bridges": sum(b.kind == "wheel" for b in sol.problem.betweens),
        "n_wheel_fused": sum(b.kind == "wheel_fused" for b in sol.problem.betweens),
        "n_span_edges": sum(b.kind == "span" for b in sol.problem.betweens),
        "n_prior_factors": sum(b.kind == "prior" for b in sol.problem.betweens)
        + sum(p.kind in ("prior", "start") for p in sol.problem.pose_priors),
        "wheel_calibration": {d.name: vars(d.wheel_calibration) for d in drives if d.wheel_calibration is not None},
        "gnss_residual_horizontal_rms_m": float(np.sqrt(np.mean(h ** 2))) if h.size else None,
        "gnss_residual_horizontal_max_m": float(h.max()) if h.size else None,
        "loops_candidates": len(sol.loops), "loops_accepted": sum(r.accepted for r in sol.loops),
        "largest_edge_residuals": edges, "timings_s": sol.timings_s, "survey_rounds": sol.survey_rounds,
    }


def _anchor_record(drives, offsets: np.ndarray, m) -> dict:
    """One survey anchor: the keyframe, the ground registration's decision, and the marking match's claimed
    absolute horizontal position (estimate at match time + shift) with its standard deviations."""
    o = _drive_of(offsets, m.i)
    rec = {"drive": drives[o].name, "scan_id": int(drives[o].scan_ids[m.i - offsets[o]]),
           "vertical_accepted": bool(m.accepted), "vertical_reason": m.reason, "fitness": float(m.fitness)}
    h = m.horizontal
    if h is not None:
        rec.update({"horizontal_accepted": bool(h.accepted), "horizontal_reason": h.reason,
                    "marking_score": float(h.score), "n_features": int(h.n_features),
                    "shift_en_m": [float(v) for v in h.shift_en_m], "yaw_deg": float(np.degrees(h.yaw_rad))})
        if h.accepted:
            cov = np.linalg.pinv(np.asarray(h.information_en, float))
            rec.update({"anchor_en_m": [float(v) for v in m.T_map_vehicle[:2, 3] + h.shift_en_m],
                        "anchor_cov_en_m2": [float(v) for v in cov.reshape(-1)]})
    return rec


def write_report(out_dir: Path, drives, sol, refs: dict, loop_rows: list[dict], survey_matches,
                 error_kernel: dict | None = None, map_frame: dict | None = None,
                 incremental: dict | None = None) -> Path:
    out_dir = Path(out_dir)
    offsets = np.cumsum([0] + [d.n for d in drives])
    report = {"map_drives": [d.name for d in drives], "reference_drives": sorted(refs),
              "map": summarize_solution(drives, sol),
              "references": {name: summarize_solution([d], ref) for name, (d, ref) in refs.items()},
              "survey_anchors": {"tried": len(survey_matches),
                                 "accepted": sum(m.accepted for m in survey_matches),
                                 "horizontal_accepted": sum(bool(m.horizontal is not None and m.horizontal.accepted)
                                                            for m in survey_matches),
                                 "records": [_anchor_record(drives, offsets, m) for m in survey_matches]},
              "loops": loop_rows, "pose_error_correlation": error_kernel, "map_frame": map_frame,
              "incremental": incremental}
    path = out_dir / "posegraph_report.json"
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(report, indent=1, default=float))
    os.replace(tmp, path)
    plot_report(out_dir, drives, sol)
    return path


def plot_report(out_dir: Path, drives, sol) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    offsets = np.cumsum([0] + [d.n for d in drives])
    stamps_s = np.concatenate([d.stamps_ns for d in drives]) * 1e-9 if drives else np.zeros(0)
    res = gnss_residuals_enu(sol.poses, sol.problem.positions)
    idx = np.array([g.i for g in sol.problem.positions], dtype=np.int64)
    fig, ax = plt.subplots(figsize=(9, 4))
    for o, d in enumerate(drives):
        m = (idx >= offsets[o]) & (idx < offsets[o + 1])
        t = stamps_s[idx[m]] - stamps_s[offsets[o]] if m.any() else np.zeros(0)
        ax.plot(t, res[m, 0], ".", ms=2, label=f"{d.name} east")
        ax.plot(t, res[m, 1], ".", ms=2, label=f"{d.name} north")
    ax.set_xlabel("time since drive start [s]")
    ax.set_ylabel("optimised - GNSS [m]")
    ax.set_title("GNSS residuals over time")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out_dir / "gnss_residuals.png", dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(7, 7))
    ax.plot(sol.poses[:, 0, 3], sol.poses[:, 1, 3], "-", lw=0.6, color="0.4")
    for r in sol.loops:
        a, b = sol.poses[r.i, :2, 3], sol.poses[min(r.j, len(sol.poses) - 1), :2, 3]
        ax.plot([a[0], b[0]], [a[1], b[1]], "-", color="tab:green" if r.accepted else "tab:red", lw=0.8)
    ax.set_aspect("equal")
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_title("loop closures (green accepted, red rejected)")
    fig.tight_layout()
    fig.savefig(out_dir / "loops.png", dpi=110)
    plt.close(fig)
