"""At publish: carry corner ids over from the map's LATEST version and write the new version's changelog.

Called from inside ``publish_version``'s writer, i.e. under the map's publish lock, so the LATEST read here
is the parent the new version will record.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Callable

import pyarrow as pa

from mapformat.changelog import (
    build_changelog,
    carry_ids,
    describe_origin,
    marking_cell_changes,
    marking_changes,
    same_frame,
)
from mapformat.corner_ids import IdGates
from pipeline.versioned import read_latest
from stages.common.geodesy import EnuOrigin

log = logging.getLogger(__name__)


def carry_history(map_dir: Path, corners: pa.Table, origin: EnuOrigin, size_m: float, staging: Path,
                  write_files: Callable[[pa.Table], dict[str, Any]], *, gates: IdGates,
                  move_threshold_m: float, new_paths: list | None = None, significance: float = 0.001,
                  min_obs: int = 8, plan: Callable[[Any, pa.Table], Any] | None = None
                  ) -> tuple[pa.Table, dict[str, Any]]:
    """(corners with stable ids, {"files": write_files' fields, "changelog": the changelog document, "plan": the
    tile plan or None}). A corner within ``gates`` of a parent corner keeps its id; one that kept its id but moved
    more than ``move_threshold_m`` is listed as moved. ``plan(parent reader, corners with ids)`` -> a
    ``stages.tiles.keep.TilePlan``: the tiles that keep the parent's files (their corners are the parent's rows);
    ``write_files(corners, kept)``."""
    from mapformat.loader import open_map

    parent = read_latest(map_dir) if map_dir.is_dir() else None
    prev = open_map(map_dir, parent) if parent is not None else None
    frame_unchanged = None if prev is None else same_frame(prev.origin, prev.tile_size_m, origin, size_m)
    if frame_unchanged is False:
        log.warning("tiles: the new version's frame (origin %s, tiles %s m) differs from %s's (origin %s, tiles "
                    "%s m); corners get new ids", describe_origin(origin), size_m, f"v{parent:04d}",
                    describe_origin(prev.origin), prev.tile_size_m)
    prev_corners = prev.all_corners() if prev is not None else None
    prev_next = prev.manifest.get("next_corner_id") if prev is not None else None
    if prev is not None and prev_next is None:  # a parent from before the counter: never reuse its ids
        prev_next = int(prev_corners["corner_id"].to_numpy().max()) + 1 if prev_corners.num_rows else 1
    ided, match, next_id = carry_ids(prev_corners if frame_unchanged else None, prev_next, corners, gates)
    tiles = plan(prev, ided) if plan is not None and prev is not None and frame_unchanged else None
    if tiles is not None and tiles.kept:
        from stages.tiles.keep import published_corners

        ided = published_corners(ided, prev_corners, tiles.kept, size_m)
    files = write_files(ided, tiles.kept if tiles is not None else {})
    markings = marking_changes(files["tiles"], staging, prev if frame_unchanged else None)
    cells = marking_cell_changes(files["tiles"], staging, prev if frame_unchanged else None, significance)
    doc = build_changelog(parent_version=parent, parent_manifest=prev.manifest if prev is not None else None,
                          prev_corners=prev_corners if frame_unchanged else None, corners=ided, match=match,
                          gates=gates, move_threshold_m=move_threshold_m, origin=origin,
                          tile_size_m=size_m, frame_unchanged=frame_unchanged, source_drives=files["source_drives"],
                          marking_px_changed=markings, next_corner_id=next_id, prev_paths=_paths(prev),
                          new_paths=new_paths, marking_cells=cells, significance=significance,
                          min_obs=min_obs)
    if prev_corners is not None and not frame_unchanged:  # every old corner is gone from this frame's view
        doc["corners"]["n_before"] = prev_corners.num_rows
    return ided, {"files": files, "changelog": doc, "plan": tiles}


def _paths(reader) -> list | None:
    """The (N,2) ENU paths of a version's drives (its trajectories, verified), None without a version or when one
    cannot be read (the changelog then calls every unmatched corner added / removed)."""
    if reader is None:
        return None
    from mapformat.trajectories import read_version_trajectory
    from pipeline.errors import CornermapError

    try:
        return [read_version_trajectory(reader, d["drive"])[1][:, :2] for d in reader.manifest["source_drives"]]
    except (CornermapError, KeyError, OSError, ValueError) as exc:
        log.warning("tiles: the parent's trajectories could not be read (%s); unmatched corners are listed as "
                    "added / removed without a visibility check", exc)
        return None
