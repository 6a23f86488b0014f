"""Adapter of the evaluate stage: Arrow tables and the published map in, eval_epochs and the report out.

The map is read only through the product's public consumer API, in ``stages.evaluate.map_access``. Beside the
metrics, the evaluation gives a verdict (``stages.evaluate.verdict``): no map coverage, or with
``fail_on_targets`` a missed target, fails it with a DataQualityError (exit 3) after the report is written.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from pipeline.declare import PartitionKey, StageContext
from pipeline.errors import DataQualityError
from stages.common.geometry import wrap_angle_rad
from stages.common.records import Extrinsics, decode_scans_raw, yaw_rad
from stages.common.road_features import extract_road_features
from stages.common.wheel_odometry import OdometryTrack, track_from_table
from stages.evaluate.localize_ekf import CornerMap, CornerObservations, corners_to_vehicle
from stages.evaluate.localize_mcl import odometry_increments
from stages.evaluate.map_access import map_inputs, open_published_map
from stages.evaluate.params import EvaluateParams
from stages.evaluate.run import DriveArrays, FrameError, evaluate_drive

log = logging.getLogger(__name__)

# Road-feature points are read up to markings.feature_range_m plus the extrinsic's lever arm plus this: a scan's own
# motion while it is deskewed (0.1 s at up to 50 m/s).
FEATURE_READ_MARGIN_M = 5.0


def _rows_of(ctx: StageContext, arg: str, drive: str, columns: list[str] | None = None) -> pa.Table:
    table = ctx.inputs.read(arg, partition=PartitionKey(drive=drive), columns=columns)
    if "drive" in table.column_names:
        table = table.filter(pc.equal(table["drive"], drive))
    return table


def epoch_index(scan_ids: np.ndarray, epoch_scan_ids: np.ndarray) -> np.ndarray:
    """Epoch of each scan id (-1 when the scan is not an epoch)."""
    pos = np.clip(np.searchsorted(epoch_scan_ids, scan_ids), 0, len(epoch_scan_ids) - 1)
    return np.where(epoch_scan_ids[pos] == scan_ids, pos, -1)


def read_icp_increments(edges: pa.Table, epoch_scan_ids: np.ndarray) -> np.ndarray:
    inc = np.full((len(epoch_scan_ids), 3), np.nan)
    if edges.num_rows == 0:
        return inc
    edges = edges.filter(pc.equal(edges["accepted"], True))
    k = epoch_index(edges["scan_id"].to_numpy(), epoch_scan_ids)
    ok = k > 0
    yaw = yaw_rad(edges)
    inc[k[ok]] = np.column_stack([edges["dx_m"].to_numpy(), edges["dy_m"].to_numpy(), yaw])[ok]
    return inc


def read_icp_covariances(edges: pa.Table, epoch_scan_ids: np.ndarray) -> np.ndarray:
    """(E,3,3) covariance of each epoch's ICP increment (dx, dy, dyaw) in the previous vehicle frame: the planar
    marginal of the inverse of the edge's 6x6 information (gtsam order rx ry rz tx ty tz); NaN where none."""
    cov = np.full((len(epoch_scan_ids), 3, 3), np.nan)
    if edges.num_rows == 0 or "information" not in edges.column_names:
        return cov
    edges = edges.filter(pc.equal(edges["accepted"], True))
    k = epoch_index(edges["scan_id"].to_numpy(), epoch_scan_ids)
    ok = k > 0
    info = np.asarray(edges["information"].combine_chunks().flatten().to_numpy(), dtype=float).reshape(-1, 6, 6)[ok]
    idx = np.array([3, 4, 2])
    cov[k[ok]] = np.linalg.inv(info)[:, idx[:, None], idx[None, :]]
    return cov


def fall_back_on_wheel(icp: np.ndarray, wheel: np.ndarray, gate_yaw_rad: float) -> np.ndarray:
    """(E,3) ICP increments with the failed ones (NaN) and, when ``gate_yaw_rad`` > 0, those whose heading change
    differs from the wheel/gyro increment's by more than it replaced by the wheel/gyro increment. Why: after a
    turn in a degenerate street (gangnam drive 1, scans 3670-3690) accepted ICP edges next to rejected ones were
    0.08-0.11 deg off each, +0.5 deg in 2 s, while the gyro's error is its bias (~0.01 deg per scan); with
    ICP-grade heading noise the EKF then held a 0.5 deg error through the corner-poor stretch."""
    out = np.array(icp, dtype=float, copy=True)
    use_wheel = ~np.all(np.isfinite(out), axis=1)
    if gate_yaw_rad > 0:
        with np.errstate(invalid="ignore"):
            use_wheel |= np.abs(wrap_angle_rad(out[:, 2] - wheel[:, 2])) > gate_yaw_rad
    out[use_wheel] = wheel[use_wheel]
    return out


def increments_without_wheel(icp: np.ndarray, gnss_q: np.ndarray) -> np.ndarray:
    """(E,3) motion increments for a drive without wheel odometry: the ICP increment, or where ICP failed the
    GNSS/INS pose difference (its velocity and yaw rate integrated over the epoch) in the frame of epoch k-1."""
    out = np.array(icp, dtype=float, copy=True)
    out[0] = 0.0
    d = np.diff(gnss_q, axis=0)
    c, s = np.cos(gnss_q[:-1, 2]), np.sin(gnss_q[:-1, 2])
    gnss_inc = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], wrap_angle_rad(d[:, 2])])
    missing = ~np.all(np.isfinite(out[1:]), axis=1)
    out[1:][missing] = gnss_inc[missing]
    return out


def read_corners(corners: pa.Table, epoch_scan_ids: np.ndarray, T_vehicle_lidar: np.ndarray) -> CornerObservations:
    k = epoch_index(corners["scan_id"].to_numpy(), epoch_scan_ids)
    order = np.argsort(k, kind="stable")
    order = order[k[order] >= 0]
    col = lambda name: corners[name].to_numpy()[order]  # noqa: E731
    cov = np.stack(
        [np.stack([col("cov_xx_m2"), col("cov_xy_m2")], -1), np.stack([col("cov_xy_m2"), col("cov_yy_m2")], -1)], -2
    )
    xy, cov_v, dirs = corners_to_vehicle(T_vehicle_lidar, np.column_stack([col("x_m"), col("y_m")]), cov,
                                         np.column_stack([col("theta1_rad"), col("theta2_rad")]))
    return CornerObservations(k[order], xy, cov_v, dirs)


def _chunk_features(t: pa.Table, epoch_scan_ids: np.ndarray, T_vehicle_lidar: np.ndarray, p: EvaluateParams,
                    track: OdometryTrack | None, epochs: list, points: list) -> int:
    """Road features of the scans of one chunk's rows; returns how many scans were not deskewed. A function of its
    own so that the chunk's arrays are freed before the next chunk is read."""
    rows = decode_scans_raw(t)
    sid, xyz, inten, ring, stamp = rows.scan_id, rows.xyz_lidar_m, rows.intensity, rows.ring, rows.stamp_ns
    t_s = rows.time_offset_s.astype(np.float64)
    bounds = np.flatnonzero(np.diff(sid)) + 1
    n_raw = 0
    for lo, hi in zip(np.concatenate([[0], bounds]), np.concatenate([bounds, [len(sid)]])):
        k = epoch_index(sid[lo:lo + 1], epoch_scan_ids)[0]
        if k < 0:
            continue
        pts = None if track is None else track.deskew_scan(xyz[lo:hi], t_s[lo:hi], int(stamp[lo]), T_vehicle_lidar)
        if pts is None:
            pts, n_raw = xyz[lo:hi], n_raw + 1
        f = extract_road_features(pts, inten[lo:hi], ring[lo:hi], T_vehicle_lidar,
                                  voxel_m=p.features.voxel_m, window_m=p.features.window_m,
                                  offset_sigma=p.features.offset_sigma, ground_band_m=p.features.ground_band_m,
                                  ground_model=p.features.ground_model,
                                  max_range_m=p.markings.feature_range_m)
        epochs.append(np.full(len(f), k)), points.append(f)
    return n_raw


def extract_features(ctx: StageContext, drive: str, epoch_scan_ids: np.ndarray, T_vehicle_lidar: np.ndarray,
                     p: EvaluateParams, track: OdometryTrack | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Road features of every scan of the drive, chunk by chunk (memory bounded by one chunk).

    With ``track`` (wheel speed + gyro) each scan is first motion-compensated to its start, the epoch's time:
    a raw revolution is 0.1 s long, so at 8 m/s its points sit up to 0.8 m (0.4 m on average) behind and, at
    30 deg/s, 1.5 deg rotated from where the scan-start pose puts them (measured on the demo drive: the MCL
    carried a +0.3 m along-track and -yaw_rate * 0.05 s heading bias without it).
    Points far beyond the features' range are not read: the filter, in the lidar frame, keeps a margin for the
    extrinsic's lever arm and a scan's motion, and ``extract_road_features`` applies the exact range.
    """
    epochs, points = [], []
    cols = ["scan_id", "x_m", "y_m", "z_m", "intensity", "ring", "time_offset_s", "stamp_ns"]
    reach = p.markings.feature_range_m + float(np.hypot(*np.asarray(T_vehicle_lidar)[:2, 3])) + FEATURE_READ_MARGIN_M
    near = pc.field("x_m") * pc.field("x_m") + pc.field("y_m") * pc.field("y_m") <= reach * reach
    n_raw = 0
    parts = [part for part in ctx.inputs.partitions("scans") if part.drive == drive]
    for i, part in enumerate(parts):
        ctx.report_step("road features of the scans", i, len(parts))
        t = ctx.inputs.read("scans", partition=part, columns=cols, filters=near)
        n_raw += _chunk_features(t, epoch_scan_ids, T_vehicle_lidar, p, track, epochs, points)
        del t
    if track is not None and n_raw:
        log.warning("evaluate %s: the odometry does not cover %d scans; their road features are not deskewed",
                    drive, n_raw)
    if not epochs:
        return np.zeros(0, np.int64), np.zeros((0, 2))
    ep, pts = np.concatenate(epochs), np.concatenate(points)
    order = np.argsort(ep, kind="stable")
    return ep[order], pts[order]


def prior_fixes(prior_rows: pa.Table, drive: str, scan_ids: np.ndarray, q: np.ndarray, std: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A drive without GNSS: the (east, north, yaw) 'fixes' the filters start from and fall back on, from its
    ``poses_prior`` rows in the map's frame (a prior trajectory in ENU, the start pose; a local prior places nothing
    by itself) with their stated std; ``q`` and ``std`` elsewhere as they were."""
    from stages.common.records import PriorPoses

    prior = PriorPoses.from_table(prior_rows, drive)
    q, std, valid = q.copy(), std.copy(), np.zeros(len(scan_ids), bool)
    usable = (prior.frame == "map_enu") & prior.valid & np.all(np.isfinite(prior.std[:, [0, 1, 5]]), axis=1)
    pos = np.searchsorted(scan_ids, prior.scan_id)
    usable &= pos < len(scan_ids)
    usable[usable] &= scan_ids[pos[usable]] == prior.scan_id[usable]
    for r in np.flatnonzero(usable):
        T = prior.T[r]
        q[pos[r]] = (T[0, 3], T[1, 3], np.arctan2(T[1, 0], T[0, 0]))
        std[pos[r]] = prior.std[r, [0, 1, 5]]
        valid[pos[r]] = True
    q[~valid] = np.nan
    return q, std, valid


def read_drive(ctx: StageContext, drive: str, p: EvaluateParams) -> tuple[DriveArrays, np.ndarray]:
    poses = _rows_of(ctx, "poses_gnss", drive).sort_by("scan_id")
    if poses.num_rows == 0:
        raise DataQualityError(f"drive {drive!r}: poses_gnss has no rows; hint: was the drive ingested?")
    scan_ids = poses["scan_id"].to_numpy()
    stamps = poses["stamp_ns"].to_numpy()
    T_vl = Extrinsics.from_table(_rows_of(ctx, "drive_info", drive)).of(drive)
    gnss_q = np.column_stack([poses["x_m"].to_numpy(), poses["y_m"].to_numpy(), yaw_rad(poses)])
    gnss_std = np.column_stack([poses[c].to_numpy() for c in ("std_east_m", "std_north_m", "std_yaw_rad")])
    gnss_valid = poses["valid"].to_numpy(zero_copy_only=False)
    if not gnss_valid.any() and ctx.inputs.has("prior"):  # a drive without GNSS: its prior / start pose in the map
        gnss_q, gnss_std, gnss_valid = prior_fixes(_rows_of(ctx, "prior", drive), drive, scan_ids, gnss_q, gnss_std)
    odo = _rows_of(ctx, "odometry", drive).sort_by("stamp_ns") if ctx.inputs.has("odometry") else None
    edges = _rows_of(ctx, "edges", drive)
    icp_raw = read_icp_increments(edges, scan_ids)
    if odo is not None and odo.num_rows >= 2:
        odo_inc = odometry_increments(odo["stamp_ns"].to_numpy(), odo["speed_mps"].to_numpy(),
                                      odo["yaw_rate_radps"].to_numpy(), stamps)
        icp = fall_back_on_wheel(icp_raw, odo_inc, np.deg2rad(p.ekf.icp.wheel_gate_deg))
    else:
        icp = icp_raw
        odo, odo_inc = None, increments_without_wheel(icp, gnss_q)
        icp_raw = None  # the wheel/gyro motion model (ekf.motion wheel_bias) needs wheels: the ICP model runs
        log.warning("evaluate %s: no wheel odometry; the EKF runs on ICP increments alone, the MCL on ICP "
                    "increments (GNSS/INS pose differences where ICP failed: %d of %d epochs), features not deskewed",
                    drive, int((~np.all(np.isfinite(icp[1:]), axis=1)).sum()), len(stamps))
    corners = read_corners(_rows_of(ctx, "corners", drive), scan_ids, T_vl)
    deskewed = bool(p.features.deskew and odo is not None)  # the EKF uses road features only deskewed
    if "mcl" in p.methods or ("ekf" in p.methods and p.ekf.markings.enabled and deskewed):
        track = track_from_table(odo) if deskewed else None
        f_ep, f_xy = extract_features(ctx, drive, scan_ids, T_vl, p, track)
    else:
        f_ep, f_xy = np.zeros(0, np.int64), np.zeros((0, 2))
    where = None
    if not poses["valid"].to_numpy(zero_copy_only=False).any() and gnss_valid.any():  # no GNSS: from its start
        from stages.evaluate.localize_ekf import dead_reckon

        k0 = int(np.argmax(gnss_valid))
        where = dead_reckon(icp, gnss_q[k0], k0)
    return DriveArrays(stamps, icp, odo_inc, gnss_q, gnss_std, gnss_valid, corners, f_ep, f_xy, icp_raw,
                       read_icp_covariances(edges, scan_ids), deskewed, where_q=where), scan_ids


def read_references(ctx: StageContext, drive: str, map_origin, p: EvaluateParams, cmap: CornerMap | None = None
                    ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``map`` (poses_optimized), ``truth`` (a TUM file moved into the map's frame by geodesy, see
    ``reference.read_reference``) and, when the simulator's true corners sit beside the truth, ``truth_in_map``:
    the truth moved onto the map by a rigid fit of the map corners on the true ones (the map-relative reference)."""
    from stages.evaluate.metrics import align_truth_to_map, transform_poses
    from stages.evaluate.params import parse_reference_frame
    from stages.evaluate.reference import read_reference, read_truth_corners

    refs = {}
    if ctx.inputs.has("reference"):
        t = _rows_of(ctx, "reference", drive)
        if t.num_rows:
            refs["map"] = (t["stamp_ns"].to_numpy(), np.column_stack([t["x_m"].to_numpy(), t["y_m"].to_numpy(),
                                                                       yaw_rad(t)]))
    truth = (ctx.settings.get("references") or {}).get(drive)
    if truth:
        ref = read_reference(Path(truth), map_origin, parse_reference_frame(p.reference.frame))
        refs["truth"] = (ref.stamps_ns, ref.q)
        truth_corners = read_truth_corners(Path(truth), ref.T_map_origin_ref)
        fit = align_truth_to_map(cmap.en_m, truth_corners) if cmap is not None and truth_corners is not None else None
        if fit is not None:
            R, t, resid = fit
            log.info("truth_in_map: map frame = truth + (%.3f, %.3f) m, %.3f deg; %d corners, residual rms %.3f m",
                     t[0], t[1], np.degrees(np.arctan2(R[1, 0], R[0, 0])), len(resid), np.sqrt(np.mean(resid**2)))
            refs["truth_in_map"] = (refs["truth"][0], transform_poses(refs["truth"][1], R, t))
    return refs


def compute(ctx: StageContext) -> dict:
    import json

    import pyarrow.parquet as pq

    from stages.evaluate.outputs import epochs_table, metrics_table_text, write_report
    from stages.evaluate.run import first_fix
    from stages.evaluate.verdict import coverage, verdict, verdict_line

    p: EvaluateParams = ctx.params  # type: ignore[assignment]
    drive = ctx.partition.drive
    ctx.report_step("reading the drive")
    d, scan_ids = read_drive(ctx, drive, p)
    ctx.report_step("localizing (" + ", ".join(p.methods) + ")")
    reader = open_published_map(ctx)
    p_map = with_map_correlation(p, reader)
    where_q, where_ok = d.roughly
    cmap, fetch = map_inputs(reader, np.where(where_ok[:, None], where_q, np.nan),
                             sensor_range_m=p.ekf.corners.sensor_range_m, field=p.markings,
                             coverage_margin_m=p.markings.coverage_margin())
    frame = FrameError.from_map(getattr(reader, "map_frame", None))
    ev = evaluate_drive(d, cmap, fetch, read_references(ctx, drive, reader.origin, p, cmap), p_map,
                        frame)
    ekf = ev.runs.get("ekf")
    cov = coverage(where_q, where_ok, cmap.en_m, ekf.n_associated if ekf is not None else None, first_fix(d),
                   p.ekf.corners.sensor_range_m, p.coverage.min_in_range, p.coverage.min_associated)
    v = verdict(ev.metrics, cov, p.targets)
    ctx.report_step("the previous version")
    comparison, prev_ev = compare_with_previous(ctx, drive, reader, d, cmap, ev, p)
    ctx.report_step("writing the report")
    out = ctx.artifact_dir("report")
    name = reader.path.parent.name
    write_report(out, ev, cmap, fetch, drive=drive, verdict=v, comparison=comparison, previous=prev_ev,
                 map_info={"name": name, "path": str(reader.path), "version": reader.version,
                           "enu_origin": reader.origin.as_dict(),
                           "corner_error_correlation": {"share": p_map.ekf.map.corr_share,
                                                        "length_m": p_map.ekf.map.corr_length_m,
                                                        "from": "map" if p_map is not p else "params"}})
    table = epochs_table(ev, drive)
    pq.write_table(table, out / "epochs.parquet")  # the per-epoch table beside the report, for DIR users
    log.info("evaluate %s on %s v%04d: %s", drive, name, reader.version, verdict_line(v))
    if v["status"] == "no coverage" or (v["status"] == "fail" and p.fail_on_targets):
        raise DataQualityError(f"evaluation of {drive} on map {name} v{reader.version:04d}: {verdict_line(v)}; "
                               f"report: {out / 'report.html'}")
    final = ctx.committed_artifact_dir("report")
    doc = json.loads((out / "metrics.json").read_text())
    outcome = [f"evaluation of {drive} on map version {reader.version}:", metrics_table_text(doc), verdict_line(v),
               f"report: {final / 'report.html'}", f"metrics: {final / 'metrics.json'}"]
    return {"epochs": table, "_extra": {"outcome": outcome}}


def with_map_correlation(p: EvaluateParams, reader) -> EvaluateParams:
    """The params with the map's own corner-error correlation (``MapReader.corner_error_correlation``) when
    ``ekf.map.corr_source`` is ``map`` and the map states one; else ``p`` itself."""
    stated = getattr(reader, "corner_error_correlation", None)
    if p.ekf.map.corr_source != "map" or stated is None:
        return p
    log.info("evaluate: the map states its corners' errors correlate %.2f exp(-d^2 / 2 (%.0f m)^2)", *stated)
    return p.model_copy(update={"ekf": p.ekf.replace(map={"corr_share": stated[0], "corr_length_m": stated[1]})})


def compare_with_previous(ctx: StageContext, drive: str, reader, d: DriveArrays, cmap: CornerMap, ev, p):
    """The EKF on the map's previous version (same drive, same references): (comparison entry, Evaluation) or
    (None, None) when the version has no parent."""
    from stages.evaluate.compare import comparison_document, previous_version
    from stages.evaluate.verdict import judged_reference

    prev = previous_version(reader)
    if prev is None:
        return None, None
    prev_cmap, prev_fetch = map_inputs(prev, d.gnss_q, sensor_range_m=p.ekf.corners.sensor_range_m, field=p.markings,
                                      coverage_margin_m=p.markings.coverage_margin())
    cfg_prev = with_map_correlation(p, prev).model_copy(update={"methods": ["ekf"]})
    ev_prev = evaluate_drive(d, prev_cmap, prev_fetch, read_references(ctx, drive, reader.origin, p, prev_cmap),
                             cfg_prev, FrameError.from_map(getattr(prev, "map_frame", None)))
    ref = judged_reference(ev.metrics, "ekf")
    if ref == "truth_in_map":  # fitted on each version's own corners: compare against the common absolute truth
        ref = "truth"
    doc = comparison_document(reader.version, prev.version, cmap, prev_cmap, ev.metrics, ev_prev.metrics, ref)
    log.info("evaluate %s: previous version v%04d: %d corners added, %d removed, %d moved near the drive", drive,
             prev.version, doc["added"], doc["removed"], doc["moved"])
    return doc, ev_prev
