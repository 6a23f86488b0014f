"""At publish: the tiles that keep their parent's files (``stages/tiles/tilelocal.py``'s rules on this version's
inputs and its parent version), and the published corner table that goes with them.

I/O edge of the tiles stage: reads the parent's trajectories, cells and raster files, hashes the raster files this
version would publish.
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from mapformat import layout
from mapformat.localizability import LOCALIZABILITY_FILE
from mapformat.vectors import MARKINGS_FILE
from pipeline.fingerprint import file_sha256
from stages.tiles.tilelocal import (
    CornerSet,
    Tolerances,
    changed_poses,
    corner_changed_tiles,
    tiles_of,
)

log = logging.getLogger(__name__)

Key = tuple[int, int]
_DERIVED = {layout.CORNERS_FILE, MARKINGS_FILE, LOCALIZABILITY_FILE}  # written by this stage, not copied rasters


@dataclass(frozen=True)
class KeptTile:
    """A tile published with its parent's files: the parent's manifest entry and its tile folder."""

    entry: dict[str, Any]
    src_dir: Path


@dataclass(frozen=True)
class TilePlan:
    kept: dict[Key, KeptTile]
    record: dict[str, Any]  # the manifest's ``tile_local`` entry


def corner_set(table: pa.Table) -> CornerSet:
    col = lambda c: table[c].to_numpy()  # noqa: E731
    n = table.num_rows
    return CornerSet(
        col("corner_id").astype(np.int64) if n else np.zeros(0, np.int64),
        np.column_stack([col("east_m"), col("north_m")]) if n else np.zeros((0, 2)),
        np.column_stack([col("cov_ee_m2"), col("cov_en_m2"), col("cov_nn_m2")]) if n else np.zeros((0, 3)),
        col("n_obs") if n else np.zeros(0, np.int64),
        table["drives"].to_pylist() if n else [],
    )


def plan_tiles(
    prev,
    corners: pa.Table,
    trajectories: list,
    rasters: list,
    cells: dict[Key, pa.Table] | None,
    size_m: float,
    tol: Tolerances,
    same_derivation: bool,
) -> TilePlan:
    """Which tiles of the new version keep the parent's (``prev``, a ``MapReader``) files. ``corners``: the new
    derivation with the parent's ids carried; ``cells``: the new localizability layer by tile; ``same_derivation``:
    the parent was published by this stage's code and params (else nothing is kept)."""
    record: dict[str, Any] = {
        "tolerances": {
            "corner_tol_m": tol.corner_tol_m,
            "cov_tol_rel": tol.cov_tol_rel,
            "pose_tol_m": tol.pose_tol_m,
            "pose_reach_m": tol.pose_reach_m,
        },
        "parent_version": int(prev.manifest.get("version", 0) or 0),
    }
    prev_tiles = {(int(t["i"]), int(t["j"])): t for t in prev.manifest.get("tiles", [])}
    if not same_derivation:
        return TilePlan({}, {**record, "n_kept": 0, "reason": "the parent was published with other code or params"})
    touched_corners, shift = corner_changed_tiles(corner_set(prev.all_corners()), corner_set(corners), size_m, tol)
    moved_pts, within = changed_poses(_parent_poses(prev, trajectories), _new_poses(trajectories), tol)
    touched_paths = tiles_of(moved_pts, size_m)
    by_key = {(r.i, r.j): r for r in rasters}
    candidates = set(prev_tiles) - touched_corners - touched_paths
    touched_rasters: set[Key] = set()
    for key in sorted(candidates):
        if _raster_changed(prev_tiles[key], by_key.get(key)):
            touched_rasters.add(key)
    # vector markings read the neighbours' masks within their margin: a changed raster touches its 8 neighbours
    touched_rasters |= {(i + di, j + dj) for i, j in touched_rasters for di in (-1, 0, 1) for dj in (-1, 0, 1)}
    kept: dict[Key, KeptTile] = {}
    cell_diff = 0.0
    for key in sorted(candidates - touched_rasters):
        entry = prev_tiles[key]
        has_cells = cells is not None and key in cells
        if has_cells != (LOCALIZABILITY_FILE in (entry.get("files") or {})):
            continue  # the layer appears or disappears in this tile
        if has_cells:
            cell_diff = max(cell_diff, _cell_sigma_diff(prev.tile_localizability(*key), cells[key]))
        kept[key] = KeptTile(entry, Path(prev.path) / str(entry["dir"]))
    shifts = shift[np.isfinite(shift)]
    in_kept = _in_tiles(corners, kept, size_m) & np.isfinite(shift)
    record.update(
        {
            "n_kept": len(kept),
            "n_rederived": len(set(prev_tiles) - set(kept)),
            "touched": {"corners": len(touched_corners), "paths": len(touched_paths), "rasters": len(touched_rasters)},
            "kept_corner_shift_max_m": round(float(shift[in_kept].max()), 6) if in_kept.any() else None,
            "within_tol_corner_shift_max_m": round(float(shifts.max()), 6) if len(shifts) else None,
            "kept_pose_move_max_m": round(max(within.values()), 6) if within else None,
            "kept_cells_sigma_diff_max_m": round(cell_diff, 6) if kept else None,
        }
    )
    return TilePlan(kept, record)


def published_corners(corners: pa.Table, prev_corners: pa.Table, kept: dict[Key, KeptTile], size_m: float) -> pa.Table:
    """``corners`` (the new derivation, ids carried) with the rows of the kept tiles replaced by the parent's rows
    of the same id, row order unchanged (a kept tile holds exactly the parent's ids)."""
    corners = corners.select(list(layout.CORNER_COLUMNS))
    sel = _in_tiles(corners, kept, size_m)
    if not sel.any():
        return corners
    prev = prev_corners.select(corners.column_names).cast(corners.schema)
    row_of = {int(c): r for r, c in enumerate(prev["corner_id"].to_numpy().tolist())}
    ids = corners["corner_id"].to_numpy()
    take = np.arange(corners.num_rows, dtype=np.int64)
    take[sel] = corners.num_rows + np.array([row_of[int(c)] for c in ids[sel]], np.int64)
    return pa.concat_tables([corners, prev]).take(pa.array(take))


def _in_tiles(corners: pa.Table, kept: dict[Key, KeptTile], size_m: float) -> np.ndarray:
    from stages.common.tiling import tile_key_of

    if not kept or corners.num_rows == 0:
        return np.zeros(corners.num_rows, bool)
    i, j = tile_key_of(corners["east_m"].to_numpy(), corners["north_m"].to_numpy(), size_m)
    return np.array([(a, b) in kept for a, b in zip(i.tolist(), j.tolist())], bool)


def _parent_poses(prev, trajectories: list) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The parent's poses of each drive, read from its published trajectories; a drive whose trajectory the new
    version states identically (its fingerprint) is given the new poses (nothing to read)."""
    from mapformat.trajectories import read_version_trajectory

    new = {t.drive: t for t in trajectories}
    out = {}
    for d in prev.manifest.get("source_drives", []):
        name = d.get("drive")
        t = new.get(name)
        if t is not None and t.fingerprint and t.fingerprint == d.get("fingerprint"):
            out[name] = (t.stamp_ns, t.pose_xyz_qxyzw)
        else:
            out[name] = read_version_trajectory(prev, name)
    return out


def _new_poses(trajectories: list) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    return {t.drive: (np.asarray(t.stamp_ns, np.int64), np.asarray(t.pose_xyz_qxyzw, float)) for t in trajectories}


def _raster_changed(entry: dict[str, Any], raster) -> bool:
    """Would the tile's raster files get other bytes (rule 3)?"""
    published = {n: s for n, s in (entry.get("files") or {}).items() if n not in _DERIVED}
    if raster is None or not published:
        return (raster is None) != (not published)
    if set(raster.files) != set(published):
        return True
    mask = (entry.get("marking") or {}).get("mask_file")
    for name, src in raster.files.items():
        sha = _transcoded_sha256(src) if name == mask else file_sha256(src)
        if sha != published[name]:
            return True
    return False


def _transcoded_sha256(src: Path) -> str:
    import tempfile

    from stages.tiles.writer import transcode_mask_png

    with tempfile.TemporaryDirectory(prefix="cornermap-mask-") as tmp:
        dst = Path(tmp) / "mask.png"
        transcode_mask_png(src, dst)
        return hashlib.sha256(dst.read_bytes()).hexdigest()


def _cell_sigma_diff(prev_cells: pa.Table | None, new_cells: pa.Table) -> float:
    """Largest |sigma_2d_m| difference between the kept (parent's) and the re-derived cells of one tile."""
    if prev_cells is None or prev_cells.num_rows == 0 or new_cells.num_rows == 0:
        return 0.0

    def index(t: pa.Table) -> dict:
        return {
            (a, b, m): s
            for a, b, m, s in zip(
                t["cell_i"].to_pylist(), t["cell_j"].to_pylist(), t["method"].to_pylist(), t["sigma_2d_m"].to_pylist()
            )
        }

    a, b = index(prev_cells), index(new_cells)
    common = set(a) & set(b)
    return max((abs(a[k] - b[k]) for k in common), default=0.0)
