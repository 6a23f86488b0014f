"""Ingest adapter: drive.yaml -> the eight ingest datasets (Arrow tables, scans streamed by piece)."""
from __future__ import annotations

import logging
from typing import Callable, Iterable, Iterator

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.declare import StageContext
from pipeline.errors import ConfigError, DataQualityError
from stages.common.geodesy import EnuOrigin, geodetic_to_enu
from stages.common.records import Extrinsics
from stages.ingest.drive_file import DriveSpec, load_drive_file
from stages.ingest.frame import frame_source
from stages.ingest.gnss_csv import GnssLimits, check_within_area, find_gaps, read_gnss, read_odometry
from stages.ingest.origin import resolve_enu_origin
from stages.ingest.params import IngestParams
from stages.ingest.pose_interpolation import attitude_from_rpy, interpolate_poses, vehicle_origin_from_reference
from stages.ingest.report import IngestReport
from stages.ingest.scan_list import list_scans
from stages.ingest.scan_pass import PIECE_ROWS, ScanResult, iter_scan_results, points_table
from stages.ingest.survey import iter_survey_enu

log = logging.getLogger(__name__)


class _Deferred:
    """An iterable of tables computed on first iteration (after the scan pass when it has run)."""

    def __init__(self, produce: Callable[[], Iterable]):
        self._produce = produce

    def __iter__(self) -> Iterator:
        yield from self._produce()


def _table(name: str, columns: dict):
    import pyarrow as pa

    from schemas import SCHEMAS

    return pa.table(columns, schema=SCHEMAS[name])


def gnss_limits(params: IngestParams) -> GnssLimits:
    return GnssLimits((params.gnss_default_std_east_m, params.gnss_default_std_north_m, params.gnss_default_std_up_m),
                      float(np.radians(params.gnss_default_std_heading_deg)),
                      (params.gnss_height_min_m, params.gnss_height_max_m), params.gnss_max_speed_mps)


class DriveIngest:
    def __init__(self, drive: str, spec: DriveSpec, params: IngestParams, origin: EnuOrigin | None,
                 drive_file: str = ""):
        self.drive, self.spec, self.params, self.origin = drive, spec, params, origin
        self.drive_file = drive_file or str(spec.drive_dir / "drive.yaml")
        self.report = IngestReport()
        self.gnss = None
        if spec.gnss:
            self.gnss, issues = read_gnss(spec.path(spec.gnss.file), spec.gnss, gnss_limits(params))
            for issue in issues:
                kind = "timestamp" if "time" in issue.reason else "gnss_row"
                self.report.add(kind, spec.gnss.file, issue.record, 1, issue.reason)
            for key in self.gnss.defaults_used:
                param = "gnss_default_std_heading_deg" if key == "std_heading" else f"gnss_default_{key}_m"
                value = getattr(params, param)
                log.warning("%s: the GNSS file has no %s; using the ingest param %s = %s", spec.gnss.file, key,
                            param, value)
                self.report.add("gnss_default", spec.gnss.file, None, len(self.gnss.stamp_ns),
                                f"no {key} column: ingest param {param} = {value} used for every fix")
            if not self.gnss.roll_pitch_known:
                self.report.add("gnss_default", spec.gnss.file, None, len(self.gnss.stamp_ns),
                                "no roll/pitch columns: attitude is yaw only; no roll/pitch prior downstream")
            for i, gap_s in find_gaps(self.gnss.stamp_ns, params.gnss_gap_s):
                self.report.add("gnss_gap", spec.gnss.file, int(self.gnss.records[i]), 1,
                                f"{gap_s:.3f} s without a fix after this record (threshold {params.gnss_gap_s} s)")
        self.scans = list_scans(spec, self.gnss, params.max_scans, self.report)
        self.report_coverage()
        self._index_rows: list[dict] | None = None
        self._untimed = 0
        self._prior = None

    # ---- scan list and stamps --------------------------------------------------------------------------
    # ---- the scan pass -----------------------------------------------------------------------------------
    def _results(self) -> Iterator[ScanResult]:
        p = self.params
        return iter_scan_results(self.scans, self.spec, p.chunk_size_scans, p.min_range_m, p.ring_vote_min_share)

    def _record(self, rows: list[dict], result: ScanResult) -> None:
        row = result.index_row
        rows.append(row)
        file = row["source_file"] or f"scan {row['scan_id']}"
        if row["status"] != "ok":
            self.report.add("quarantined_file", file, row["scan_id"], 1, row["reason"])
            return
        if result.points.time_unused:  # the file has times, but not within one sweep: named per scan
            self.report.add("deskew", file, row["scan_id"], len(result.points), result.points.time_unused)
        elif result.points.time_offset_s is None:
            self._untimed += 1
        reasons = {"nonfinite": "non-finite coordinate or time", "zero": "zero point (0, 0, 0)",
                   "near": f"closer than min_range_m {self.params.min_range_m} m"}
        for key, count in result.drops.items():
            if count:
                self.report.add("dropped_points", file, row["scan_id"], count, reasons[key])
        if result.missing_rings:
            self.report.add("ring_coverage", file, row["scan_id"], len(result.missing_rings),
                            f"{row['rings_present']} rings present; missing {result.missing_rings[:16]}")

    def iter_scan_tables(self) -> Iterator:
        rows: list[dict] = []
        pending: list[ScanResult] = []
        pending_rows = 0
        already_counted = self._index_rows is not None
        for result in self._results():
            if not already_counted:
                self._record(rows, result)
            if pending and (result.index_row["chunk"] != pending[0].index_row["chunk"]
                            or pending_rows + result.index_row["n_points"] > PIECE_ROWS):
                yield points_table(self.drive, pending[0].index_row["chunk"], pending)
                pending, pending_rows = [], 0
            if result.points is not None:
                pending.append(result)
                pending_rows += len(result.points)
        if pending:
            yield points_table(self.drive, pending[0].index_row["chunk"], pending)
        if not already_counted:
            self._scan_pass_done(rows)

    def index_rows(self) -> list[dict]:
        if self._index_rows is None:  # scans not streamed (yet): a counting pass without tables
            rows: list[dict] = []
            for result in self._results():
                self._record(rows, result)
            self._scan_pass_done(rows)
        return self._index_rows

    def _scan_pass_done(self, rows: list[dict]) -> None:
        """The scan pass's index rows kept, the untimed scans reported, and a drive whose scan files were all
        quarantined refused: it has no map to give, so a data-quality error names the folder and the first file's
        reason (downstream it only showed as "no poses_gnss rows" in the pose graph)."""
        self._index_rows = rows
        if self._untimed:
            self.report.add("deskew", self.spec.scans.folder, None, self._untimed,
                            "no per-point time in these scans: time_offset_s is 0, so they are not deskewed (the "
                            "motion during one sweep stays in the cloud)")
        if rows and not any(r["status"] == "ok" for r in rows):
            first = rows[0]
            raise DataQualityError(
                f"ingest {self.drive}: none of the {len(rows)} scans in {self.spec.path(self.spec.scans.folder)} "
                f"could be read; first: {first['source_file'] or first['scan_id']}: {first['reason']}; hint: check "
                "that the files exist (a symbolic link whose target is gone counts as missing) and the drive file's "
                "scans.format")

    # ---- tables -----------------------------------------------------------------------------------------
    def scan_index_table(self):
        rows = self.index_rows()
        cols = ["chunk", "scan_id", "stamp_ns", "source_file", "n_points", "n_dropped_nonfinite",
                "n_dropped_zero", "rings_present", "ring_source", "status", "reason"]
        return _table("scan_index", {"drive": [self.drive] * len(rows), **{c: [r[c] for r in rows] for c in cols}})

    def report_coverage(self) -> None:
        """How much of the scans' time the GNSS covers (drive-level; reported, never silent)."""
        g = self.gnss
        stamps = np.array([s.stamp_ns for s in self.scans if s.stamp_ns is not None], np.int64)
        if g is None or not len(stamps):
            return
        if not len(g.stamp_ns):
            self.report.add("gnss_coverage", self.spec.gnss.file, None, len(stamps),
                            "no usable GNSS fix: no scan has a GNSS pose")
            return
        inside = (stamps >= g.stamp_ns[0]) & (stamps <= g.stamp_ns[-1])
        if not inside.all():
            span = lambda a, b: f"{a / 1e9:.3f}..{b / 1e9:.3f} s"  # noqa: E731
            self.report.add("gnss_coverage", self.spec.gnss.file, None, int((~inside).sum()),
                            f"{int(inside.sum())} of {len(stamps)} scan stamps inside the GNSS time span "
                            f"(scans {span(stamps.min(), stamps.max())}, GNSS {span(g.stamp_ns[0], g.stamp_ns[-1])}); "
                            f"the others have no valid GNSS pose. Hint: check gnss.time.base and scan_times")

    def _vehicle_fixes(self):
        g = self.gnss
        attitude = attitude_from_rpy(g.roll_rad, g.pitch_rad, g.yaw_enu_rad)
        reference = geodetic_to_enu(g.lat_deg, g.lon_deg, g.h_m, self.origin)
        return vehicle_origin_from_reference(reference, attitude, self.spec.gnss.lever_arm_m), attitude

    def gnss_table(self):
        g = self.gnss
        if g is None or self.origin is None or not len(g.stamp_ns):
            return _table("gnss_enu", {n: [] for n in _names("gnss_enu")})
        position, _ = self._vehicle_fixes()
        unknown = np.full(len(g.stamp_ns), np.nan)
        return _table("gnss_enu", {
            "drive": [self.drive] * len(g.stamp_ns), "stamp_ns": g.stamp_ns, "east_m": position[:, 0],
            "north_m": position[:, 1], "up_m": position[:, 2],
            "roll_rad": g.roll_rad if g.roll_pitch_known else unknown,
            "pitch_rad": g.pitch_rad if g.roll_pitch_known else unknown,
            "yaw_enu_rad": g.yaw_enu_rad, "std_east_m": g.std_enu_m[:, 0], "std_north_m": g.std_enu_m[:, 1],
            "std_up_m": g.std_enu_m[:, 2], "std_yaw_rad": g.std_yaw_rad})

    def prior(self):
        """The drive's ``poses_prior`` rows (prior file at the scans, start pose), computed once."""
        if self._prior is None:
            from stages.ingest.prior import concat, prior_file_poses, start_pose

            scans = [s for s in self.scans if s.stamp_ns is not None]
            ids = np.array([s.scan_id for s in scans], np.int64)
            stamps = np.array([s.stamp_ns for s in scans], np.int64)
            parts = []
            if self.spec.prior is not None and len(ids):
                parts.append(prior_file_poses(self.spec, self.drive, ids, stamps, self.origin,
                                              self.params.prior_gap_s))
                n_bad = int((~parts[-1].valid).sum())
                if n_bad:
                    self.report.add("prior", self.spec.prior.file, None, n_bad,
                                    f"{n_bad} of {len(ids)} scans without a prior pose (outside the prior's span or "
                                    f"in a gap longer than prior_gap_s {self.params.prior_gap_s} s)")
            if self.spec.start is not None and len(ids):
                parts.append(start_pose(self.spec, self.drive, int(ids[0]), int(stamps[0]), self.origin))
            self._prior = concat(parts, self.drive)
        return self._prior

    def prior_table(self):
        return _table("poses_prior", self.prior().to_columns())

    def _poses_from_prior(self):
        """poses_gnss rows from the prior where the drive has no GNSS (``prior_as_gnss``), or None."""
        from stages.ingest.prior import as_absolute_poses

        if self.spec.gnss is not None or not self.params.prior_as_gnss or self.origin is None:
            return None
        absolute = as_absolute_poses(self.prior())
        if absolute is None:
            return None
        self.report.add("prior", self.spec.prior.file, None, int(absolute.valid.sum()),
                        f"no GNSS: poses_gnss holds {absolute.how} (ingest param prior_as_gnss)")
        q = Rotation.from_matrix(absolute.T[:, :3, :3]).as_quat()
        n = len(absolute.scan_id)
        return _table("poses_gnss", {
            "drive": [self.drive] * n, "scan_id": absolute.scan_id, "stamp_ns": absolute.stamp_ns,
            "x_m": absolute.T[:, 0, 3], "y_m": absolute.T[:, 1, 3], "z_m": absolute.T[:, 2, 3],
            "qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2], "qw": q[:, 3], "std_east_m": absolute.std_enu_yaw[:, 0],
            "std_north_m": absolute.std_enu_yaw[:, 1], "std_up_m": absolute.std_enu_yaw[:, 2],
            "std_yaw_rad": absolute.std_enu_yaw[:, 3], "valid": absolute.valid,
            "roll_pitch_known": np.ones(n, bool)})

    def poses_table(self):
        g = self.gnss
        scans = [s for s in self.scans if s.stamp_ns is not None]
        if g is None and scans:
            from_prior = self._poses_from_prior()
            if from_prior is not None:
                return from_prior
            return self._scans_without_fix(scans)
        if g is None or self.origin is None or not len(g.stamp_ns) or not scans:
            return _table("poses_gnss", {n: [] for n in _names("poses_gnss")})
        position, attitude = self._vehicle_fixes()
        std = np.column_stack([g.std_enu_m, g.std_yaw_rad])
        query = np.array([s.stamp_ns for s in scans], np.int64)
        poses = interpolate_poses(g.stamp_ns, position, attitude, std, query, self.params.gnss_gap_s)
        q = poses.quat_xyzw
        return _table("poses_gnss", {
            "drive": [self.drive] * len(query), "scan_id": [s.scan_id for s in scans], "stamp_ns": query,
            "x_m": poses.position_enu_m[:, 0], "y_m": poses.position_enu_m[:, 1], "z_m": poses.position_enu_m[:, 2],
            "qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2], "qw": q[:, 3], "std_east_m": poses.std[:, 0],
            "std_north_m": poses.std[:, 1], "std_up_m": poses.std[:, 2], "std_yaw_rad": poses.std[:, 3],
            "valid": poses.valid, "roll_pitch_known": np.full(len(query), g.roll_pitch_known)})

    def _scans_without_fix(self, scans):
        """A drive without GNSS: one row per stamped scan, valid false (no fix; the pose graph places the drive from
        its ``poses_prior``), so that every stage sees the drive's scans."""
        n = len(scans)
        nan, zero = np.full(n, np.nan), np.zeros(n)
        return _table("poses_gnss", {
            "drive": [self.drive] * n, "scan_id": [s.scan_id for s in scans],
            "stamp_ns": np.array([s.stamp_ns for s in scans], np.int64), "x_m": zero, "y_m": zero, "z_m": zero,
            "qx": zero, "qy": zero, "qz": zero, "qw": np.ones(n), "std_east_m": nan, "std_north_m": nan,
            "std_up_m": nan, "std_yaw_rad": nan, "valid": np.zeros(n, bool), "roll_pitch_known": np.zeros(n, bool)})

    def odometry_table(self):
        if self.spec.odometry is None:
            return _table("odometry_raw", {n: [] for n in _names("odometry_raw")})
        cols, issues = read_odometry(self.spec.path(self.spec.odometry.file), self.spec.odometry)
        for issue in issues:
            self.report.add("timestamp", self.spec.odometry.file, issue.record, 1, issue.reason)
        return _table("odometry_raw", {"drive": [self.drive] * len(cols["stamp_ns"]), **cols})

    def drive_info_table(self):
        rows = self.index_rows()
        o = self.origin
        return _table("drive_info", {
            "drive": [self.drive], "sensor": [self.spec.sensor],
            "T_vehicle_lidar": [Extrinsics.to_column(self.spec.T_vehicle_lidar_matrix)],
            "origin_lat_deg": [o.lat_deg if o else np.nan], "origin_lon_deg": [o.lon_deg if o else np.nan],
            "origin_h_m": [o.h_m if o else np.nan], "n_scans": [len(rows)],
            "n_quarantined": [sum(r["status"] != "ok" for r in rows)],
            "drive_file": [self.drive_file]})

    def iter_survey_tables(self) -> Iterator:
        s = self.spec.survey
        if s is None:
            yield _table("survey_enu", {n: [] for n in _names("survey_enu")})
            return
        if self.origin is None:
            raise ConfigError(f"drive {self.drive}", ["survey needs an ENU origin: name enu_origin in the "
                                                      "workflow, or give a drive GNSS"])
        for enu, intensity in iter_survey_enu(self.spec.path(s.file), s.crs, self.origin,
                                              self.params.survey_chunk_points):
            yield _table("survey_enu", {"drive": [self.drive] * len(enu), "east_m": enu[:, 0],
                                        "north_m": enu[:, 1], "up_m": enu[:, 2], "intensity": intensity})


def _survey_source(spec) -> str | None:
    """The survey cloud's content hash (stages/common/survey_parts.py: readers read each distinct cloud once), or
    None without a survey or when the file cannot be read (ingest's own survey reader names that error)."""
    if spec.survey is None:
        return None
    from pipeline.fingerprint import file_sha256

    try:
        return file_sha256(spec.path(spec.survey.file))
    except OSError:
        return None


def _names(dataset: str) -> list[str]:
    from schemas import SCHEMAS

    return SCHEMAS[dataset].names


def compute(ctx: StageContext) -> dict:
    drive = ctx.partition.drive
    if drive not in ctx.drives:
        raise ConfigError(f"ingest partition {drive!r}", [f"no drive file for {drive!r}; drives: "
                                                          f"{', '.join(ctx.drives)}"])
    from pipeline.drive_store import is_uri, local_drive
    from pipeline.storage import normalise_uri

    recorded = ctx.drives[drive]
    spec = load_drive_file(local_drive(recorded))  # a drive in a bucket: fetched into this task's scratch
    if is_uri(recorded):
        recorded = normalise_uri(recorded)
    frame = frame_source(spec)
    placed = set(ctx.settings.get("map_drives") or []) | set(ctx.settings.get("eval_drives") or [])
    if frame.problem and drive in placed:  # before anything is read: a map or evaluation drive that cannot be placed
        raise ConfigError(f"ingest {drive}", [frame.problem])  # in the map's frame stops the build here, in one line
    if spec.name != drive:
        log.warning("drive file %s names the drive %r; the workflow calls it %r (used)", recorded,
                    spec.name, drive)
    origin = resolve_enu_origin(ctx.settings.get("enu_origin"), (local_drive(p) for p in ctx.drives.values()))
    ingest = DriveIngest(drive, spec, ctx.params, origin, str(recorded))
    if ingest.gnss is not None and drive in ctx.settings.get("map_drives", [drive]):
        # before any scan is read: a map drive outside the map's area is refused (exit 3); an evaluation drive is
        # localized anyway (far off, its verdict is "no coverage")
        check_within_area(ingest.gnss, origin, ctx.settings.get("max_radius_m"), drive, spec.gnss.file)
    return {
        "scans": ingest.iter_scan_tables(),
        "scan_index": _Deferred(lambda: [ingest.scan_index_table()]),
        "gnss": ingest.gnss_table(),
        "odometry": ingest.odometry_table(),
        "poses_gnss": ingest.poses_table(),
        "poses_prior": ingest.prior_table(),
        "drive_info": _Deferred(lambda: [ingest.drive_info_table()]),
        "survey": ingest.iter_survey_tables(),
        "report": _Deferred(lambda: [ingest.report.to_table(drive)]),
        "_extra": {"enu_origin": origin.as_dict() if origin else None, "drive": drive,
                   "time_base": spec.gnss.time.base if spec.gnss else None,
                   "survey_sha256": _survey_source(spec)},
    }
