"""What fixes a drive in the map's frame, said in one line before anything is read.

A drive is placed in the map's ENU frame by (in order): its GNSS/INS fixes; a prior trajectory in ENU about a
stated origin; a prior trajectory in a local frame plus a stated start heading (at the map's origin or a stated
position); a start heading alone (odometry and loop closures give the rest), unless the drive is a keyframe drive
(its edges would rest on unchecked global registrations). A local prior without a start heading, a keyframe drive
with a start heading alone, and a drive with none of these, cannot be placed: ``cornermap drive check`` warns
(``--placed``: exit 3, as ``cornermap rebuild`` runs it to quarantine the drive), and a run refuses it before any
stage starts (``preflight``, exit 3: the drive lacks what places it); a drive that starts at the map's origin needs
that origin stated (``cornermap build --origin``, a pinned map, the workflow's ``enu_origin``; exit 2 without it).
"""
from __future__ import annotations

from dataclasses import dataclass

from stages.ingest.drive_file import DriveSpec

ADD = ("add one of: a gnss section (GNSS/INS CSV or KITTI oxts folder); prior: a TUM/KITTI poses file with its "
       "frame (enu + origin, or local) and std; start: {heading_deg, heading_convention} for a drive that starts at "
       "cornermap build --origin (docs/drive-file.md)")


# The odometry's default keyframe_min_dt_s: consecutive scans further apart are registered as keyframes (global
# registration where no reference increment exists). Stated here as a number: a stage does not import another.
KEYFRAME_GAP_S = 0.35


def median_scan_gap_s(spec: DriveSpec) -> float | None:
    """The median time between consecutive stamped scans of the drive (None: fewer than two, or unreadable; the
    drive check names that)."""
    import numpy as np

    from pipeline.errors import CornermapError
    from stages.ingest.report import IngestReport
    from stages.ingest.scan_list import list_scans

    try:
        stamps = np.array([f.stamp_ns for f in list_scans(spec, None, None, IngestReport()) if f.stamp_ns is not None],
                          np.int64)
    except (CornermapError, OSError):
        return None
    return float(np.median(np.diff(np.sort(stamps)))) * 1e-9 if len(stamps) > 1 else None


@dataclass(frozen=True)
class FrameSource:
    kind: str | None  # gnss | prior_enu | prior_local+start | start | prior_local | None
    line: str  # what places the drive (drive check's summary line)
    problem: str | None  # why a build refuses the drive now, with what to add; None: it can be built
    needs_origin: bool = False  # it starts at the map's origin (start: without a position)


def frame_source(spec: DriveSpec) -> FrameSource:
    p, s = spec.prior, spec.start
    if spec.gnss is not None:
        extra = " (prior trajectory: poses_prior, odometry seeds)" if p else ""
        return FrameSource("gnss", f"frame: the GNSS/INS fixes of {spec.gnss.file}{extra}", None)
    if p is not None and p.frame == "enu":
        o = p.origin
        return FrameSource("prior_enu", f"frame: no GNSS; the prior trajectory {p.file} in ENU about {o.lat_deg:.7f}, "
                                        f"{o.lon_deg:.7f}, {o.h_m:.2f} m (the drive's absolute input)", None)
    where = "the map's origin (cornermap build --origin)" if s is None or s.position is None else \
        f"{s.position.lat_deg:.7f}, {s.position.lon_deg:.7f}"
    at_origin = s is not None and s.position is None
    if p is not None and s is not None:
        return FrameSource("prior_local+start", f"frame: no GNSS; the local prior trajectory {p.file} aligned at the "
                                                f"start heading {s.heading_deg:g} deg ({s.heading_convention}, std "
                                                f"{s.std_heading_deg:g} deg) at {where}", None, at_origin)
    if s is not None:
        line = (f"frame: no GNSS; the start heading {s.heading_deg:g} deg ({s.heading_convention}, std "
                f"{s.std_heading_deg:g} deg) at {where}, then odometry and loop closures")
        gap_s = median_scan_gap_s(spec)
        if gap_s is not None and gap_s > KEYFRAME_GAP_S:
            return FrameSource("start", line, f"drive {spec.name}: a keyframe drive (median {gap_s:.2f} s between "
                               "scans) with a start heading alone: its scan-to-scan edges would rest on global "
                               "registrations nothing checks (one matched a wrong place 7.8 m off on tiny seed 862); "
                               "add prior: its keyframes' poses (TUM/KITTI) with their std", at_origin)
        return FrameSource("start", line, None, at_origin)
    if p is not None:
        return FrameSource("prior_local", f"frame: none (the prior trajectory {p.file} is in a local frame)",
                           f"drive {spec.name}: its frame cannot be fixed: no GNSS, and the prior trajectory "
                           f"{p.file} is in a local frame; add start: {{heading_deg, heading_convention}} (the drive "
                           "starts at cornermap build --origin), or state the prior's ENU origin (prior.frame: enu, "
                           "prior.origin)")
    return FrameSource(None, "frame: none (no GNSS, no prior trajectory, no start heading)",
                       f"drive {spec.name}: its frame cannot be fixed: no GNSS, no prior trajectory, no start "
                       f"heading; {ADD}")


def preflight(drives: dict, settings: dict) -> None:
    """Before any stage of a run: every map and evaluation drive can be placed in the map's frame. A drive nothing
    places: ``DataQualityError`` (exit 3), one line naming each such drive and what to add to its drive file; a
    drive that starts at the map's origin while the run states none: ``OptionError`` (exit 2) naming the drive and
    ``--origin``. (The ingest stage's declared ``preflight``.)"""
    from pipeline.errors import DataQualityError, OptionError
    from stages.ingest.drive_file import load_drive_file

    placed = list(settings.get("map_drives") or []) + list(settings.get("eval_drives") or [])
    problems, at_origin = [], []
    for name in placed:
        if name not in drives:
            continue
        frame = frame_source(load_drive_file(drives[name]))
        if frame.problem:
            problems.append(f"{frame.problem} ({drives[name]})")
        elif frame.needs_origin and not settings.get("enu_origin"):
            at_origin.append(name)
    if problems:
        raise DataQualityError("; ".join(problems))
    if at_origin:
        raise OptionError("--origin", [f"drive {', '.join(at_origin)} starts at the map's origin (start: without a "
                                       "position) and the map states none; give cornermap build --origin LAT,LON,H "
                                       "(where the drive starts), or start.position in its drive file"])


def frame_check_lines(spec: DriveSpec, ingest) -> tuple[list[str], list[str], list[str]]:
    """``cornermap drive check``'s lines on the drive's frame, prior trajectory and beam table: (summary, warnings,
    problems). A drive that cannot be placed is a warning here (the drive file is valid; a build refuses it); a prior
    or calibration file that does not decode is a problem. ``ingest`` is the check's ``DriveIngest`` (no origin)."""
    from pipeline.errors import CornermapError

    summary, warnings, problems = [], [], []
    frame = frame_source(spec)
    summary.append(frame.line)
    if frame.problem:
        warnings.append(f"{frame.problem}; a build refuses it")
    if spec.calibration_file:
        from stages.ingest.sensor_calibration import read_beam_calibration

        try:
            cal = read_beam_calibration(spec.path(spec.calibration_file))
            summary.append(f"beam table: {len(cal.elevations_deg)} beams {cal.elevations_deg[0]:.2f}.."
                           f"{cal.elevations_deg[-1]:.2f} deg from {spec.calibration_file} ({cal.kind}; {cal.why})")
            if cal.model not in (None, spec.sensor) and spec.sensor != "generic":
                warnings.append(f"calibration_file {spec.calibration_file} looks like {cal.model} ({cal.why}); the "
                                f"drive file says sensor {spec.sensor}")
        except CornermapError as exc:
            problems.append(f"calibration_file: {exc}")
    if spec.prior is not None:
        try:
            if ingest.origin is None:  # the check knows no map origin: the prior's own, or any (only counts matter)
                from stages.common.geodesy import EnuOrigin

                o = spec.prior.origin
                ingest.origin = EnuOrigin(o.lat_deg, o.lon_deg, o.h_m) if o is not None else EnuOrigin(0.0, 0.0, 0.0)
            prior = ingest.prior()
            rows = prior.source == "prior_file"
            n, ok = int(rows.sum()), int((prior.valid & rows).sum())
            summary.append(f"prior: {spec.prior.file} ({spec.prior.format}, frame {spec.prior.frame}, time "
                           f"{spec.prior.time}): a pose for {ok} of {n} scans")
            if n and not ok:
                problems.append(f"prior: {spec.prior.file} gives no scan a pose; hint: check prior.time and that "
                                "its times are in the drive's time base")
        except CornermapError as exc:
            problems.append(f"prior: {exc}")
    return summary, warnings, problems
