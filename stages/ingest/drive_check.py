"""``cornermap drive check drive.yaml``: validate a drive file against its files and summarise the drive.

Runs what ingest would run on the drive's small inputs (the drive file, GNSS, odometry and stamps CSVs, the
scan list) plus a sample of scans, without writing anything. Problems that would make a build wrong or fail
(no scans, no GNSS pose for any scan, unreadable samples, every GNSS row rejected, an incomplete drive) are listed
together; everything else is summarised.

A drive is incomplete (a copy still running or cut short) when:
  * a stamps file lists scans that have no file: more than ``MAX_MISSING_LISTED`` of them (fewer are gaps: kept as
    such and warned about);
  * the folder holds a ``SHA256SUMS`` file (``sha256sum`` format, paths relative to it) and a file it lists is
    missing or differs.
Scans that span less than ``MIN_GNSS_SPAN_SHARE`` of the GNSS/INS time span are a warning only: without a stamps
file or SHA256SUMS nothing says how many scans there should be, and a GNSS log longer than the lidar's is legitimate
(the simulator's ``--max-scans`` drives: 30 scans over 30.8 s of GNSS).
``content_fingerprint`` (``--content``): sha256 over the drive file and every file it references as ingest reads
them (the scan files of its format, the GNSS, odometry, stamps and survey files), by name relative to the drive
folder and content: a copy with new modification times keeps it, a file beside them that ingest never reads does
not enter it.
"""
from __future__ import annotations

import hashlib
import os
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stages.ingest.params import IngestParams

MAX_MISSING_LISTED = 0.1  # share of the scans a stamps file lists that may lack a file (gaps)
MIN_GNSS_SPAN_SHARE = 0.5  # share of the GNSS/INS time span the scans must cover
SUMS_FILE = "SHA256SUMS"
_SUM_LINE = re.compile(r"^([0-9a-fA-F]{64}) [ *](.+)$")


@dataclass
class DriveCheck:
    summary: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)


def _span(stamps_ns: np.ndarray) -> str:
    return (
        f"{(stamps_ns.max() - stamps_ns.min()) / 1e9:.1f} s ({stamps_ns.min() / 1e9:.3f}..{stamps_ns.max() / 1e9:.3f})"
    )


def check_drive(path: Path, params: IngestParams = IngestParams(), sample_scans: int = 5,
                content: bool = False) -> DriveCheck:
    """Validate and summarise one drive; raises ConfigError only for a drive file that does not parse. ``content``:
    add the line ``content: sha256 ...`` (``content_fingerprint``; reads every file the drive references)."""
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
    _completeness(spec, scans, g, out)
    _sample_scans(scans, spec, params, sample_scans, out, process_scan)
    if content:
        digest, n_files, n_bytes = content_fingerprint(Path(path), spec)
        out.summary.append(f"content: sha256 {digest} of {n_files} files the drive file references "
                           f"({n_bytes / 2**20:.1f} MiB)")
    return out


def _completeness(spec, scans, g, out: DriveCheck) -> None:
    """The problems of a drive still being copied, or cut short (module docstring)."""
    stamped = np.array([s.stamp_ns for s in scans if s.path is not None and s.stamp_ns is not None], np.int64)
    listed = spec.scan_times.source in ("stamps_csv", "pcd_field")
    no_file = [s.scan_id for s in scans if s.path is None]
    if listed and scans and no_file:
        share = len(no_file) / len(scans)
        line = (f"scans: incomplete: {len(no_file)} of the {len(scans)} scans listed in {spec.stamps_file.name} have "
                f"no file in {spec.scans.folder} (first: scan {no_file[0]})")
        if share > MAX_MISSING_LISTED:
            out.problems.append(line + "; a copy still running or cut short? hint: deliver the whole folder")
        else:
            out.warnings.append(line + " (kept as gaps)")
    if g is not None and len(g.stamp_ns) > 1 and len(stamped) > 1:
        gnss_s = (g.stamp_ns[-1] - g.stamp_ns[0]) / 1e9
        scans_s = (stamped.max() - stamped.min()) / 1e9 + 1.0 / spec.scan_rate_hz
        if gnss_s > 0 and scans_s < MIN_GNSS_SPAN_SHARE * gnss_s:
            expected = int(round(gnss_s * spec.scan_rate_hz))
            out.warnings.append(
                f"the scans span {scans_s:.1f} s of the GNSS/INS file's {gnss_s:.1f} s (at {spec.scan_rate_hz:g} Hz "
                f"about {expected} scans, {len(stamped)} found): a copy cut short, or a GNSS log longer than the "
                f"lidar's; hint: if scans are missing, deliver the whole folder (a {SUMS_FILE} file makes it checked)")
    _check_sums(spec.drive_dir, out)


def _check_sums(folder: Path, out: DriveCheck) -> None:
    """A ``SHA256SUMS`` file in the drive folder: every file it lists must be there with that content."""
    sums = folder / SUMS_FILE
    if not sums.is_file():
        return
    missing, differ, bad_lines, n = [], [], 0, 0
    with open(sums, "rb") as fh:
        for raw in fh:
            m = _SUM_LINE.match(raw.decode("utf-8", "replace").rstrip("\r\n"))
            if not m:
                bad_lines += bool(raw.strip())
                continue
            n += 1
            rel = m.group(2)
            target = Path(os.path.normpath(folder / rel))
            if not target.is_relative_to(folder) or not target.is_file():
                missing.append(rel)
            elif _sha256(target) != m.group(1).lower():
                differ.append(rel)
    if missing or differ or bad_lines:
        out.problems.append(f"{SUMS_FILE}: incomplete: it lists {n} files: {len(missing)} missing, {len(differ)} with "
                            f"another content, {bad_lines} unreadable line(s)"
                            + (f" (first missing: {missing[0]})" if missing else "")
                            + (f" (first differing: {differ[0]})" if differ else ""))
    else:
        out.summary.append(f"{SUMS_FILE}: {n} files present and intact")


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(1 << 20):
            h.update(block)
    return h.hexdigest()


def content_fingerprint(drive_yaml: Path, spec) -> tuple[str, int, int]:
    """(sha256, files, bytes) over the drive file and what it references as ingest reads it (module docstring)."""
    from stages.ingest.scan_pass import list_scan_files

    files = {drive_yaml.name: drive_yaml}
    for p in list_scan_files(spec.path(spec.scans.folder), spec.scans.format):
        files[os.path.relpath(p, spec.drive_dir)] = p
    named = [(spec.gnss, "file"), (spec.odometry, "file"), (spec.survey, "file")]
    for section, key in named:
        if section is not None:
            files[getattr(section, key)] = spec.path(getattr(section, key))
    if spec.scan_times.source in ("stamps_csv", "pcd_field"):
        files[os.path.relpath(spec.stamps_file, spec.drive_dir)] = spec.stamps_file
    h, n_bytes = hashlib.sha256(), 0
    for rel in sorted(files):
        path = files[rel]
        if not path.is_file():
            continue
        digest = _sha256(path)
        n_bytes += path.stat().st_size
        h.update(f"{rel}\0{digest}\n".encode())
    return h.hexdigest(), len(files), n_bytes


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
