"""``cornermap drive init``: which sensor recorded the scans, and why.

Evidence, strongest first:
1. a calibration file in the drive's folder (Ouster metadata JSON, Velodyne db.xml, Hesai angle-correction CSV,
   ``sensor_calibration``): its table and model, and the draft names it as ``calibration_file``;
2. the beam count: the ring field's ids (0..max: the upper beams of a scan in a street may see only sky, so the
   distinct ids can be fewer than the beams), else the rows of an organised PCD (HEIGHT > 1, the way Ouster's
   driver writes them), else the laser lines of a laser-by-laser export;
3. the point count per scan: a sensor cannot give more than ``MAX_POINTS_PER_BEAM`` points per beam and sweep
   (a 0.08 deg azimuth step at 5 Hz), which rules out too few beams;
4. the elevations: each beam's median elevation (by ring, organised row or laser line; points beyond ``FAR_M``,
   where the beam origins' offsets from the sensor origin no longer matter) against each table with as many beams
   (RMS, degrees; a unit's calibration is a few 0.1 degree off its model's); without beams,
   the share of far points within ``HIT_DEG`` of a table beam less the share a table that dense would explain by
   chance (the elevation span its windows cover), the model that explains the histogram best.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stages.ingest.sensors import SENSORS, elevation_deg

MAX_POINTS_PER_BEAM = 4500
FAR_M = 5.0
HIT_DEG = 0.08
MAX_CALIBRATION_CANDIDATE_BYTES = 4 << 20


@dataclass
class ScanEvidence:
    """What the sampled scans say about their sensor."""

    points_per_scan: list[int] = field(default_factory=list)  # records in the file (zeros and no-returns included)
    ring_ids: int | None = None  # distinct ring ids of the ring field
    ring_max: int | None = None  # the largest ring id
    organised_rows: int | None = None  # PCD HEIGHT when > 1
    lines: int | None = None  # laser lines in point order (16/32/64/128 only)
    far_elev_deg: list[np.ndarray] = field(default_factory=list)
    ring_medians_deg: np.ndarray | None = None  # per beam, ascending (far points); NaN: a beam without points

    def beams(self) -> tuple[int | None, str]:
        if self.ring_ids:
            n = self.ring_max + 1
            if n in (16, 32, 40, 64, 128) and self.ring_ids <= n:
                of = f" of 0..{self.ring_max}" if self.ring_ids < n else ""
                return n, f"{self.ring_ids} distinct ring ids{of}"
            return self.ring_ids, f"{self.ring_ids} distinct ring ids"
        if self.organised_rows:
            return self.organised_rows, f"an organised cloud of {self.organised_rows} rows"
        if self.lines:
            return self.lines, f"{self.lines} laser lines in point order"
        return None, "beam count unknown (no ring field, not organised)"


def collect_evidence(paths: list[Path], fmt: str) -> ScanEvidence:
    """Evidence from a few sampled scan files (unreadable ones are skipped; drive check reports them). The beams'
    median elevations come from the ring field, else the rows of an organised PCD, else the laser lines of a
    laser-by-laser export."""
    from stages.ingest.scan_formats import points_from_pcd, read_scan
    from stages.ingest.sensors import rings_from_point_order

    ev = ScanEvidence()
    beams_seen: list[np.ndarray] = []
    for path in paths:
        try:
            if fmt == "pcd":
                from stages.ingest.pcd import read_pcd

                cloud = read_pcd(path)
                pts = points_from_pcd(cloud, str(path))
                width, height = cloud.header.width, cloud.header.height
            else:
                pts, width, height = read_scan(path, fmt), 0, 1
        except Exception:  # noqa: BLE001 - a draft notes unreadable samples, check reports them
            continue
        ev.points_per_scan.append(len(pts))
        ok = np.isfinite(pts.x_m) & (np.abs(pts.x_m) + np.abs(pts.y_m) + np.abs(pts.z_m) > 0)
        rng = np.sqrt(pts.x_m.astype(float) ** 2 + pts.y_m.astype(float) ** 2 + pts.z_m.astype(float) ** 2)
        far = ok & (rng > FAR_M)
        elev = elevation_deg(pts.x_m, pts.y_m, pts.z_m)
        ev.far_elev_deg.append(elev[far])
        if pts.ring is not None:
            beam = pts.ring.astype(np.int64)
            ev.ring_ids = max(ev.ring_ids or 0, int(np.unique(pts.ring[ok]).size))
            ev.ring_max = max(ev.ring_max or 0, int(pts.ring[ok].max()) if ok.any() else 0)
        elif height > 1 and width * height == len(pts):
            ev.organised_rows = height
            beam = np.arange(len(pts)) // width
        else:
            beam = np.full(len(pts), -1, np.int64)
            lines = rings_from_point_order(pts.x_m[ok], pts.y_m[ok], pts.z_m[ok])
            n = int(lines.max()) + 1 if len(lines) else 0
            if n in (16, 32, 64, 128):
                ev.lines = n
                beam[ok] = lines
        use = far & (beam >= 0)
        beams_seen.append(np.column_stack([beam[use].astype(float), elev[use]]))
    n, _ = ev.beams()
    if beams_seen and n:
        a = np.concatenate(beams_seen)
        ids = np.unique(a[:, 0]).astype(int)
        if len(ids) == n:  # every beam seen: their medians in ascending order (rows and lines are not ring ids)
            ev.ring_medians_deg = np.sort([np.median(a[a[:, 0] == r, 1]) for r in ids])
        elif ev.ring_ids and ids.max() < n:  # ring ids index the table (0 = lowest); a beam that saw nothing: NaN
            med = np.full(n, np.nan)
            for r in ids:
                med[r] = np.median(a[a[:, 0] == r, 1])
            ev.ring_medians_deg = med
    return ev


def find_calibration(folder: Path):
    """The first calibration file in ``folder`` (sorted, depth-first): (path, BeamCalibration), or None."""
    from pipeline.errors import CornermapError
    from stages.ingest.sensor_calibration import read_beam_calibration

    marks = {".json": b"beam_altitude_angles", ".xml": b"vertCorrection_", ".csv": b"levation"}
    for path in sorted(folder.rglob("*")):
        mark = marks.get(path.suffix.lower())
        try:
            if mark is None or not path.is_file() or path.stat().st_size > MAX_CALIBRATION_CANDIDATE_BYTES:
                continue
            if mark not in path.read_bytes()[: 1 << 16 if path.suffix.lower() == ".csv" else None]:
                continue
            return path, read_beam_calibration(path)
        except (CornermapError, OSError):
            continue
    return None


def _explained(elev: np.ndarray, table: np.ndarray) -> float:
    """Share of ``elev`` within HIT_DEG of a beam, less the share of the table's span its windows cover."""
    idx = np.clip(np.searchsorted(table, elev), 1, len(table) - 1)
    d = np.minimum(np.abs(elev - table[idx - 1]), np.abs(elev - table[idx]))
    lo, hi = table[0] - HIT_DEG, table[-1] + HIT_DEG
    inside = (elev >= lo) & (elev <= hi)
    gaps = np.minimum(np.diff(table), 2 * HIT_DEG)
    covered = (gaps.sum() + 2 * HIT_DEG) / (hi - lo)
    return float((d <= HIT_DEG).mean() - covered * inside.mean())


def guess_sensor(ev: ScanEvidence) -> tuple[str, str]:
    """(the SENSORS model, why) from scan evidence (module docstring); 'generic' when nothing fits."""
    n, how = ev.beams()
    most = max(ev.points_per_scan, default=0)
    candidates = [m for m in SENSORS.values() if m.elevations_deg and (n is None or m.n_rings == n)
                  and most <= m.n_rings * MAX_POINTS_PER_BEAM]
    why = [how, f"{most} points per scan"]
    if not candidates:
        return "generic", "; ".join(why + ["no model has " + (f"{n} beams" if n else "enough beams")])
    scores = []
    if ev.ring_medians_deg is not None and n is not None and len(ev.ring_medians_deg) == n:
        med = ev.ring_medians_deg
        seen = np.isfinite(med)
        why.append(f"beam elevations {np.nanmin(med):.2f}..{np.nanmax(med):.2f} deg")
        for m in candidates:
            rms = float(np.sqrt(np.mean((np.asarray(m.elevations_deg)[seen] - med[seen]) ** 2)))
            scores.append((rms, m.name, f"{m.name} ({m.label}) table RMS {rms:.2f} deg"))
        scores.sort()
        ok = scores[0][0] < 1.0
    else:
        elev = np.concatenate(ev.far_elev_deg) if ev.far_elev_deg else np.zeros(0)
        if len(elev) < 100:
            return "generic", "; ".join(why + ["too few points beyond 5 m to read the beam elevations"])
        lo, hi = np.percentile(elev, [0.5, 99.5])
        why.append(f"elevations {lo:.1f}..{hi:.1f} deg")
        for m in candidates:
            s = _explained(elev, np.asarray(m.elevations_deg))
            scores.append((-s, m.name, f"{m.name} ({m.label}) explains {100 * s:.0f} % beyond chance"))
        scores.sort()
        ok = -scores[0][0] > 0.2
    best = scores[0]
    runner = f"; next {scores[1][2]}" if len(scores) > 1 else ""
    return (best[1] if ok else "generic"), "; ".join(why + [best[2] + runner])
