"""Writes one map version's files into a staging directory and returns its manifest fields.

I/O edge of the stage: takes plain arrays/tables (already validated) and a staging path from
``pipeline.versioned.publish_version``; the publisher adds checksums of every file, the version number and
the LATEST pointer.
"""
from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from mapformat import layout
from mapformat.localizability import LOCALIZABILITY_FILE
from mapformat.vectors import MARKINGS_FILE, features_table, tile_features
from pipeline.errors import DatasetIOError
from pipeline.fingerprint import file_sha256
from pipeline.names import inside
from stages.common.tiling import tile_bounds
from stages.tiles.core import group_by_tile

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RasterTile:
    """One tile's marking raster: its georeference and the artifact files to copy (published name -> src)."""

    i: int
    j: int
    meta: dict[str, Any]  # origin_east_m, origin_north_m, cell_m, width_px, height_px, n_marking_px, ...
    files: dict[str, Path] = field(default_factory=dict)


@dataclass(frozen=True)
class DriveTrajectory:
    drive: str
    stamp_ns: np.ndarray  # (N,) int64
    pose_xyz_qxyzw: np.ndarray  # (N,7) T_map_vehicle as x y z qx qy qz qw
    fingerprint: str | None


def format_tum_lines(stamp_ns: np.ndarray, pose_xyz_qxyzw: np.ndarray) -> str:
    """TUM rows 't x y z qx qy qz qw' with the stamp printed exactly from integer nanoseconds."""
    stamp_ns = np.asarray(stamp_ns, np.int64)
    sec, frac = np.divmod(stamp_ns, 1_000_000_000)
    body = np.char.mod("%.6f", np.asarray(pose_xyz_qxyzw[:, :3], float))
    quat = np.char.mod("%.9f", np.asarray(pose_xyz_qxyzw[:, 3:7], float))
    stamps = np.char.add(np.char.add(sec.astype(str), "."), np.char.zfill(frac.astype(str), 9))
    cols = np.column_stack([stamps, body, quat])
    return "".join(" ".join(row) + "\n" for row in cols.tolist())


def _write_corners(path: Path, table: pa.Table) -> None:
    """Small footer: a tile holds tens of corners, so the Arrow schema blob and statistics would dominate the
    file (5.9 kB -> 2.2 kB for 10 corners). Units live in docs/map-format.md; the loader re-attaches them."""
    pq.write_table(table, path, compression="zstd", store_schema=False, write_statistics=False,
                   use_dictionary=False)


def transcode_mask_png(src: Path, dst: Path) -> None:
    """Copy a marking mask PNG re-encoded losslessly at zlib level 9 (same pixels, same bit depth).

    OpenCV's default PNG settings (used by the markings stage) decode a 1000 x 1000 mask in 4-8 ms on the
    2-core machine, level 9 in ~2.6 ms and ~4x smaller; the loader decodes this file on every tile load.
    """
    import cv2

    pixels = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
    if pixels is None:
        raise DatasetIOError(f"{src}: not a readable PNG; hint: rerun the markings stage for this tile")
    ok, buf = cv2.imencode(".png", pixels, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok or not np.array_equal(cv2.imdecode(buf, cv2.IMREAD_UNCHANGED), pixels):
        raise DatasetIOError(f"{src}: lossless PNG re-encoding failed ({pixels.dtype}, {pixels.shape})")
    dst.write_bytes(buf.tobytes())


def _vectorize(by_key: dict[tuple[int, int], RasterTile], tile_size_m: float,
               skip: Any = ()) -> dict[tuple[int, int], pa.Table]:
    """Vector markings of every raster tile but those in ``skip`` (mapformat/vectors.py), masks decoded once
    each."""
    import cv2

    masks: dict[tuple[int, int], Any] = {}

    def mask_of(key: tuple[int, int]):
        if key not in masks:
            raster = by_key.get(key)
            name = next((f for f in layout.MARKING_MASK_FILES if raster and f in raster.files), None)
            img = cv2.imread(str(raster.files[name]), cv2.IMREAD_GRAYSCALE) if name else None
            masks[key] = None if img is None else (img, float(raster.meta["origin_east_m"]),
                                                   float(raster.meta["origin_north_m"]), float(raster.meta["cell_m"]))
        return masks[key]

    return {key: features_table(tile_features(key, tile_size_m, mask_of)) for key in sorted(by_key) if key not in skip}


def _bring_kept(src_dir: Path, tile_dir: Path, files: dict[str, str]) -> bool:
    """The parent's tile files into ``tile_dir``: a hard link where the file system allows one (the bytes are not
    copied), else a copy; each checked against the parent's sha256. False (``tile_dir`` emptied) when one differs."""
    import os

    for name, sha in sorted(files.items()):
        src, dst = inside(src_dir, name), inside(tile_dir, name)
        try:
            os.link(src, dst)
        except OSError:
            shutil.copyfile(src, dst)
        if file_sha256(dst) != sha:
            for p in tile_dir.iterdir():
                p.unlink()
            return False
    return True


def write_map_files(staging: Path, corners: pa.Table, tile_size_m: float, rasters: list[RasterTile],
                    trajectories: list[DriveTrajectory],
                    localizability: dict[tuple[int, int], pa.Table] | None = None,
                    kept: dict[tuple[int, int], Any] | None = None) -> dict[str, Any]:
    """Write tiles/ and trajectories/ under ``staging``; return the ``tiles`` and ``source_drives`` fields.
    ``localizability``: each tile's cells of the localizability layer (a tile holding only cells gets an empty
    corners.parquet, as a raster-only tile does). ``kept``: tiles published with their parent's files and manifest
    entry (``stages.tiles.keep.KeptTile``); one whose parent file does not match its sha256 is written anew."""
    corners = corners.select(list(layout.CORNER_COLUMNS)).sort_by("corner_id")
    east = corners["east_m"].to_numpy()
    north = corners["north_m"].to_numpy()
    groups = group_by_tile(east, north, tile_size_m)
    by_key = {(r.i, r.j): r for r in rasters}
    kept = kept or {}
    vectors = _vectorize(by_key, tile_size_m, skip=kept)
    empty = corners.slice(0, 0)
    tiles = []
    localizability = localizability or {}
    for key in sorted(set(groups) | set(by_key) | set(localizability) | set(kept)):
        i, j = key
        rel_dir = layout.tile_dir_name(i, j)
        tile_dir = staging / rel_dir
        tile_dir.mkdir(parents=True)
        if key in kept:
            if _bring_kept(kept[key].src_dir, tile_dir, dict(kept[key].entry["files"])):
                tiles.append(dict(kept[key].entry))
                continue
            log.warning("tiles: tile (%d,%d) of the parent version does not match its sha256; written anew "
                        "(hint: run `cornermap tiles verify` on the parent)", i, j)
            if key in by_key and key not in vectors:
                vectors.update(_vectorize(by_key, tile_size_m, skip=set(by_key) - {key}))
        idx = groups.get(key)
        part = corners.take(pa.array(idx)) if idx is not None else empty
        _write_corners(tile_dir / layout.CORNERS_FILE, part)
        entry: dict[str, Any] = {"i": i, "j": j, "bounds_m": list(tile_bounds(i, j, tile_size_m)),
                                 "dir": rel_dir, "n_corners": part.num_rows, "n_marking_px": 0, "marking": None}
        raster = by_key.get(key)
        if raster is not None:
            mask = next((f for f in layout.MARKING_MASK_FILES if f in raster.files), None)
            for name, src in sorted(raster.files.items()):
                if name == mask:
                    transcode_mask_png(src, tile_dir / name)
                else:
                    shutil.copyfile(src, tile_dir / name)
            pq.write_table(vectors[key], tile_dir / MARKINGS_FILE, compression="zstd")
            entry["n_marking_features"] = vectors[key].num_rows
            entry["n_marking_px"] = int(raster.meta.get("n_marking_px", 0))
            entry["marking"] = {**raster.meta, "mask_file": mask, "layers": sorted(raster.files)}
        if key in localizability:
            pq.write_table(localizability[key], tile_dir / LOCALIZABILITY_FILE, compression="zstd")
            entry["n_localizability_cells"] = localizability[key].num_rows
        entry["files"] = {p.name: file_sha256(p) for p in sorted(tile_dir.iterdir())}
        tiles.append(entry)
    drives = []
    for traj in sorted(trajectories, key=lambda t: t.drive):
        rel = layout.trajectory_file_name(traj.drive)
        path = inside(staging, rel)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("# t x y z qx qy qz qw  (T_map_vehicle, map ENU frame, t in s)\n"
                                   + format_tum_lines(traj.stamp_ns, traj.pose_xyz_qxyzw), encoding="utf-8")
        xy = traj.pose_xyz_qxyzw[:, :2]
        length = float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum()) if len(xy) > 1 else 0.0
        drives.append({"drive": traj.drive, "fingerprint": traj.fingerprint, "n_poses": int(len(xy)),
                       "path_length_m": round(length, 3), "trajectory": rel})
    return {"tiles": tiles, "source_drives": drives}
