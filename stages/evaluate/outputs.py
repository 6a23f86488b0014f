"""What an evaluation writes: the eval_epochs table, metrics.json, TUM trajectories and report.html."""
from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import numpy as np
import pyarrow as pa

from stages.evaluate.metrics import METRIC_KEYS, compute_errors
from stages.evaluate.run import Evaluation

log = logging.getLogger(__name__)

# The papers' figures beside the targets (Im et al. 2016 Table 3; Kim et al. Table 2); targets are in the params.
PAPER = {
    "ekf": {"rms_2d_m": 0.138, "p95_2d_m": 0.25, "p99_2d_m": 0.33, "max_2d_m": 0.46, "heading_rms_deg": 0.168},
    "mcl": {"mean_abs_x_m": 0.125, "mean_abs_y_m": 0.129, "mean_abs_heading_deg": 0.195},
}
METHOD_ORDER = ("ekf", "mcl", "rtk_ins", "icp_dr")


def epochs_table(ev: Evaluation, drive: str | None = None) -> pa.Table:
    from schemas import schema_of

    schema = schema_of("eval_epochs")
    ref = ev.references.get(ev.primary) if ev.primary else None
    cols: dict[str, list] = {name: [] for name in schema.names}
    for method in (m for m in METHOD_ORDER if m in ev.runs):
        r = ev.runs[method]
        ok = np.all(np.isfinite(r.q), axis=1)
        k = np.flatnonzero(ok)
        P = r.P[k] if r.P is not None else np.full((len(k), 3, 3), np.nan)
        e = compute_errors(r.q[k], ref[k] if ref is not None else np.full((len(k), 3), np.nan), None)
        cols["method"] += [method] * len(k)
        cols["epoch"] += k.tolist()
        cols["stamp_ns"] += ev.stamps_ns[k].tolist()
        for i, name in enumerate(("x_m", "y_m", "yaw_rad")):
            cols[name] += r.q[k, i].tolist()
        cols["cov_xy_yaw"] += P.reshape(len(k), 9).tolist()
        cols["err_x_m"] += e.err_xy_m[:, 0].tolist()
        cols["err_y_m"] += e.err_xy_m[:, 1].tolist()
        cols["err_yaw_rad"] += e.err_yaw_rad.tolist()
        cols["err_lateral_m"] += e.err_lateral_m.tolist()
        cols["err_longitudinal_m"] += e.err_longitudinal_m.tolist()
        counts = r.n_associated[k].astype(int).tolist()
        zeros = [0] * len(k)
        cols["n_associated"] += zeros if method == "mcl" else counts
        cols["n_features"] += counts if method == "mcl" else zeros
        err = np.column_stack([e.err_xy_m, e.err_yaw_rad])
        with np.errstate(invalid="ignore"):
            ok_p = np.all(np.isfinite(P.reshape(len(k), 9)), axis=1) & np.all(np.isfinite(err), axis=1)
            nees = np.full(len(k), np.nan)
            if ok_p.any():
                nees[ok_p] = np.einsum("ni,ni->n", err[ok_p], np.linalg.solve(P[ok_p], err[ok_p][..., None])[..., 0])
        cols["nees"] += [None if not np.isfinite(v) else float(v) for v in nees]
        if "drive" in cols:
            cols["drive"] += [drive] * len(k)
    return pa.table({name: pa.array(cols[name], type=schema.field(name).type) for name in schema.names},
                     schema=schema)


def metrics_document(ev: Evaluation, drive: str | None, map_info: dict, verdict: dict | None = None,
                     comparison: dict | None = None) -> dict:
    """metrics.json: per method its metrics against the primary reference, each reference beside, the targets
    judged (``verdict``, see stages.evaluate.verdict) and, when the map has a previous version, ``comparison``."""
    methods = {}
    for m in (m for m in METHOD_ORDER if m in ev.runs):
        by_ref = ev.metrics.get(m, {})
        primary = by_ref.get(ev.primary, {key: None for key in METRIC_KEYS}) if ev.primary else {}
        r = ev.runs[m]
        n_run = int(np.all(np.isfinite(r.q), axis=1).sum())
        methods[m] = {**primary, "map_relative": by_ref.get("map"), "absolute": by_ref.get("truth"),
                      "truth_in_map": by_ref.get("truth_in_map"),
                      "seconds": round(r.seconds, 4),
                      "epochs_per_s": round(n_run / r.seconds, 1) if r.seconds > 0 else None,
                      "targets": (verdict or {}).get("targets", {}).get(m)}
        if r.marking_rows is not None:  # the EKF's road-marking measurement: how often it measured, how often gated
            ran = np.all(np.isfinite(r.q), axis=1)
            methods[m]["markings"] = {"share_measured": round(float(np.mean(r.marking_rows[ran] > 0)), 3) if ran.any()
                                      else 0.0, "gated_out": int(np.sum(r.marking_rows < 0))}
    doc = {"drive": drive, "map": map_info, "primary_reference": ev.primary,
           "references": sorted(ev.references), "methods": methods}
    if verdict is not None:
        doc["verdict"] = verdict
    if comparison is not None:
        doc["comparison"] = comparison
    return doc


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


def planar_tum_text(stamps_ns: np.ndarray, q: np.ndarray, header: list[str]) -> str:
    """TUM rows of planar poses (x, y, yaw): z = 0, roll = pitch = 0, the stamp exact from integer ns; epochs with a
    non-finite pose are left out."""
    ok = np.all(np.isfinite(q), axis=1)
    sec, frac = np.divmod(np.asarray(stamps_ns, np.int64)[ok], 1_000_000_000)
    rows = [f"{s}.{f:09d} {x:.6f} {y:.6f} 0.000000 0.000000000 0.000000000 {np.sin(yaw / 2):.9f} {np.cos(yaw / 2):.9f}"
            for s, f, (x, y, yaw) in zip(sec.tolist(), frac.tolist(), q[ok].tolist())]
    return "".join(f"# {h}\n" for h in header) + "".join(r + "\n" for r in rows)


def write_tum_files(out_dir: Path, ev: Evaluation, origin: dict | None = None) -> list[Path]:
    """``<method>_tum.txt`` per method and ``reference_<name>_tum.txt`` per reference (at the epochs, as the metrics
    used them), all planar in the map frame, each with a header naming frame, origin and attitude. evo's defaults
    on a method and a reference file give the metrics' RMS (translation) and, with ``--pose_relation angle_deg``,
    the heading RMS of the same epochs."""
    from stages.common.geodesy import EnuOrigin
    from stages.common.trajectory_frame import attitude_header, frame_header

    frame = [frame_header(EnuOrigin.from_dict(origin))] if origin else \
        ["frame: the map's ENU frame (origin not stated); rows: t x y z qx qy qz qw (T_enu_vehicle)"]
    tail = [attitude_header(planar=True), "t: seconds of the drive's time base, exact from integer ns"]
    paths = []
    series = [(f"{m}_tum.txt", f"cornermap evaluation: {m} estimate", r.q) for m, r in ev.runs.items()]
    series += [(f"reference_{name}_tum.txt", f"cornermap evaluation: reference '{name}' at the epochs", ref)
               for name, ref in sorted(ev.references.items())]
    for name, title, q in series:
        path = out_dir / name
        _atomic_write(path, planar_tum_text(ev.stamps_ns, np.asarray(q, float), [title, *frame, *tail]))
        paths.append(path)
    return paths


def write_report(out_dir: Path, ev: Evaluation, cmap, fetch, *, drive: str | None, map_info: dict,
                 verdict: dict | None = None, comparison: dict | None = None, previous=None) -> dict:
    """metrics.json, <method>_tum.txt, reference_<name>_tum.txt and the self-contained report.html into ``out_dir``."""
    from stages.evaluate.report import render_report

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    doc = metrics_document(ev, drive, map_info, verdict, comparison)
    _atomic_write(out_dir / "metrics.json", json.dumps(doc, indent=2))
    write_tum_files(out_dir, ev, map_info.get("enu_origin"))
    _atomic_write(out_dir / "report.html", render_report(ev, doc, cmap, previous))
    log.info("evaluation report written to %s", out_dir / "report.html")
    return doc


def metrics_table_text(doc: dict) -> str:
    """The metrics as a fixed-width text table (for the CLI)."""
    keys = ("rms_2d_m", "p95_2d_m", "p99_2d_m", "max_2d_m", "heading_rms_deg", "lateral_rms_m",
            "longitudinal_rms_m", "mean_abs_x_m", "mean_abs_y_m", "mean_abs_heading_deg", "nees_mean", "epochs")
    short = ("rms_2d", "p95_2d", "p99_2d", "max_2d", "hdg_rms_deg", "lat_rms", "lon_rms", "mean|x|", "mean|y|",
             "mean|hdg|deg", "nees_mean", "epochs")
    head = f"{'method':<8} {'ref':<14} " + " ".join(f"{k:>12}" for k in short)
    lines, with_startup = [head], False
    for m, entry in doc["methods"].items():
        for ref_name, summary in (("map", entry.get("map_relative")), ("truth", entry.get("absolute")),
                                  ("truth_in_map", entry.get("truth_in_map"))):
            if not summary:
                continue
            for name, row in ((ref_name, summary), (f"{ref_name}+s", summary.get("all_epochs"))):
                if not row:
                    continue
                vals = []
                for k in keys:
                    v = row.get(k)
                    vals.append(f"{'-':>12}" if v is None else (f"{v:>12d}" if isinstance(v, int) else f"{v:>12.4f}"))
                lines.append(f"{m:<8} {name:<14} " + " ".join(vals))
                with_startup |= row is not summary
    if with_startup:
        lines.append("ekf rows: from its first map-corner association on; '+s': all epochs, start-up included")
    return "\n".join(lines)
