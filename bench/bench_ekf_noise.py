"""The corner EKF's own noise on a built root: the ICP and gyro heading noise per scan measured against the truth
beside what the drive itself says (the registration's stated information, the ICP-gyro scatter), and the EKF run
again in-process on the committed map and drive with evaluate params changed, its NEES split into parts.

    .venv/bin/python -m bench.bench_ekf_noise --root ROOT/demo-1 [--set ekf.icp.sigma_yaw_deg=0.008 ...]

ROOT is a folder `bench_seeds` built (its `workflow-*.yaml` and committed stages up to the tiles). Nothing is
written under ROOT: the evaluate stage's inputs are read through the store as the stage reads them.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import yaml

from stages.common.geometry import wrap_angle_rad


def load(root: Path, cache: Path | None = None):
    """(drive arrays, corner map, raster fetcher, references, params, frame error, edge columns) of the root's
    evaluation drive, as the evaluate stage reads them. With ``cache`` (a folder) everything but the map is kept
    there as a pickle, so that a root's scans and simulator output may be deleted once read."""
    import pickle

    from mapformat.loader import open_map
    from stages.evaluate.compute import with_map_correlation
    from stages.evaluate.map_access import map_inputs

    path = None if cache is None else Path(cache) / (Path(root).resolve().name + ".pkl")
    if path is not None and path.is_file():
        saved = pickle.loads(path.read_bytes())
    else:
        saved = read_root(root)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(pickle.dumps(saved))
    d, refs, params, frame, map_path, edges = saved
    params = type(params).model_validate(params.model_dump())  # a pickle of older code: today's fields and defaults
    reader = open_map(map_path)
    p_map = with_map_correlation(params, reader)
    where_q, where_ok = d.roughly
    cmap, fetch = map_inputs(
        reader,
        np.where(where_ok[:, None], where_q, np.nan),
        sensor_range_m=params.ekf.corners.sensor_range_m,
        field=params.markings,
        coverage_margin_m=params.markings.coverage_margin(),
    )
    return d, cmap, fetch, refs, p_map, frame, edges


def read_root(root: Path):
    from pipeline.declare import PartitionKey
    from pipeline.plan import make_plan
    from pipeline.reader import StoreInputReader
    from pipeline.workflow import load_workflow
    from stages.evaluate.compute import read_drive, read_references
    from stages.evaluate.map_access import map_inputs
    from stages.evaluate.run import FrameError

    wf_path = sorted(Path(root).glob("workflow-*.yaml"), key=lambda p: p.stat().st_mtime)[-1]
    wf = load_workflow(wf_path)
    plan = make_plan(wf, wf.root_dir(None))
    sp = plan.stages["evaluate"]
    ins = StoreInputReader(plan.root, dict(sp.inputs), {k: None for k in sp.inputs})
    params = sp.decl.params(**sp.params)
    drive = next(d["name"] for d in yaml.safe_load(wf_path.read_text())["drives"] if d.get("role") == "eval")
    settings = dict(sp.settings)
    settings.setdefault("root", str(plan.root))
    ctx = SimpleNamespace(
        inputs=ins,
        params=params,
        settings=settings,
        partition=PartitionKey(drive=drive),
        report_step=lambda *a, **k: None,
    )
    d, scan_ids = read_drive(ctx, drive, params)
    reader = published_map(root)
    where_q, where_ok = d.roughly
    cmap, _ = map_inputs(
        reader,
        np.where(where_ok[:, None], where_q, np.nan),
        sensor_range_m=params.ekf.corners.sensor_range_m,
        field=params.markings,
        coverage_margin_m=params.markings.coverage_margin(),
    )
    frame = FrameError.from_map(getattr(reader, "map_frame", None))
    refs = read_references(ctx, drive, reader.origin, params, cmap)
    edges = scan_table(root, "edges", drive)
    rmse = np.full(len(scan_ids), np.nan)
    k = np.searchsorted(scan_ids, edges["scan_id"])
    good = (k < len(rmse)) & (scan_ids[np.minimum(k, len(rmse) - 1)] == edges["scan_id"])
    rmse[k[good]] = edges["inlier_rmse_m"][good]
    return d, refs, params, frame, str(reader.path), rmse


def published_map(root: Path):
    """The newest committed map_tiles version's published map (not through the plan: a change of the tiles' code,
    e.g. of the localizer defaults, does not hide the committed map)."""
    from bench.roots import read
    from mapformat.loader import open_map

    path = read(root, "map_tiles").to_pylist()[-1]["path"]
    return open_map(path if Path(path).is_absolute() else Path(root) / path)


def scan_table(root: Path, dataset: str, drive: str) -> dict:
    """Columns of a drive's accepted consecutive odometry edges."""
    import pyarrow.compute as pc

    from bench.roots import read

    t = read(root, "odometry_edges")
    t = t.filter(pc.equal(t["drive"], drive)) if "drive" in t.column_names else t
    t = t.filter(pc.equal(t["accepted"], True)).sort_by("scan_id")
    return {c: t[c].to_numpy(zero_copy_only=False) for c in ("scan_id", "inlier_rmse_m")}


def increment_errors(d, ref_q: np.ndarray) -> dict:
    """Per-epoch heading-increment errors against a reference (E,3): ICP (raw), gyro, and their difference."""
    true_dyaw = np.concatenate([[np.nan], wrap_angle_rad(np.diff(ref_q[:, 2]))])
    icp = d.icp_raw_increments if d.icp_raw_increments is not None else d.icp_increments
    return {
        "icp": wrap_angle_rad(icp[:, 2] - true_dyaw),
        "gyro": wrap_angle_rad(d.odo_increments[:, 2] - true_dyaw),
        "icp_minus_gyro": wrap_angle_rad(icp[:, 2] - d.odo_increments[:, 2]),
    }


def nees_parts(q: np.ndarray, P: np.ndarray, ref: np.ndarray, keep: np.ndarray) -> dict:
    """NEES and its position / heading parts, along / across error RMS against the stated std."""
    from stages.evaluate.ekf import nees

    ok = keep & np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(ref), axis=1)
    q, P, ref = q[ok], P[ok], ref[ok]
    e = q - ref
    e[:, 2] = wrap_angle_rad(e[:, 2])
    c, s = np.cos(ref[:, 2]), np.sin(ref[:, 2])
    R = np.stack([np.stack([c, s], -1), np.stack([-s, c], -1)], -2)  # ENU -> (along, across)
    e_al = np.einsum("nij,nj->ni", R, e[:, :2])
    P_al = R @ P[:, :2, :2] @ np.transpose(R, (0, 2, 1))
    pos = np.einsum("ni,ni->n", e[:, :2], np.linalg.solve(P[:, :2, :2], e[:, :2, None])[:, :, 0])
    return {
        "nees": float(np.mean(nees(q, P, ref))),
        "pos": float(np.mean(pos)),
        "hdg": float(np.mean(e[:, 2] ** 2 / P[:, 2, 2])),
        "along": (float(np.sqrt(np.mean(e_al[:, 0] ** 2))), float(np.sqrt(np.mean(P_al[:, 0, 0])))),
        "across": (float(np.sqrt(np.mean(e_al[:, 1] ** 2))), float(np.sqrt(np.mean(P_al[:, 1, 1])))),
        "heading_deg": (
            float(np.degrees(np.sqrt(np.mean(e[:, 2] ** 2)))),
            float(np.degrees(np.sqrt(np.mean(P[:, 2, 2])))),
        ),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, nargs="+", required=True)
    ap.add_argument("--cache", type=Path, default=None, help="keep each root's drive arrays here (pickles)")
    ap.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="NAME=VALUE",
        action="append",
        help="one run per --set group (evaluate params by their place in the sections)",
    )
    args = ap.parse_args()

    from bench.params_args import nested
    from stages.evaluate.run import evaluate_drive

    groups = [g for g in (args.set or [[]])] or [[]]
    if [] not in groups:
        groups = [[]] + groups
    for root in args.root:
        d, cmap, fetch, refs, p, frame, rmse = load(root, args.cache)
        judge = "truth_in_map" if "truth_in_map" in refs else "truth"
        from stages.evaluate.metrics import interpolate_poses

        ref = interpolate_poses(d.stamps_ns, *refs[judge], int(p.reference.max_gap_s * 1e9))
        errs = increment_errors(d, ref)
        moving = np.concatenate([[False], np.hypot(*np.diff(ref[:, :2], axis=0).T) > 0.05])
        print(f"{root}: {len(d.stamps_ns)} epochs")
        for name, e in errs.items():
            ok = np.isfinite(e) & moving
            dd = np.diff(e[ok])
            print(
                f"  {name}: RMS {np.degrees(np.sqrt(np.mean(e[ok] ** 2))):.4f} deg, first-difference / sqrt2 "
                f"{np.degrees(np.std(dd) / np.sqrt(2)):.4f} deg, mean {np.degrees(np.mean(e[ok])):.4f}"
            )
        if d.icp_cov is not None:
            sy = np.sqrt(d.icp_cov[:, 2, 2])
            e = errs["icp"]
            ok = np.isfinite(sy) & moving & np.isfinite(e)
            print(
                f"  registration's stated yaw std: median {np.degrees(np.median(sy[ok])):.4f} deg "
                f"(p10 {np.degrees(np.percentile(sy[ok], 10)):.4f}, p90 {np.degrees(np.percentile(sy[ok], 90)):.4f});"
                f" ICP error / stated RMS {np.sqrt(np.mean((e[ok] / sy[ok]) ** 2)):.2f}"
            )
            ok2 = ok & np.isfinite(rmse)
            cen = sy * rmse
            print(
                f"  residual-scaled (Censi): error / (stated x rmse) RMS "
                f"{np.sqrt(np.mean((e[ok2] / cen[ok2]) ** 2)):.2f} m^-1; median rmse {np.median(rmse[ok2]):.4f}"
            )
            for lo_q, hi_q in ((0, 33), (33, 67), (67, 100)):
                lo_v, hi_v = np.percentile(sy[ok], [lo_q, hi_q])
                b = ok & (sy >= lo_v) & (sy <= hi_v)
                print(
                    f"    stated tercile {lo_q}-{hi_q}: stated RMS {np.degrees(np.sqrt(np.mean(sy[b] ** 2))):.4f}, "
                    f"error RMS {np.degrees(np.sqrt(np.mean(e[b] ** 2))):.4f} deg ({b.sum()} scans)"
                )
        for g in groups:
            over = nested({k: yaml.safe_load(v) for k, v in (a.split("=", 1) for a in g)})
            from bench.params_args import merged

            pp = p.model_validate(merged(p.model_dump(), over)) if over else p
            pp = pp.model_copy(update={"methods": ["ekf"]})
            ev = evaluate_drive(d, cmap, fetch, refs, pp, frame)
            r = ev.runs["ekf"]
            m = ev.metrics["ekf"][judge]
            first = int(np.argmax(r.n_associated > 0))
            keep = np.arange(len(r.q)) >= first
            parts = nees_parts(r.q, r.P, ev.references[judge], keep)
            band = m.get("nees_band95") or [None, None]
            print(
                f"  {' '.join(g) or 'defaults'}: RMS {m['rms_2d_m']:.3f} p99 {m['p99_2d_m']:.3f} max "
                f"{m['max_2d_m']:.3f} hdg {m['heading_rms_deg']:.3f} NEES {m['nees_mean']:.2f} "
                f"[{band[0]:.2f}, {band[1]:.2f}] | pos {parts['pos']:.2f} hdg {parts['hdg']:.2f} along "
                f"{parts['along'][0]:.3f}/{parts['along'][1]:.3f} across {parts['across'][0]:.3f}/"
                f"{parts['across'][1]:.3f} heading {parts['heading_deg'][0]:.3f}/{parts['heading_deg'][1]:.3f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
