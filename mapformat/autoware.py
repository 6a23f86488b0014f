"""``tiles export --format autoware``: an Autoware map folder built from a published map version.

    OUT/
      map_projector_info.yaml          LocalCartesian about the map's ENU origin
      pointcloud_map/{ix}_{iy}.pcd     binary PCD (float32 x y z intensity), map ENU metres, one per grid cell
      pointcloud_map_metadata.yaml     x_resolution, y_resolution, "{ix}_{iy}.pcd: [x_min, y_min]" per file
      lanelet2_map.osm                 road markings as Lanelet2 line strings / areas (local_x, local_y, ele tags)

The point cloud is accumulated from the map drives' scans (``scans_raw`` under the output root) on their
optimized poses (the version's ``poses`` input), deskewed, filtered by the free-space test of
stages/common/pointcloud_map.py and voxel-downsampled (centroid per voxel), streamed in batches of scan points. Layout
follows Autoware's map loader
documentation (divided point cloud map + metadata; map_projection_loader's LocalCartesian; Autoware's Lanelet2
conventions: line_thin solid/solid_solid/dashed, stop_line, crosswalk_polygon).
"""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from pipeline.errors import DatasetIOError
from stages.common.geodesy import EnuOrigin, enu_to_geodetic
from stages.common.pointcloud_map import (
    VoxelSums,
    dynamic_voxels,
    free_space_evidence,
    grid_split,
    merge_counts,
    scan_to_map,
)
from stages.common.records import Extrinsics

if TYPE_CHECKING:  # pragma: no cover
    from mapformat.loader import MapReader

log = logging.getLogger(__name__)
BATCH_POINTS = 500_000  # scan points per streamed batch (peak memory; see accumulate_map_cloud)
GROUND_CLEAR_M = 0.3  # points this far above the road under the vehicle take part in the free-space test
DOUBLE_LINE_MIN_WIDTH_M = 0.55  # two lines merged in the raster (0.5 m of paint drawn ~0.7 m; a single
# 0.15 m line is drawn 0.3-0.4 m wide)
OSM_TAGS = {"lane_solid": {"type": "line_thin", "subtype": "solid"},
            "lane_dashed": {"type": "line_thin", "subtype": "dashed"},
            "stop_line": {"type": "stop_line"},
            "crosswalk": {"type": "crosswalk_polygon", "area": "yes"}}


def pointcloud_metadata_yaml(cells: list[tuple[int, int]], cell_m: float) -> str:
    """Autoware ``pointcloud_map_metadata.yaml``: resolution and each file's lower-left (x, y) in metres."""
    lines = [f"x_resolution: {cell_m:g}", f"y_resolution: {cell_m:g}"]
    lines += [f"{i}_{j}.pcd: [{i * cell_m:g}, {j * cell_m:g}]" for i, j in sorted(cells)]
    return "\n".join(lines) + "\n"


def lanelet2_osm(features: list, origin: EnuOrigin, height_m: float = 0.0) -> str:
    """OSM XML of the marking features (arrows have no Lanelet2 line type here and are skipped): one node per
    vertex (lat/lon from the ENU origin, plus Autoware's local_x / local_y / ele tags), one way per feature,
    closed for crosswalk areas."""
    from xml.sax.saxutils import quoteattr

    nodes, ways = [], []
    next_id = 1
    for f in features:
        tags = OSM_TAGS.get(f.type)
        if tags is None:
            continue
        if f.type == "lane_solid" and f.width_m >= DOUBLE_LINE_MIN_WIDTH_M:
            tags = {**tags, "subtype": "solid_solid"}  # a double (centre) line
        xy = np.asarray(f.xy_m, float)
        llh = enu_to_geodetic(np.column_stack([xy, np.full(len(xy), height_m)]), origin)
        ids = []
        for (e, n), (lat, lon, h) in zip(xy, llh):
            nodes.append(f'  <node id="{next_id}" version="1" lat="{lat:.10f}" lon="{lon:.10f}">\n'
                         f'    <tag k="local_x" v="{e:.4f}"/>\n    <tag k="local_y" v="{n:.4f}"/>\n'
                         f'    <tag k="ele" v="{height_m:.4f}"/>\n  </node>')
            ids.append(next_id)
            next_id += 1
        if f.is_polygon:
            ids.append(ids[0])
        refs = "".join(f'\n    <nd ref="{k}"/>' for k in ids)
        tag_xml = "".join(f"\n    <tag k={quoteattr(k)} v={quoteattr(v)}/>" for k, v in
                          {**tags, "cornermap:type": f.type, "width": f"{f.width_m:.2f}"}.items())
        ways.append(f'  <way id="{next_id}" version="1">{refs}{tag_xml}\n  </way>')
        next_id += 1
    return ('<?xml version="1.0" encoding="UTF-8"?>\n<osm version="0.6" generator="cornermap">\n'
            + "\n".join(nodes + ways) + "\n</osm>\n")


def _committed(root: Path, dataset: str, fingerprint: str | None = None) -> tuple[Path, dict]:
    """Committed directory + manifest of ``dataset`` (the given fingerprint, else the latest committed)."""
    from pipeline.store import dataset_dir, read_manifest

    if fingerprint:
        d = dataset_dir(root, dataset, fingerprint)
        m = read_manifest(d)
        if m is not None:
            return d, m
    found = [(read_manifest(p), p) for p in sorted((root / "datasets" / dataset).glob("*")) if p.is_dir()]
    found = [(m, p) for m, p in found if m is not None]
    if not found:
        raise DatasetIOError(f"{root}/datasets/{dataset}: no committed data; hint: the autoware export reads the "
                             "map's scans and poses from the output root (--root) that built the map")
    m, p = max(found, key=lambda mp: mp[0].get("committed_utc", ""))
    return p, m


def _read(root: Path, dataset: str, drive: str, fingerprint: str | None = None, columns=None):
    import pyarrow as pa
    import pyarrow.parquet as pq

    d, m = _committed(root, dataset, fingerprint)
    files = [d / f["path"] for f in m["files"] if f.get("partition", {}).get("drive") == drive]
    if not files:
        raise DatasetIOError(f"{d}: no {dataset} rows for drive {drive!r}")
    return pa.concat_tables([pq.read_table(f, columns=columns) for f in files])


def _scan_batches(root: Path, drive: str, batch_points: int, columns: list[str]):
    """``scans_raw`` rows of ``drive`` (the latest committed version) as record batches of ``batch_points``."""
    import pyarrow.parquet as pq

    from pipeline.progress import report

    d, m = _committed(root, "scans_raw")
    files = [d / f["path"] for f in m["files"] if f.get("partition", {}).get("drive") == drive]
    if not files:
        raise DatasetIOError(f"{d}: no scans_raw rows for drive {drive!r}")
    readers = [pq.ParquetFile(f) for f in files]
    done, total = 0, sum(r.metadata.num_rows for r in readers)
    for r in readers:
        for batch in r.iter_batches(batch_size=batch_points, columns=columns):
            report("autoware", done, total, step=f"point cloud of {drive}: scan points")
            yield batch
            done += batch.num_rows


class _Evidence:
    """Free-space evidence of the batches seen so far, merged whenever it grows past ``compact_rows``."""

    def __init__(self, compact_rows: int = 4_000_000):
        self.hits, self.free, self.free_n, self.compact_rows = [], [], [], compact_rows

    def add(self, hits: np.ndarray, free: np.ndarray, free_n: np.ndarray) -> None:
        self.hits.append(hits)
        self.free.append(free)
        self.free_n.append(free_n)
        if sum(len(x) for x in self.free) + sum(len(x) for x in self.hits) > self.compact_rows:
            self.compact()

    def compact(self) -> None:
        self.hits = [np.unique(np.vstack(self.hits), axis=0)] if self.hits else []
        if self.free:
            free, n = merge_counts(np.vstack(self.free), np.concatenate(self.free_n))
            self.free, self.free_n = [free], [n]


def accumulate_map_cloud(reader: "MapReader", root: Path, drives: list[str], *, voxel_m: float = 0.2,
                         free_voxel_m: float = 0.5, pass_s: float = 5.0, max_range_m: float = 60.0,
                         batch_points: int = BATCH_POINTS) -> tuple[np.ndarray, np.ndarray, dict]:
    """Map-frame cloud of ``drives`` (deskewed, dynamic points dropped, downsampled): (xyz, intensity, stats).

    Streams the scans in batches of ``batch_points``: each batch adds its free-space evidence and its voxel
    sums (stages/common/pointcloud_map.py), so the peak memory is set by the batch size and the number of
    occupied voxels, not by the number of points."""
    from scipy.spatial import cKDTree

    from pipeline.progress import report

    inputs = reader.manifest.get("inputs", {})
    sums, evidence = VoxelSums(voxel_m, free_voxel_m), _Evidence()
    n_in = 0
    cols = ["stamp_ns", "x_m", "y_m", "z_m", "intensity", "time_offset_s"]
    for k, drive in enumerate(drives):
        report("autoware", k, len(drives))  # drives streamed so far (the step counts a drive's scan points)
        poses = _read(root, "poses_optimized", drive, (inputs.get("poses") or {}).get("fingerprint")).sort_by(
            "stamp_ns"
        )
        info = _read(root, "drive_info", drive, (inputs.get("drive_info") or {}).get("fingerprint"))
        T_vl = Extrinsics.from_table(info).of(drive)
        stamps = poses["stamp_ns"].to_numpy()
        pxyz = np.column_stack([poses[c].to_numpy() for c in ("x_m", "y_m", "z_m")])
        pq_ = np.column_stack([poses[c].to_numpy() for c in ("qx", "qy", "qz", "qw")])
        road = cKDTree(pxyz[:, :2])  # the road under the vehicle: its height at the nearest pose
        for batch in _scan_batches(root, drive, batch_points, cols):
            lidar = np.column_stack([batch.column(c).to_numpy().astype(float) for c in ("x_m", "y_m", "z_m")])
            rng = np.linalg.norm(lidar, axis=1)
            t_ns = batch.column("stamp_ns").to_numpy() + np.round(
                batch.column("time_offset_s").to_numpy().astype(float) * 1e9).astype(np.int64)
            ok = (rng > 1.0) & (rng < max_range_m) & (t_ns >= stamps[0]) & (t_ns <= stamps[-1])
            if not ok.any():
                continue
            pts, origins = scan_to_map(lidar[ok], t_ns[ok], T_vl, stamps, pxyz, pq_)
            gz = pxyz[road.query(pts[:, :2])[1], 2]
            pid = k * 1_000_000 + (t_ns[ok] - stamps[0]) // int(pass_s * 1e9)
            evidence.add(*free_space_evidence(pts, origins, pid, gz, voxel_m=free_voxel_m,
                                              ground_clear_m=GROUND_CLEAR_M, first_index=n_in))
            sums.add(pts, batch.column("intensity").to_numpy()[ok].astype(float), pts[:, 2] > gz + GROUND_CLEAR_M)
            n_in += len(pts)
    report("autoware", len(drives), len(drives))
    report("autoware", step="dynamic points, voxel centroids")
    evidence.compact()
    dyn = dynamic_voxels(evidence.hits[0], evidence.free[0], evidence.free_n[0]) if n_in else np.zeros(0, np.int64)
    xyz, inten, n_dropped = sums.centroids(dyn)
    stats = {"points_in": int(n_in), "dynamic_dropped": n_dropped, "points_out": int(len(xyz)),
             "drives": drives, "voxel_m": voxel_m, "free_voxel_m": free_voxel_m, "pass_s": pass_s,
             "batch_points": batch_points}
    return xyz, inten, stats


def map_drives(reader: "MapReader") -> list[str]:
    """Drives whose observations built the corner map (its ``drives`` column), else every source drive."""
    corners = reader.all_corners()
    seen = sorted({d for s in corners["drives"].to_pylist() for d in (s or "").split(",") if d})
    return seen or sorted(d["drive"] for d in reader.manifest.get("source_drives", []))


def export_autoware(reader: "MapReader", out: Path, root: Path, *, grid_m: float = 20.0, voxel_m: float = 0.2,
                    batch_points: int = BATCH_POINTS, write: Callable[[Path, bytes], None]) -> list[Path]:
    """Write the Autoware folder (module docstring) under ``out``; returns the files written."""
    from mapformat.export import autoware_projector_yaml, pcd_bytes
    from mapformat.vectors import read_map_features
    from pipeline.progress import finish, report

    out = Path(out)
    drives = map_drives(reader)
    xyz, inten, stats = accumulate_map_cloud(reader, Path(root), drives, voxel_m=voxel_m, batch_points=batch_points)
    log.info("autoware point cloud: %s", stats)
    files = [out / "map_projector_info.yaml"]
    write(files[0], autoware_projector_yaml(reader.origin).encode("utf-8"))
    cells = grid_split(xyz, grid_m)
    for n, ((i, j), idx) in enumerate(sorted(cells.items())):
        report("autoware", n, len(cells), step="point cloud tiles")
        path = out / "pointcloud_map" / f"{i}_{j}.pcd"
        write(path, pcd_bytes(xyz[idx], inten[idx]))
        files.append(path)
    files.append(out / "pointcloud_map_metadata.yaml")
    write(files[-1], pointcloud_metadata_yaml(list(cells), grid_m).encode("utf-8"))
    report("autoware", step="Lanelet2 markings")
    feats = read_map_features(reader.path, [reader.tile_entry(*k) for k in reader.tile_keys()])
    files.append(out / "lanelet2_map.osm")
    write(files[-1], lanelet2_osm(feats, reader.origin).encode("utf-8"))
    files.append(out / "cornermap_export.json")
    write(files[-1], json.dumps({"map_name": reader.manifest.get("map_name"), "version": reader.version,
                                 "manifest_sha256": reader.manifest_sha256, "pointcloud": stats,
                                 "grid_m": grid_m, "n_marking_features": len(feats)}, indent=1).encode("utf-8"))
    finish("autoware")
    return files
