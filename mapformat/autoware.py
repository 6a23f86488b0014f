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

from mapformat.lanelets import DOUBLE_LINE_MIN_WIDTH_M, LaneRun
from mapformat.lineage import VersionLineage
from pipeline.errors import MapFormatError
from stages.common.geodesy import EnuOrigin, enu_to_geodetic
from stages.common.pointcloud_map import (
    VoxelSums,
    dynamic_voxels,
    free_space_evidence,
    grid_split,
    merge_counts,
    scan_to_map,
)
from stages.common.records import Extrinsics, decode_scans_raw

if TYPE_CHECKING:  # pragma: no cover
    from mapformat.loader import MapReader

log = logging.getLogger(__name__)
HeightOf = Callable[[np.ndarray], np.ndarray]  # (K, 2) map ENU -> (K,) road height, map up (m); NaN unknown
BATCH_POINTS = 500_000  # scan points per streamed batch (peak memory; see accumulate_map_cloud)
GROUND_CLEAR_M = 0.3  # points this far above the road under the vehicle take part in the free-space test
LANELET_TAGS = {"type": "lanelet", "subtype": "road", "location": "urban", "one_way": "yes"}
OSM_TAGS = {"lane_solid": {"type": "line_thin", "subtype": "solid"},
            "lane_dashed": {"type": "line_thin", "subtype": "dashed"},
            "stop_line": {"type": "stop_line"},
            "crosswalk": {"type": "crosswalk_polygon", "area": "yes"}}


def pointcloud_metadata_yaml(cells: list[tuple[int, int]], cell_m: float) -> str:
    """Autoware ``pointcloud_map_metadata.yaml``: resolution and each file's lower-left (x, y) in metres."""
    lines = [f"x_resolution: {cell_m:g}", f"y_resolution: {cell_m:g}"]
    lines += [f"{i}_{j}.pcd: [{i * cell_m:g}, {j * cell_m:g}]" for i, j in sorted(cells)]
    return "\n".join(lines) + "\n"


def lanelet2_osm(features: list, origin: EnuOrigin, height_of: HeightOf | None = None,
                 lanes: list[LaneRun] = ()) -> str:
    """OSM XML: the marking features as line strings / areas (arrows have no Lanelet2 line type here and are
    skipped) and the driven lanes as lanelets (``mapformat.lanelets``) with their boundary ways.

    Every node carries ``lat`` / ``lon`` and the tag ``ele`` (WGS84 ellipsoidal height, m) of its point on the road
    (map ENU (e, n, z) with z = ``height_of`` (e, n); 0 without it), plus Autoware's ``local_x`` / ``local_y``
    (map ENU east / north). Lanelet2's and Autoware's LocalCartesian projector about (lat0, lon0, 0) maps a node
    to (e, n, z + h0): the frame of the point cloud map this export writes beside it."""
    from xml.sax.saxutils import quoteattr

    enu, ways, relations = [], [], []
    ids = iter(range(1, 1 << 62))

    def way(node_ids: list[int], tags: dict[str, str]) -> int:
        wid = next(ids)
        refs = "".join(f'\n    <nd ref="{k}"/>' for k in node_ids)
        tag_xml = "".join(f"\n    <tag k={quoteattr(k)} v={quoteattr(v)}/>" for k, v in tags.items())
        ways.append(f'  <way id="{wid}" version="1">{refs}{tag_xml}\n  </way>')
        return wid

    def nodes(xyz: np.ndarray) -> list[int]:
        out = []
        for p in np.asarray(xyz, float):
            out.append(next(ids))
            enu.append((out[-1], p))
        return out

    def heights(xy: np.ndarray) -> np.ndarray:
        z = height_of(xy) if height_of is not None else np.full(len(xy), np.nan)
        return np.where(np.isfinite(z), z, 0.0)

    for f in features:
        tags = OSM_TAGS.get(f.type)
        if tags is None:
            continue
        if f.type == "lane_solid" and f.width_m >= DOUBLE_LINE_MIN_WIDTH_M:
            tags = {**tags, "subtype": "solid_solid"}  # a double (centre) line
        xy = np.asarray(f.xy_m, float)
        node_ids = nodes(np.column_stack([xy, heights(xy)]))
        way(node_ids + node_ids[:1] if f.is_polygon else node_ids,
            {**tags, "cornermap:type": f.type, "width": f"{f.width_m:.2f}"})
    for run in lanes:
        left_ids = dict(zip(run.left_keep.tolist(), nodes(run.left[run.left_keep])))
        right_ids = dict(zip(run.right_keep.tolist(), nodes(run.right[run.right_keep])))
        for k, (left_type, right_type) in enumerate(run.subtypes):
            li, ri = run.lanelet_bounds(k)
            lw = way([left_ids[i] for i in li.tolist()], _boundary_tags(left_type))
            rw = way([right_ids[i] for i in ri.tolist()], _boundary_tags(right_type))
            rid = next(ids)
            tag_xml = "".join(f'\n    <tag k="{k_}" v="{v}"/>' for k_, v in LANELET_TAGS.items())
            relations.append(f'  <relation id="{rid}" version="1">\n    <member type="way" role="left" ref="{lw}"/>'
                             f'\n    <member type="way" role="right" ref="{rw}"/>{tag_xml}'
                             f'\n    <tag k="cornermap:drive" v={quoteattr(run.drive)}/>\n  </relation>')
    node_xml = []
    if enu:
        xyz = np.array([p for _, p in enu])
        llh = enu_to_geodetic(xyz, origin)
        for (nid, (e, n, _)), (lat, lon, h) in zip(enu, llh):
            node_xml.append(f'  <node id="{nid}" version="1" lat="{lat:.10f}" lon="{lon:.10f}">\n'
                            f'    <tag k="local_x" v="{e:.4f}"/>\n    <tag k="local_y" v="{n:.4f}"/>\n'
                            f'    <tag k="ele" v="{h:.4f}"/>\n  </node>')
    return ('<?xml version="1.0" encoding="UTF-8"?>\n<osm version="0.6" generator="cornermap">\n'
            + "\n".join(node_xml + ways + relations) + "\n</osm>\n")


def _boundary_tags(subtype: str) -> dict[str, str]:
    return {"type": "virtual"} if subtype == "virtual" else {"type": "line_thin", "subtype": subtype}


def ground_height_sampler(reader: "MapReader", paths: dict[str, np.ndarray], layer: str = "elevation_mean",
                          window_m: float = 0.25) -> HeightOf:
    """(K, 2) map ENU -> (K,) the road surface height (map up, m): the median of the version's ``layer`` raster
    within ``window_m`` of each point (the markings stage's mean height of the road points per cell), else the
    height of the nearest trajectory pose (the vehicle frame's origin is on the road, docs/drive-file.md), else
    NaN."""
    from scipy.spatial import cKDTree

    from stages.common.tiling import tile_key_of

    cache: dict[tuple[int, int], tuple[np.ndarray, dict] | None] = {}
    s = reader.tile_size_m
    pose_xyz = np.vstack([p for p in paths.values() if len(p)]) if any(len(p) for p in paths.values()) else None
    tree = cKDTree(pose_xyz[:, :2]) if pose_xyz is not None else None

    def raster(key: tuple[int, int]):
        if key not in cache:
            meta = reader.tile_entry(*key).get("marking") if key in keys else None
            try:
                cache[key] = (reader.tile_layer(*key, layer), meta) if meta else None
            except MapFormatError:
                cache[key] = None
        return cache[key]

    keys = set(reader.tile_keys())

    def height_of(xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, float).reshape(-1, 2)
        z = np.full(len(xy), np.nan)
        for k, (e, n) in enumerate(xy):
            got = raster(tuple(int(v) for v in tile_key_of(e, n, s)))
            if got is None:
                continue
            values, meta = got
            cell = float(meta["cell_m"])
            col = (e - float(meta["origin_east_m"])) / cell
            row = values.shape[0] - (n - float(meta["origin_north_m"])) / cell
            r = int(np.ceil(window_m / cell))
            c0, r0 = int(np.floor(col)), int(np.floor(row))
            win = values[max(r0 - r, 0):r0 + r + 1, max(c0 - r, 0):c0 + r + 1]
            if win.size and np.isfinite(win).any():
                z[k] = float(np.nanmedian(win))
        if tree is not None and np.isnan(z).any():
            miss = np.isnan(z)
            z[miss] = pose_xyz[tree.query(xy[miss])[1], 2]
        return z

    return height_of


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


def accumulate_map_cloud(lineage: VersionLineage, drives: list[str], *, voxel_m: float = 0.2,
                         free_voxel_m: float = 0.5, pass_s: float = 5.0, max_range_m: float = 60.0,
                         batch_points: int = BATCH_POINTS) -> tuple[np.ndarray, np.ndarray, dict]:
    """Map-frame cloud of ``drives`` (deskewed, dynamic points dropped, downsampled): (xyz, intensity, stats).

    Streams the scans in batches of ``batch_points``: each batch adds its free-space evidence and its voxel
    sums (stages/common/pointcloud_map.py), so the peak memory is set by the batch size and the number of
    occupied voxels, not by the number of points."""
    from scipy.spatial import cKDTree

    from pipeline.progress import report

    sums, evidence = VoxelSums(voxel_m, free_voxel_m), _Evidence()
    n_in = 0
    cols = ["stamp_ns", "x_m", "y_m", "z_m", "intensity", "time_offset_s"]
    for k, drive in enumerate(drives):
        report("autoware", k, len(drives))  # drives streamed so far (the step counts a drive's scan points)
        poses = lineage.read("poses_optimized", drive).sort_by("stamp_ns")
        info = lineage.read("drive_info", drive)
        T_vl = Extrinsics.from_table(info).of(drive)
        stamps = poses["stamp_ns"].to_numpy()
        pxyz = np.column_stack([poses[c].to_numpy() for c in ("x_m", "y_m", "z_m")])
        pq_ = np.column_stack([poses[c].to_numpy() for c in ("qx", "qy", "qz", "qw")])
        road = cKDTree(pxyz[:, :2])  # the road under the vehicle: its height at the nearest pose
        done, total = 0, lineage.rows("scans_raw", drive)
        for batch in lineage.batches("scans_raw", drive, cols, batch_points):
            report("autoware", done, total, step=f"point cloud of {drive}: scan points")
            done += batch.num_rows
            rows = decode_scans_raw(batch, by_scan=False)
            lidar = rows.xyz_lidar_m.astype(float)
            rng = np.linalg.norm(lidar, axis=1)
            t_ns = rows.stamp_ns + np.round(rows.time_offset_s.astype(float) * 1e9).astype(np.int64)
            ok = (rng > 1.0) & (rng < max_range_m) & (t_ns >= stamps[0]) & (t_ns <= stamps[-1])
            if not ok.any():
                continue
            pts, origins = scan_to_map(lidar[ok], t_ns[ok], T_vl, stamps, pxyz, pq_)
            gz = pxyz[road.query(pts[:, :2])[1], 2]
            pid = k * 1_000_000 + (t_ns[ok] - stamps[0]) // int(pass_s * 1e9)
            evidence.add(*free_space_evidence(pts, origins, pid, gz, voxel_m=free_voxel_m,
                                              ground_clear_m=GROUND_CLEAR_M, first_index=n_in))
            sums.add(pts, rows.intensity[ok].astype(float), pts[:, 2] > gz + GROUND_CLEAR_M)
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


def export_autoware(reader: "MapReader", out: Path, root: "Path | str", *, grid_m: float = 20.0, voxel_m: float = 0.2,
                    batch_points: int = BATCH_POINTS, write: Callable[[Path, bytes], None]) -> list[Path]:
    """Write the Autoware folder (module docstring) under ``out`` from the datasets ``reader``'s version records
    (``mapformat.lineage``: never the newest of a name); returns the files written."""
    from mapformat.export import autoware_projector_yaml, pcd_bytes
    from mapformat.lanelets import driven_lanes
    from mapformat.trajectories import read_version_trajectory
    from mapformat.vectors import read_map_features
    from pipeline.progress import finish, report

    out = Path(out)
    drives = map_drives(reader)
    label = f"map {reader.manifest.get('map_name')!r} v{reader.version:04d} ({reader.path})"
    lineage = VersionLineage(root, reader.manifest, label)  # a folder or an s3:// root: the datasets' store
    xyz, inten, stats = accumulate_map_cloud(lineage, drives, voxel_m=voxel_m, batch_points=batch_points)
    log.info("autoware point cloud: %s", stats)
    h0 = float(reader.origin.h_m)
    files = [out / "map_projector_info.yaml"]
    write(files[0], autoware_projector_yaml(reader.origin).encode("utf-8"))
    cells = grid_split(xyz, grid_m)
    for n, ((i, j), idx) in enumerate(sorted(cells.items())):
        report("autoware", n, len(cells), step="point cloud tiles")
        path = out / "pointcloud_map" / f"{i}_{j}.pcd"
        write(path, pcd_bytes(xyz[idx] + np.array([0.0, 0.0, h0]), inten[idx]))  # the Autoware frame: z + h0
        files.append(path)
    files.append(out / "pointcloud_map_metadata.yaml")
    write(files[-1], pointcloud_metadata_yaml(list(cells), grid_m).encode("utf-8"))
    report("autoware", step="Lanelet2 markings")
    feats = read_map_features(reader.path, [reader.tile_entry(*k) for k in reader.tile_keys()])
    paths = {d["drive"]: read_version_trajectory(reader, d["drive"])[1][:, :3]
             for d in reader.manifest.get("source_drives", [])}
    height_of = ground_height_sampler(reader, paths)
    lanes = driven_lanes({d: p for d, p in paths.items() if d in drives}, feats, height_of)
    files.append(out / "lanelet2_map.osm")
    write(files[-1], lanelet2_osm(feats, reader.origin, height_of, lanes).encode("utf-8"))
    files.append(out / "cornermap_export.json")
    n_lanelets = sum(len(r.subtypes) for r in lanes)
    frame = {"projector_type": "LocalCartesian", "origin": {**reader.origin.as_dict(), "h_m": 0.0},
             "T_autoware_map": [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, h0], [0.0, 0.0, 0.0, 1.0]],
             "note": "the folder's frame is ENU about the map origin's latitude and longitude at 0 m ellipsoidal "
                     "height (Autoware's map_projection_loader sets the origin altitude to 0): the map frame "
                     f"raised by the origin's height h0 = {h0:g} m"}
    write(files[-1], json.dumps({"map_name": reader.manifest.get("map_name"), "version": reader.version,
                                 "manifest_sha256": reader.manifest_sha256, "frame": frame, "pointcloud": stats,
                                 "grid_m": grid_m, "n_marking_features": len(feats), "n_lanelets": n_lanelets,
                                 "inputs": {d: c.fingerprint for d in ("poses_optimized", "drive_info", "scans_raw")
                                            for c in (lineage.find(d),)}},
                                indent=1).encode("utf-8"))
    finish("autoware")
    return files
