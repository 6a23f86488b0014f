"""A version's changelog (``changelog.json`` in the version folder, checksummed with the other files) and
the corner identity carried over from the previous version at publish.

Written by the tiles stage while it holds the map's publish lock, so "the previous version" is the LATEST the
new one will replace (``parent_version`` in both the manifest and the changelog). File format:
docs/map-format.md, "Corner identity and changelog".
"""
from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pyarrow as pa

from mapformat.change_tests import DOF, SIGNIFICANCE, chi2_threshold, corner_chi2
from mapformat.corner_ids import IdGates, IdMatch, assign_ids, match_corners
from stages.common.geodesy import EnuOrigin
from stages.common.tiling import tile_key_of

CHANGELOG_FILE = "changelog.json"
CHANGELOG_FORMAT = "cornermap-changelog"
CHANGELOG_FORMAT_VERSION = 2  # 2: kept corners tested by chi-square, markings per cell (1 still read)
MARKING_CELL_M = 10.0  # the markings' change regions
MARKING_TOLERANCE_PX = 2  # paint within this many raster cells in the other version is not a change
def same_frame(origin_a: EnuOrigin, size_a: float, origin_b: EnuOrigin, size_b: float) -> bool:
    """One tiling of one frame: the same origin (``EnuOrigin.same_frame``) and the same tile size."""
    return origin_a.same_frame(origin_b) and float(size_a) == float(size_b)


def describe_origin(o: EnuOrigin) -> str:
    return f"({o.lat_deg:.9f}, {o.lon_deg:.9f}, {o.h_m:.3f} m)"


def _en(table: pa.Table) -> np.ndarray:
    if table.num_rows == 0:
        return np.zeros((0, 2))
    return np.column_stack([table["east_m"].to_numpy(), table["north_m"].to_numpy()])


def covariances(table: pa.Table | None) -> np.ndarray:
    """(N,2,2) corner covariances through the loader's public reader of them (whatever columns hold them)."""
    from mapformat.loader import MapReader

    return MapReader.covariances(table) if table is not None and table.num_rows else np.zeros((0, 2, 2))


def _theta(table: pa.Table) -> np.ndarray:
    if table.num_rows == 0:
        return np.zeros((0, 2))
    return np.column_stack([table["theta1_rad"].to_numpy(), table["theta2_rad"].to_numpy()])


def carry_ids(prev_corners: pa.Table | None, prev_next_id: int | None, corners: pa.Table,
              gates: IdGates) -> tuple[pa.Table, IdMatch, int]:
    """``corners`` with ``corner_id`` replaced by stable ids; the match to ``prev_corners`` (None: no previous
    version in this frame) and the id counter after. Fresh ids go in (east, north) order. A map's first version
    (no previous corners and no counter) keeps the corner stage's ids when they are unique and positive."""
    en, theta = _en(corners), _theta(corners)
    given = corners["corner_id"].to_numpy() if corners.num_rows else np.zeros(0, np.int64)
    if prev_corners is None and prev_next_id is None and (len(given) == 0 or (
            given.min() >= 1 and len(np.unique(given)) == len(given))):
        empty = match_corners(np.zeros((0, 2)), np.zeros((0, 2)), en, theta, gates)
        return corners, empty, int(given.max()) + 1 if len(given) else 1
    order = np.lexsort((en[:, 1], en[:, 0])) if len(en) else np.zeros(0, np.int64)
    if prev_corners is None or prev_corners.num_rows == 0:
        match = match_corners(np.zeros((0, 2)), np.zeros((0, 2)), en, theta, gates)
        prev_ids = np.zeros(0, np.int64)
    else:
        match = match_corners(_en(prev_corners), _theta(prev_corners), en, theta, gates)
        prev_ids = prev_corners["corner_id"].to_numpy()
    floor = int(prev_ids.max()) + 1 if len(prev_ids) else 1  # cornermap numbers from 1
    next_id = max(int(prev_next_id or 0), floor)
    ids, next_id = assign_ids(prev_ids, match, len(en), next_id, order)
    col = corners.schema.get_field_index("corner_id")
    out = corners.set_column(col, corners.schema.field(col), pa.array(ids, corners.schema.field(col).type))
    return out, match, next_id


def _corner_entries(table: pa.Table | None, idx: np.ndarray, size_m: float, keep: np.ndarray | None = None,
                    looks: np.ndarray | None = None, want: bool = True) -> list[dict[str, Any]]:
    """Entries of the corners ``idx`` of ``table`` (those whose ``keep`` is ``want``), with the other version's
    scans that had them in view when given."""
    if table is None:
        return []
    sel = np.ones(len(idx), bool) if keep is None else (np.asarray(keep, bool) == want)
    idx = np.asarray(idx, np.int64)[sel]
    en = _en(table)[idx]
    ids = table["corner_id"].to_numpy()[idx] if len(idx) else np.zeros(0, np.int64)
    ti, tj = tile_key_of(en[:, 0], en[:, 1], size_m) if len(idx) else (np.zeros(0), np.zeros(0))
    out = [{"id": int(c), "east_m": round(float(e), 3), "north_m": round(float(n), 3), "tile": [int(i), int(j)]}
           for c, (e, n), i, j in zip(ids.tolist(), en.tolist(), np.asarray(ti).tolist(), np.asarray(tj).tolist())]
    if looks is not None and keep is not None:
        for entry, lk in zip(out, np.asarray(looks)[sel]):
            entry["scans_in_view"] = int(lk)
    return out


def build_changelog(*, parent_version: int | None, parent_manifest: dict[str, Any] | None,
                    prev_corners: pa.Table | None, corners: pa.Table, match: IdMatch, gates: IdGates,
                    move_threshold_m: float, origin: EnuOrigin, tile_size_m: float, frame_unchanged: bool | None,
                    source_drives: list[dict[str, Any]], marking_px_changed: dict[tuple[int, int], int],
                    next_corner_id: int, significance: float = SIGNIFICANCE,
                    prev_paths: list[np.ndarray] | None = None, new_paths: list[np.ndarray] | None = None,
                    marking_cells: tuple[list[dict], dict] | None = None, min_obs: int = 8) -> dict[str, Any]:
    """The changelog document of a new version (all lists sorted, numbers rounded: deterministic text).

    Kept corners are ``moved`` when the chi-square test on their displacement with both covariances rejects
    "unchanged" at ``significance`` (mapformat/change_tests.py); ``move_threshold_m`` is recorded for readers of
    format 1. With ``prev_paths`` / ``new_paths`` (the two versions' drives, (N,2) ENU each), an unmatched corner is
    ``removed`` / ``added`` only when the other version's drives had it in view from at least ``min_obs`` scans
    (the corner map's minimum observations; ``change_tests``' module doc), else ``not_reobserved`` /
    ``newly_observed``. ``marking_cells``: ``change_tests.changed_cells``' result."""
    prev_drives = {d["drive"]: d.get("fingerprint") for d in (parent_manifest or {}).get("source_drives", [])}
    new_drives = {d["drive"]: d.get("fingerprint") for d in source_drives}
    n_prev = 0 if prev_corners is None else prev_corners.num_rows
    removed = np.setdiff1d(np.arange(n_prev), match.i_prev)
    added = np.setdiff1d(np.arange(corners.num_rows), match.i_new)
    new_ids = corners["corner_id"].to_numpy() if corners.num_rows else np.zeros(0, np.int64)
    stat, p_value = (corner_chi2(_en(corners)[match.i_new] - _en(prev_corners)[match.i_prev],
                                 covariances(prev_corners)[match.i_prev], covariances(corners)[match.i_new])
                     if len(match.i_new) else (np.zeros(0), np.zeros(0)))
    moved_sel = stat > chi2_threshold(significance)
    en_new = _en(corners)
    moved = [{"id": int(new_ids[j]), "dist_m": round(float(d), 3), "angle_deg": round(float(a), 2),
              "chi2": round(float(c), 2), "p_value": float(f"{pv:.3g}"), "east_m": round(float(en_new[j, 0]), 3),
              "north_m": round(float(en_new[j, 1]), 3)}
             for j, d, a, c, pv in zip(match.i_new[moved_sel], match.dist_m[moved_sel], match.angle_deg[moved_sel],
                                       stat[moved_sel], p_value[moved_sel])]
    seen_new, looks_new = _confirmed(new_paths, prev_corners, removed, min_obs)
    seen_old, looks_old = _confirmed(prev_paths, corners, added, min_obs)
    dist = match.dist_m
    frame = {"enu_origin": origin.as_dict(), "tile_size_m": float(tile_size_m), "unchanged": frame_unchanged}
    if parent_manifest is not None and not frame_unchanged:
        frame["parent_enu_origin"] = parent_manifest.get("enu_origin")
        frame["parent_tile_size_m"] = parent_manifest.get("tile_size_m")
    return {
        "format": CHANGELOG_FORMAT, "format_version": CHANGELOG_FORMAT_VERSION,
        "parent_version": parent_version, "frame": frame,
        "drives": {"added": sorted(set(new_drives) - set(prev_drives)),
                   "removed": sorted(set(prev_drives) - set(new_drives)),
                   "changed": sorted(d for d in set(new_drives) & set(prev_drives) if new_drives[d] != prev_drives[d]),
                   "all": sorted(new_drives)},
        "corners": {"n_before": int(n_prev), "n_after": int(corners.num_rows), "kept": int(len(match.i_new)),
                    "unchanged": int(len(match.i_new) - len(moved)),
                    "test": {"method": "chi2: d^T (C_parent + C_new)^-1 d of each kept corner", "dof": DOF,
                             "significance": significance, "threshold": round(chi2_threshold(significance), 3)},
                    "presence": {"rule": "removed / added when the other version's drives had the corner in "
                                 "view from at least min_obs scans", "min_obs": int(min_obs)},
                    "added": _corner_entries(corners, added, tile_size_m, seen_old, looks_old, True),
                    "newly_observed": _corner_entries(corners, added, tile_size_m, seen_old, looks_old, False),
                    "removed": _corner_entries(prev_corners, removed, tile_size_m, seen_new, looks_new, True),
                    "not_reobserved": _corner_entries(prev_corners, removed, tile_size_m, seen_new, looks_new, False),
                    "moved": moved, "move_threshold_m": move_threshold_m,
                    "kept_dist_m": {"median": round(float(np.median(dist)), 4) if len(dist) else None,
                                    "p95": round(float(np.percentile(dist, 95)), 4) if len(dist) else None,
                                    "max": round(float(dist.max()), 4) if len(dist) else None},
                    "id_gates": asdict(gates), "next_corner_id": int(next_corner_id)},
        "markings": {"tiles": [{"tile": [i, j], "px_changed": int(n)}
                               for (i, j), n in sorted(marking_px_changed.items()) if n],
                     "total_px_changed": int(sum(marking_px_changed.values())),
                     "cell_m": MARKING_CELL_M,
                     "test": (marking_cells[1] if marking_cells else None),
                     "cells": (marking_cells[0] if marking_cells else [])},
    }


def _confirmed(paths: list[np.ndarray] | None, table: pa.Table | None, idx: np.ndarray, min_obs: int
               ) -> tuple[np.ndarray, np.ndarray]:
    """For those corners of ``table``: (confirmed: the other version's drives ``paths`` had them in view from at
    least ``min_obs`` scans; those scans). All confirmed when the paths are not known."""
    if paths is None or table is None or len(idx) == 0:
        return np.ones(len(idx), bool), np.zeros(len(idx), np.int64)
    from mapformat.change_tests import looks_from

    looks = looks_from(paths, _en(table)[idx], _theta(table)[idx],
                       table["convex"].to_numpy(zero_copy_only=False).astype(bool)[idx])
    return looks >= min_obs, looks


def marking_changes(new_tiles: list[dict[str, Any]], staging: Path, prev: Any | None) -> dict[tuple[int, int], int]:
    """Per tile: marking pixels whose painted state differs from the previous version (0 when the mask file's
    sha256 is the same). ``prev`` is the previous version's MapReader, or None."""
    import cv2

    from mapformat.diff import count_changed_pixels

    prev_entries = {k: prev.tile_entry(*k) for k in prev.tile_keys()} if prev is not None else {}
    new_entries = {(int(t["i"]), int(t["j"])): t for t in new_tiles}
    out = {}
    for key in sorted(set(prev_entries) | set(new_entries)):
        en, ep = new_entries.get(key, {}), prev_entries.get(key, {})
        mask_n = (en.get("marking") or {}).get("mask_file")
        mask_p = (ep.get("marking") or {}).get("mask_file")
        sha_n = en.get("files", {}).get(mask_n) if mask_n else None
        sha_p = ep.get("files", {}).get(mask_p) if mask_p else None
        if sha_n == sha_p:
            continue
        img_n = cv2.imread(str(staging / en["dir"] / mask_n), cv2.IMREAD_UNCHANGED) if mask_n else None
        img_p = prev.tile_marking(*key) if mask_p else None
        out[key] = count_changed_pixels(img_p, img_n)
    return out


def marking_cell_changes(new_tiles: list[dict[str, Any]], staging: Path, prev: Any | None,
                         significance: float = SIGNIFICANCE) -> tuple[list[dict], dict] | None:
    """The marking cells that changed since the previous version (``change_tests.changed_cells``), over the tiles
    both versions hold a raster of, where both observed the ground. None without a previous version."""
    if prev is None:
        return None
    import cv2

    from mapformat.change_tests import changed_cells, tile_cells
    from mapformat.layers import read_layer, sidecar_layers

    cells = []
    for entry in new_tiles:
        key = (int(entry["i"]), int(entry["j"]))
        meta = entry.get("marking") or {}
        if not meta.get("mask_file") or key not in prev.tile_keys() or prev.tile_marking(*key) is None:
            continue
        tile_dir = staging / entry["dir"]
        mask = cv2.imread(str(tile_dir / meta["mask_file"]), cv2.IMREAD_UNCHANGED)
        seen_new = (read_layer(tile_dir, meta, "point_count") > 0) if "point_count" in sidecar_layers(tile_dir, meta) \
            else np.ones(mask.shape[:2], bool)
        e0, n0 = float(meta["origin_east_m"]), float(meta["origin_north_m"])
        cell = float(meta["cell_m"])
        seen_old, _, _ = prev.observed_window(e0, n0, e0 + mask.shape[1] * cell, n0 + mask.shape[0] * cell)
        if seen_old.shape != seen_new.shape:
            continue
        cells.append(tile_cells(prev.tile_marking(*key), mask, seen_new & (seen_old > 0), (e0, n0), cell,
                                MARKING_CELL_M, MARKING_TOLERANCE_PX))
    return changed_cells(cells, MARKING_CELL_M, significance)


def write_changelog(staging: Path, doc: dict[str, Any]) -> str:
    (staging / CHANGELOG_FILE).write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    return CHANGELOG_FILE


def read_changelog(version_dir: Path, manifest: dict[str, Any],
                   read: Callable[[Path, str, dict], bytes] | None = None) -> dict[str, Any] | None:
    """The version's changelog, its bytes checked against the manifest (None for a version without one)."""
    from mapformat.loader import read_verified
    from pipeline.errors import MapFormatError

    rel = manifest.get("changelog")
    if not rel:
        return None
    data = (read or read_verified)(Path(version_dir), str(rel), manifest.get("files", {}))
    try:
        doc = json.loads(data)
    except ValueError as exc:
        raise MapFormatError(
            f"{Path(version_dir) / rel}: not JSON ({exc}); hint: run `cornermap tiles verify`"
        ) from exc
    if not isinstance(doc, dict) or doc.get("format") != CHANGELOG_FORMAT:
        raise MapFormatError(f"{Path(version_dir) / rel}: not a {CHANGELOG_FORMAT} document")
    return doc


def summary_line(version: str, manifest: dict[str, Any], doc: dict[str, Any] | None) -> str:
    """One line of ``cornermap tiles log``."""
    parent = doc.get("parent_version") if doc else None
    head = f"{version}  {manifest.get('created_utc', '?')}  parent={f'v{parent:04d}' if parent is not None else '-'}"
    if doc is None:
        return f"{head}  (no changelog: published before changelogs existed)"
    c, d, m, f = doc["corners"], doc["drives"], doc["markings"], doc["frame"]
    drives = ("+" + ",+".join(d["added"]) if d["added"] else "") + \
             (" " + " ".join("-" + x for x in d["removed"]) if d["removed"] else "")
    frame = {True: "frame unchanged", False: "FRAME CHANGED", None: "first version"}[f.get("unchanged")]
    views = (f" (+{len(c['newly_observed'])} newly observed, -{len(c['not_reobserved'])} not re-observed)"
             if c.get("newly_observed") or c.get("not_reobserved") else "")
    cells = f", {len(m['cells'])} cell(s) changed" if m.get("cells") is not None and doc["format_version"] >= 2 else ""
    return (f"{head}  drives {drives.strip() or 'unchanged'}  corners +{len(c['added'])} -{len(c['removed'])} "
            f"~{len(c['moved'])}{views} kept={c['kept']} (n={c['n_after']})  marking px changed "
            f"{m['total_px_changed']} in {len(m['tiles'])} tile(s){cells}  {frame}")
