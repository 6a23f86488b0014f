"""``cornermap drive check drive.yaml``: validate a drive file against its files and summarise the drive.

Runs what ingest would run on the drive's small inputs (the drive file, GNSS, odometry and stamps CSVs, the
scan list) plus a sample of scans, without writing anything. Problems that would make a build wrong or fail
(no scans, no GNSS pose for any scan, unreadable samples, every GNSS row rejected) are listed together;
everything else is summarised.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stages.ingest.params import IngestParams


@dataclass
class DriveCheck:
    summary: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)


def _span(stamps_ns: np.ndarray) -> str:
    return (
        f"{(stamps_ns.max() - stamps_ns.min()) / 1e9:.1f} s ({stamps_ns.min() / 1e9:.3f}..{stamps_ns.max() / 1e9:.3f})"
    )


def check_drive(path: Path, params: IngestParams = IngestParams(), sample_scans: int = 5) -> DriveCheck:
    """Validate and summarise one drive; raises ConfigError only for a drive file that does not parse."""
    from stages.common.geodesy import EnuOrigin
    from stages.ingest.compute import DriveIngest
    from stages.ingest.drive_file import load_drive_file
    from stages.ingest.frame import frame_check_lines
    from stages.ingest.scan_pass import process_scan

    spec = load_drive_file(path)
    out = DriveCheck()
    ingest = DriveIngest(spec.name, spec, params, None, str(path))
    g = ingest.gnss
    if g is not None and len(g.stamp_ns):
        ingest.origin = EnuOrigin(float(g.lat_deg[0]), float(g.lon_deg[0]), float(g.h_m[0]))
    scans = ingest.scans
    stamped = np.array([s.stamp_ns for s in scans if s.stamp_ns is not None], np.int64)
    with_file = sum(s.path is not None for s in scans)
    out.summary.append(f"drive {spec.name}: sensor {spec.sensor}, scans {spec.scans.format} in {spec.scans.folder}")
    if not scans:
        out.problems.append(f"scans: no {spec.scans.format} files in {spec.path(spec.scans.folder)}")
    else:
        gaps = ingest.report.count("scan_gap")
        out.summary.append(f"scans: {len(scans)} (ids {scans[0].scan_id}..{scans[-1].scan_id}, {with_file} with a "
                           f"file, {len(stamped)} stamped, {gaps} gap(s)); time span "
                           + (_span(stamped) if len(stamped) else "unknown"))
    lines = frame_check_lines(spec, ingest)  # the frame, prior trajectory and beam table (stages/ingest/frame.py)
    out.summary += lines[0]
    out.warnings += lines[1]
    out.problems += lines[2]
    if g is None:
        pass  # the frame line above says what places the drive
    elif not len(g.stamp_ns):
        out.problems.append(f"gnss: every row of {spec.gnss.file} was rejected")
    else:
        dt = np.diff(g.stamp_ns) / 1e9
        rate = 1.0 / np.median(dt) if len(dt) else 0.0
        inside = (stamped >= g.stamp_ns[0]) & (stamped <= g.stamp_ns[-1]) if len(stamped) else np.zeros(0, bool)
        out.summary.append(
            f"gnss: {len(g.stamp_ns)} fixes at {rate:.1f} Hz over {_span(g.stamp_ns)}; covers "
            f"{int(inside.sum())} of {len(stamped)} scan stamps ({100 * inside.mean() if len(inside) else 0:.0f} %)"
            f"; roll/pitch {'present' if g.roll_pitch_known else 'absent (no prior)'}"
            f"; std {'defaults for ' + ', '.join(g.defaults_used) if g.defaults_used else 'from the file'}"
        )
        if len(stamped) and not inside.any():
            out.problems.append(f"gnss: no scan stamp lies inside the GNSS time span (scans {_span(stamped)}, GNSS "
                                f"{_span(g.stamp_ns)}); hint: check gnss.time.base, scan_times and their units")
        elif len(inside) and not inside.all():
            out.warnings.append(f"gnss: {int((~inside).sum())} scan stamps lie outside the GNSS time span")
    rejected = Counter(r["kind"] for r in ingest.report.rows if r["kind"] in ("timestamp", "gnss_row"))
    if rejected:
        first = next(r for r in ingest.report.rows if r["kind"] in ("timestamp", "gnss_row"))
        out.warnings.append(f"rows rejected: {dict(rejected)}; first: {first['file']} record {first['record']}: "
                            f"{first['reason']}")
    if spec.odometry is None:
        out.summary.append("odometry: none (the EKF evaluation uses ICP increments)")
    else:
        track = ingest.odometry_table()
        n = track.num_rows
        out.summary.append(f"odometry: {n} rows" + (f" over {_span(track['stamp_ns'].to_numpy())}" if n else ""))
        if not n:
            out.problems.append(f"odometry: {spec.odometry.file} has no usable row")
    if spec.survey is not None:
        out.summary.append(f"survey: {spec.survey.file} in {spec.survey.crs}")
    _sample_scans(scans, spec, params, sample_scans, out, process_scan)
    return out


def _sample_scans(scans, spec, params, n_sample: int, out: DriveCheck, process_scan) -> None:
    from stages.ingest.scan_pass import elevation_table

    have = [s for s in scans if s.path is not None and s.stamp_ns is not None]
    if not have:
        return
    picks = sorted({int(round(i)) for i in np.linspace(0, len(have) - 1, min(n_sample, len(have)))})
    rings, points, bad = [], [], []
    for i in picks:
        r = process_scan(have[i], spec, 0, params.min_range_m, params.ring_vote_min_share)
        if r.points is None:
            bad.append(f"{r.index_row['source_file']}: {r.index_row['reason']}")
            continue
        rings.append(r.index_row["rings_present"])
        points.append(r.index_row["n_points"])
    table = len(elevation_table(spec))
    if rings:
        out.summary.append(f"sampled {len(picks)} scans: {min(points)}-{max(points)} points, rings per scan "
                           f"{min(rings)}-{max(rings)}" + (f" of {table}" if table else ""))
    if bad:
        (out.problems if len(bad) == len(picks) else out.warnings).append(
            f"{len(bad)} of {len(picks)} sampled scans unreadable: " + "; ".join(bad[:3]))
