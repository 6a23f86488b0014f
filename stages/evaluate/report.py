"""report.html: the papers' figures as PNGs embedded (base64) in one self-contained page.

Figures: trajectories over the map (Im Fig. 15), horizontal error over time (Fig. 16/17), heading error
(Fig. 18), CDF of horizontal error (Fig. 19), corners used per epoch (Fig. 21/22), covariance ellipses where
corners are sparse (Fig. 23).
"""
from __future__ import annotations

import base64
import html
import io

import numpy as np

from stages.evaluate.metrics import compute_errors

COLORS = {"ekf": "tab:red", "mcl": "tab:green", "rtk_ins": "tab:blue", "icp_dr": "tab:orange",
          "map": "k", "truth": "tab:gray"}


def _png(fig) -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _horizontal_errors(ev) -> dict[str, np.ndarray]:
    ref = ev.references.get(ev.primary) if ev.primary else None
    if ref is None:
        return {}
    return {m: np.hypot(*compute_errors(r.q, ref).err_xy_m.T) for m, r in ev.runs.items()}


def figure_trajectories(ev, cmap) -> str:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 7))
    if cmap is not None and len(cmap.en_m):
        ax.scatter(cmap.en_m[:, 0], cmap.en_m[:, 1], s=6, c="0.6", marker="s", label="map corners")
    for name, ref in ev.references.items():
        ax.plot(ref[:, 0], ref[:, 1], color=COLORS.get(name, "k"), lw=2.0, alpha=0.5, label=f"reference: {name}")
    for m, r in ev.runs.items():
        ax.plot(r.q[:, 0], r.q[:, 1], color=COLORS.get(m), lw=0.9, label=m)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("east (m)"), ax.set_ylabel("north (m)"), ax.legend(fontsize=8), ax.set_title("Trajectories")
    return _png(fig)


def figure_errors_over_time(ev) -> str:
    import matplotlib.pyplot as plt

    t = (ev.stamps_ns - ev.stamps_ns[0]) * 1e-9
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    ref = ev.references.get(ev.primary) if ev.primary else None
    for m, h in _horizontal_errors(ev).items():
        a1.plot(t, h, color=COLORS.get(m), lw=0.8, label=m)
        if m in ("ekf", "mcl"):
            a2.plot(t, np.rad2deg(compute_errors(ev.runs[m].q, ref).err_yaw_rad), color=COLORS.get(m), lw=0.8,
                    label=m)
    a1.set_ylabel("horizontal error (m)"), a1.set_yscale("log"), a1.legend(fontsize=8)
    a1.set_title(f"Errors against the '{ev.primary}' reference")
    a2.set_ylabel("heading error (deg)"), a2.set_xlabel("time (s)"), a2.legend(fontsize=8)
    return _png(fig)


def figure_cdf(ev) -> str:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for m, h in _horizontal_errors(ev).items():
        h = np.sort(h[np.isfinite(h)])
        if len(h):
            ax.plot(h, np.arange(1, len(h) + 1) / len(h), color=COLORS.get(m), label=m)
    for p in (0.95, 0.99):
        ax.axhline(p, color="0.7", lw=0.6, ls="--")
    ax.set_xscale("log"), ax.set_xlabel("horizontal error (m)"), ax.set_ylabel("CDF"), ax.legend(fontsize=8)
    ax.set_title("CDF of the horizontal error")
    return _png(fig)


def figure_corners_per_epoch(ev) -> str:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 3.5))
    if "ekf" in ev.runs:
        ax.step(np.arange(len(ev.stamps_ns)), ev.runs["ekf"].n_associated, where="mid", color=COLORS["ekf"], lw=0.7)
    ax.set_xlabel("epoch"), ax.set_ylabel("corners associated"), ax.set_title("Corners used per epoch (EKF)")
    return _png(fig)


def sparse_window(n_associated: np.ndarray, width: int) -> tuple[int, int]:
    """Epoch window of ``width`` around the longest run without associations (where the EKF dead-reckons)."""
    n = len(n_associated)
    zero = np.concatenate([[0], (n_associated == 0).astype(int), [0]])
    edges = np.flatnonzero(np.diff(zero))
    if len(edges) < 2:
        return 0, min(n, width)
    starts, ends = edges[::2], edges[1::2]
    i = int(np.argmax(ends - starts))
    mid = (starts[i] + ends[i]) // 2
    lo = int(np.clip(mid - width // 2, 0, max(0, n - width)))
    return lo, min(n, lo + width)


def figure_ellipses(ev, cmap, width: int = 200, every: int = 10) -> str | None:
    import matplotlib.pyplot as plt
    from matplotlib.patches import Ellipse

    if "ekf" not in ev.runs:
        return None
    r = ev.runs["ekf"]
    lo, hi = sparse_window(r.n_associated, width)
    fig, ax = plt.subplots(figsize=(8, 6))
    ref = ev.references.get(ev.primary) if ev.primary else None
    if ref is not None:
        ax.plot(ref[lo:hi, 0], ref[lo:hi, 1], color="tab:blue", lw=1.5, label=f"reference ({ev.primary})")
    ax.plot(r.q[lo:hi, 0], r.q[lo:hi, 1], color="tab:red", lw=1.0, label="EKF")
    scale = 10.0
    for k in range(lo, hi, every):
        if not np.all(np.isfinite(r.P[k])):
            continue
        w, v = np.linalg.eigh(r.P[k][:2, :2])
        angle = np.degrees(np.arctan2(v[1, 1], v[0, 1]))
        ax.add_patch(Ellipse(r.q[k, :2], 2 * scale * 2.4477 * np.sqrt(max(w[1], 0)),
                             2 * scale * 2.4477 * np.sqrt(max(w[0], 0)), angle=angle, fill=False, color="tab:red",
                             lw=0.6))
    sel = (r.assoc_epoch >= lo) & (r.assoc_epoch < hi) & (cmap is not None)
    for k, i in zip(r.assoc_epoch[sel][::3], r.assoc_map_idx[sel][::3]):
        ax.plot([r.q[k, 0], cmap.en_m[i, 0]], [r.q[k, 1], cmap.en_m[i, 1]], color="tab:green", lw=0.3)
    ax.set_aspect("equal", adjustable="datalim"), ax.legend(fontsize=8)
    ax.set_xlabel("east (m, map ENU)"), ax.set_ylabel("north (m, map ENU)")
    ax.set_title(f"Epochs {lo}-{hi}: 95 % covariance ellipses x{scale:g} (sparsest corners), green: associations")
    return _png(fig)


def _metrics_html(doc: dict) -> str:
    keys = ("rms_2d_m", "p95_2d_m", "p99_2d_m", "max_2d_m", "heading_rms_deg", "lateral_rms_m",
            "longitudinal_rms_m", "mean_abs_x_m", "mean_abs_y_m", "mean_abs_heading_deg", "nees_mean", "epochs")
    rows = []
    for m, entry in doc["methods"].items():
        for ref_name, s in (("map-relative", entry.get("map_relative")), ("absolute (truth)", entry.get("absolute")),
                            ("truth fitted on the map's corners", entry.get("truth_in_map"))):
            if not s:
                continue
            for name, row in ((ref_name, s), (f"{ref_name}, all epochs (start-up "
                                              f"{_fmt(s.get('startup_s'))} s included)", s.get("all_epochs"))):
                if not row:
                    continue
                cells = "".join(f"<td>{_cell(row.get(k))}</td>" for k in keys)
                rows.append(f"<tr><th>{html.escape(m)}</th><td>{name}</td>{cells}</tr>")
    head = "".join(f"<th>{k}</th>" for k in keys)
    return f"<table><tr><th>method</th><th>reference</th>{head}</tr>{''.join(rows)}</table>"


def _cell(v) -> str:
    return "" if v is None else str(v) if isinstance(v, int) else f"{v:.4f}"


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return str(v) if isinstance(v, (int, str)) else f"{v:.4g}"


def _verdict_html(doc: dict) -> str:
    """The verdict: coverage, then one row per target (value, target, met) against the reference it was judged on."""
    v = doc.get("verdict")
    if not v:
        return ""
    c = v["coverage"]
    status = html.escape(v["status"])
    color = {"pass": "#1a7f37", "fail": "#cf222e", "no coverage": "#cf222e"}.get(v["status"], "#9a6700")
    assoc = "-" if c["share_associated"] is None else f"{100 * c['share_associated']:.1f} %"
    share_assoc = c["share_associated"]
    assoc_ok = "-" if share_assoc is None else "yes" if share_assoc >= c["min_share_associated"] else "NO"
    rows = [
        f"<tr><th>coverage</th><td>map corner within {c['sensor_range_m']:g} m</td>"
        f"<td>{100 * c['share_corner_in_range']:.1f} %</td><td>&ge; {100 * c['min_share_in_range']:.0f} %</td>"
        f"<td>{'yes' if c['share_corner_in_range'] >= c['min_share_in_range'] else 'NO'}</td><td>GNSS/INS</td></tr>",
        f"<tr><th>coverage</th><td>epochs with an EKF association</td><td>{assoc}</td>"
        f"<td>&ge; {100 * c['min_share_associated']:.0f} %</td><td>{assoc_ok}</td><td>EKF</td></tr>",
    ]
    for m, targets in v["targets"].items():
        ref = v["judged_against"].get(m, "-")
        for key, t in targets.items():
            if key == "nees_consistent":
                from stages.evaluate.verdict import nees_words

                share = None if t["share_below_q95"] is None else 100 * t["share_below_q95"]
                value = f"mean {_fmt(t['value'])} ({html.escape(nees_words(t))}), {_fmt(share)} % under q95"
                target = (f"mean in {_fmt(t['band95'])} (two-sided); above it: &ge; "
                          f"{100 * t['min_share_below_q95']:.0f} % under q95")
            else:
                value, target = _fmt(t["value"]), f"&le; {_fmt(t['target'])}"
            ok = "yes" if t["ok"] else "<b style='color:#cf222e'>NO</b>"
            rows.append(f"<tr><th>{html.escape(m)}</th><td>{html.escape(key)}</td><td>{value}</td><td>{target}</td>"
                        f"<td>{ok}</td><td>{html.escape(ref)}</td></tr>")
    return (f"<h2>Verdict: <span style='color:{color}'>{status}</span></h2><table><tr><th>method</th><th>metric"
            "</th><th>value</th><th>target</th><th>met</th><th>reference</th></tr>" + "".join(rows) + "</table>")


def figure_version_changes(ev, cmap, comp: dict) -> str:
    """The map's corners near the drive with those added / removed / moved since the previous version."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 7))
    if cmap is not None and len(cmap.en_m):
        ax.scatter(cmap.en_m[:, 0], cmap.en_m[:, 1], s=8, c="0.6", marker="s",
                   label=f"v{comp['current_version']:04d} corners")
    ref = ev.references.get(ev.primary) if ev.primary else None
    if ref is not None:
        ax.plot(ref[:, 0], ref[:, 1], color="tab:blue", lw=1.0, alpha=0.6, label="drive")
    for key, style, label in (("added_en_m", dict(c="tab:green", marker="+", s=90), "added"),
                              ("removed_en_m", dict(c="tab:red", marker="x", s=70), "removed"),
                              ("moved_en_m", dict(facecolors="none", edgecolors="tab:orange", marker="o", s=80),
                               f"moved > {comp['moved_threshold_m']:g} m")):
        pts = np.asarray(comp[key], dtype=float).reshape(-1, 2)
        ax.scatter(pts[:, 0], pts[:, 1], label=f"{label} ({len(pts)})", **style)
    ax.set_aspect("equal", adjustable="datalim"), ax.legend(fontsize=8)
    ax.set_xlabel("east (m)"), ax.set_ylabel("north (m)")
    ax.set_title(f"Corners changed from v{comp['previous_version']:04d} to v{comp['current_version']:04d}")
    return _png(fig)


def figure_version_errors(ev, previous, comp: dict) -> str | None:
    import matplotlib.pyplot as plt

    name = comp.get("reference")
    if name is None or "ekf" not in ev.runs or previous is None or "ekf" not in previous.runs:
        return None
    t = (ev.stamps_ns - ev.stamps_ns[0]) * 1e-9
    fig, ax = plt.subplots(figsize=(9, 3.5))
    for e, label, color in ((ev, f"v{comp['current_version']:04d}", "tab:red"),
                            (previous, f"v{comp['previous_version']:04d}", "tab:gray")):
        ref = e.references.get(name)
        if ref is not None:
            ax.plot(t, np.hypot(*compute_errors(e.runs["ekf"].q, ref).err_xy_m.T), color=color, lw=0.8, label=label)
    ax.set_yscale("log"), ax.set_xlabel("time (s)"), ax.set_ylabel("EKF horizontal error (m)"), ax.legend(fontsize=8)
    ax.set_title(f"EKF error on both versions against '{name}'")
    return _png(fig)


def _comparison_html(comp: dict | None) -> str:
    if not comp:
        return ""
    cur, prev = comp["ekf"]["current"] or {}, comp["ekf"]["previous"] or {}
    keys = ("rms_2d_m", "p99_2d_m", "max_2d_m", "heading_rms_deg", "nees_mean", "epochs")
    rows = "".join(f"<tr><th>v{v:04d}</th>" + "".join(f"<td>{_fmt(s.get(k))}</td>" for k in keys) + "</tr>"
                   for v, s in ((comp["current_version"], cur), (comp["previous_version"], prev)))
    return (f"<h2>Previous version v{comp['previous_version']:04d}</h2><p>EKF on both versions, same drive, against "
            f"'{html.escape(str(comp['reference']))}'. Corners near the drive: {comp['corners_near_drive']['previous']}"
            f" -&gt; {comp['corners_near_drive']['current']}; {comp['added']} added, {comp['removed']} removed, "
            f"{comp['moved']} moved by more than {comp['moved_threshold_m']:g} m (matched within "
            f"{comp['match_radius_m']:g} m).</p><table><tr><th>version</th>"
            + "".join(f"<th>{k}</th>" for k in keys) + f"</tr>{rows}</table>")


def render_report(ev, doc: dict, cmap, previous=None) -> str:
    import matplotlib

    matplotlib.use("Agg")
    figs = [("Trajectories over the map", figure_trajectories(ev, cmap)),
            ("Error over time", figure_errors_over_time(ev) if ev.primary else None),
            ("CDF of horizontal error", figure_cdf(ev) if ev.primary else None),
            ("Corners used per epoch", figure_corners_per_epoch(ev)),
            ("Covariance ellipses where corners are sparse", figure_ellipses(ev, cmap))]
    body = "".join(f"<h2>{t}</h2><img alt='{t}' src='data:image/png;base64,{b}'/>" for t, b in figs if b)
    comp = doc.get("comparison")
    if comp:
        cfigs = [("Corners changed since the previous version", figure_version_changes(ev, cmap, comp)),
                 ("EKF error on both versions", figure_version_errors(ev, previous, comp))]
        body = _comparison_html(comp) + "".join(f"<h3>{t}</h3><img alt='{t}' src='data:image/png;base64,{b}'/>"
                                                for t, b in cfigs if b) + body
    title = f"cornermap evaluation: drive {html.escape(str(doc.get('drive')))}"
    m = doc.get("map") or {}
    meta = html.escape(f"{m.get('name', '')} v{int(m['version']):04d} ({m.get('path', '')})" if m.get("version")
                       else str(m))
    return (f"<!doctype html><html><head><meta charset='utf-8'><title>{title}</title><style>"
            "body{font-family:sans-serif;margin:2em}table{border-collapse:collapse;font-size:12px}"
            "td,th{border:1px solid #ccc;padding:3px 6px;text-align:right}img{max-width:100%}</style></head>"
            f"<body><h1>{title}</h1><p>map: {meta}; primary reference: {doc.get('primary_reference')}</p>"
            f"{_verdict_html(doc)}<h2>Metrics</h2>{_metrics_html(doc)}{body}</body></html>")
