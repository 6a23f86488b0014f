"""The drive's scan list: ids from the numbers in the file names, stamps by the drive file's ``scan_times``."""
from __future__ import annotations

from stages.ingest.drive_file import DriveSpec
from stages.ingest.gnss_csv import NS_PER_WEEK, GnssFixes, read_scan_stamps, stamps_ns
from stages.ingest.kitti_raw import read_stamp_lines
from stages.ingest.report import IngestReport
from stages.ingest.scan_pass import MAX_SCAN_ID, ScanFile, list_scan_files, scan_numbers, stamp_from_filename_us


def list_scans(spec: DriveSpec, gnss: GnssFixes | None, max_scans: int | None, report: IngestReport
               ) -> list[ScanFile]:
    """Scan files with their ids and stamps. Ids are the numbers in the file names (KITTI ``0000000042.pcd``
    is scan 42; a missing file leaves a gap in the ids and no other scan's stamp moves); names without a
    unique number fall back to the sorted listing (reported). Stamps: rate (t0 + (id - first id) / rate),
    the file name (microseconds), or a stamps file joined on scan_id."""
    files = list_scan_files(spec.path(spec.scans.folder), spec.scans.format)
    source = spec.scan_times.source
    numbers = scan_numbers(files)
    if numbers is None and source in ("rate", "stamps_csv", "pcd_field") and files:
        report.add("scan_gap", spec.scans.folder, None, len(files),
                   "file names carry no unique scan number: ids follow the sorted listing, so a missing "
                   "file cannot be told from a gap")
    ids = numbers if numbers is not None and source != "filename_us" else list(range(len(files)))
    by_id = dict(zip(ids, files))
    if source == "rate":
        t0 = stamps_ns(spec.scan_times.t0_s) if spec.scan_times.t0_s is not None else \
            (int(gnss.stamp_ns[0]) if gnss is not None and len(gnss.stamp_ns) else 0)
        first = min(ids, default=0)
        scans = [ScanFile(i, by_id[i], t0 + round((i - first) * 1e9 / spec.scan_rate_hz)) for i in sorted(by_id)]
    elif source == "filename_us":
        scans = [ScanFile(i, p, stamp_from_filename_us(p)) for i, p in by_id.items()]
    elif source == "stamps_lines":  # line k is the stamp of scan k; a line without a file is a missing scan
        lines, issues = read_stamp_lines(spec.path(spec.scan_times.file))
        for record, reason in issues:
            report.add("timestamp", spec.scan_times.file, record, 1, reason)
        by_line = {k: t for k, t in enumerate(lines) if t is not None}
        scans = [ScanFile(i, by_id.get(i), by_line.get(i)) for i in sorted(set(by_id) | set(by_line))]
    else:
        week = None
        if spec.gnss and spec.gnss.time.week_column and gnss is not None and len(gnss.stamp_ns):
            week = int(gnss.stamp_ns[0] // NS_PER_WEEK)
        stamps, issues = read_scan_stamps(spec.stamps_file, week, MAX_SCAN_ID)
        for issue in issues:
            report.add("timestamp", spec.scan_times.file or "scan stamps", issue.record, 1, issue.reason)
        scans = [ScanFile(i, by_id.get(i), stamps.get(i)) for i in sorted(set(by_id) | set(stamps))]
    if max_scans is not None:
        scans = scans[:max_scans]
    missing = [(a.scan_id, b.scan_id) for a, b in zip(scans, scans[1:]) if b.scan_id - a.scan_id > 1]
    for before, after in missing:
        report.add("scan_gap", spec.scans.folder, before, after - before - 1,
                   f"no scan between {before} and {after}: a gap in the drive (kept as a gap)")
    known = [s for s in scans if s.stamp_ns is not None]
    stamp_file = spec.scan_times.file or "scan stamps"
    for prev, cur in zip(known, known[1:]):
        if cur.stamp_ns <= prev.stamp_ns:
            report.add("timestamp", stamp_file, cur.scan_id, 1,
                       f"scan stamp {'repeats' if cur.stamp_ns == prev.stamp_ns else 'goes back'} "
                       f"after scan {prev.scan_id}")
    return scans
