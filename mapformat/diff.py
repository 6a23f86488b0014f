"""Differences between two map versions: corners added / removed / moved, marking pixels changed, per tile.

Corner ids are carried across versions of one map (mapformat/corner_ids.py), but diff compares any two
versions (not only a parent and its child), so corners are matched geometrically here:
mutual nearest neighbours within ``match_radius_m``. A matched pair is "moved" when the chi-square test on its
displacement with both versions' covariances rejects "unchanged" at ``significance`` (mapformat/change_tests.py)
and it moved more than ``move_threshold_m`` (0: the test alone); unmatched corners of A are "removed", of B
"added". A corner that moved more than the match radius therefore shows as removed + added. Removed/moved corners
count in A's tile, added ones in B's. ``marking_cells`` gives the marking changes per 10 m cell with their test.
Two versions in different frames (ENU origin or tile size) are refused with ``ReferenceFrameError``.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from stages.common.tiling import tile_key_of

if TYPE_CHECKING:  # pragma: no cover
    from mapformat.loader import MapReader


def check_same_frame(a: "MapReader", b: "MapReader") -> None:
    """Refuse two versions in different frames (origin or tile size): their coordinates do not compare."""
    from mapformat.changelog import describe_origin, same_frame
    from pipeline.errors import ReferenceFrameError

    if not same_frame(a.origin, a.tile_size_m, b.origin, b.tile_size_m):
        raise ReferenceFrameError(
            f"v{a.version:04d} and v{b.version:04d} are in different frames: origin {describe_origin(a.origin)} "
            f"with {a.tile_size_m:g} m tiles vs origin {describe_origin(b.origin)} with {b.tile_size_m:g} m tiles; "
            "their coordinates do not compare, so no diff")


@dataclass(frozen=True)
class CornerMatch:
    ia: np.ndarray  # indices into A of matched pairs
    ib: np.ndarray  # indices into B
    dist_m: np.ndarray


def match_corners(a_en_m: np.ndarray, b_en_m: np.ndarray, match_radius_m: float) -> CornerMatch:
    """Mutual nearest neighbours between (N,2) and (M,2) east/north arrays, no further than the radius."""
    a_en_m, b_en_m = np.asarray(a_en_m, float).reshape(-1, 2), np.asarray(b_en_m, float).reshape(-1, 2)
    empty = CornerMatch(np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0))
    if len(a_en_m) == 0 or len(b_en_m) == 0:
        return empty
    d_ab, j_ab = cKDTree(b_en_m).query(a_en_m, distance_upper_bound=match_radius_m)
    _, i_ba = cKDTree(a_en_m).query(b_en_m, distance_upper_bound=match_radius_m)
    ia = np.flatnonzero(np.isfinite(d_ab))
    ib = j_ab[ia]
    mutual = i_ba[ib] == ia
    return CornerMatch(ia[mutual], ib[mutual], d_ab[ia[mutual]])


@dataclass
class TileDiff:
    i: int
    j: int
    corners_added: int = 0
    corners_removed: int = 0
    corners_moved: int = 0
    marking_px_changed: int = 0
    removed_ids: list[int] = field(default_factory=list)
    added_ids: list[int] = field(default_factory=list)
    moved_ids: list[int] = field(default_factory=list)  # ids in A

    @property
    def changed(self) -> bool:
        return bool(self.corners_added or self.corners_removed or self.corners_moved or self.marking_px_changed)

    def as_dict(self) -> dict:
        return asdict(self)


def count_changed_pixels(a: np.ndarray | None, b: np.ndarray | None) -> int:
    """Pixels whose marking state (non-zero) differs; a missing raster counts as all-empty."""
    a_on = None if a is None else (a.reshape(a.shape[0], a.shape[1], -1) > 0).any(axis=2)
    b_on = None if b is None else (b.reshape(b.shape[0], b.shape[1], -1) > 0).any(axis=2)
    if a_on is None and b_on is None:
        return 0
    if a_on is None or b_on is None or a_on.shape != b_on.shape:
        return int((0 if a_on is None else a_on.sum()) + (0 if b_on is None else b_on.sum()))
    return int(np.count_nonzero(a_on != b_on))


def diff_maps(a: "MapReader", b: "MapReader", move_threshold_m: float = 0.0,
              match_radius_m: float = 1.0, significance: float = 0.001) -> list[TileDiff]:
    """Per-tile differences from version A to version B (only tiles with a change), sorted by key."""
    from mapformat.change_tests import chi2_threshold, corner_chi2

    check_same_frame(a, b)
    size = a.tile_size_m
    ta, tb = a.all_corners(), b.all_corners()
    a_en = np.column_stack([ta["east_m"].to_numpy(), ta["north_m"].to_numpy()]) if ta.num_rows else np.zeros((0, 2))
    b_en = np.column_stack([tb["east_m"].to_numpy(), tb["north_m"].to_numpy()]) if tb.num_rows else np.zeros((0, 2))
    m = match_corners(a_en, b_en, match_radius_m)
    removed = np.setdiff1d(np.arange(len(a_en)), m.ia)
    added = np.setdiff1d(np.arange(len(b_en)), m.ib)
    stat, _ = corner_chi2(b_en[m.ib] - a_en[m.ia], a.covariances(ta)[m.ia] if len(m.ia) else np.zeros((0, 2, 2)),
                          b.covariances(tb)[m.ib] if len(m.ib) else np.zeros((0, 2, 2)))
    moved = m.ia[(stat > chi2_threshold(significance)) & (m.dist_m > move_threshold_m)]
    diffs: dict[tuple[int, int], TileDiff] = {}

    def tally(en: np.ndarray, idx: np.ndarray, ids: np.ndarray, count: str, id_list: str) -> None:
        if len(idx) == 0:
            return
        ki, kj = tile_key_of(en[idx, 0], en[idx, 1], size)
        for i, j, cid in zip(ki.tolist(), kj.tolist(), ids[idx].tolist()):
            d = diffs.setdefault((i, j), TileDiff(i, j))
            setattr(d, count, getattr(d, count) + 1)
            getattr(d, id_list).append(int(cid))

    a_ids = ta["corner_id"].to_numpy() if ta.num_rows else np.zeros(0, np.int64)
    b_ids = tb["corner_id"].to_numpy() if tb.num_rows else np.zeros(0, np.int64)
    tally(a_en, removed, a_ids, "corners_removed", "removed_ids")
    tally(b_en, added, b_ids, "corners_added", "added_ids")
    tally(a_en, moved, a_ids, "corners_moved", "moved_ids")
    keys_a, keys_b = set(a.tile_keys()), set(b.tile_keys())
    for key in sorted(keys_a | keys_b):
        ea = a.tile_entry(*key) if key in keys_a else {}
        eb = b.tile_entry(*key) if key in keys_b else {}
        sha_a = ea.get("files", {}).get((ea.get("marking") or {}).get("mask_file"))
        sha_b = eb.get("files", {}).get((eb.get("marking") or {}).get("mask_file"))
        if sha_a == sha_b:
            continue
        n = count_changed_pixels(a.tile_marking(*key) if sha_a else None, b.tile_marking(*key) if sha_b else None)
        if n:
            diffs.setdefault(key, TileDiff(*key)).marking_px_changed = n
    return [d for _, d in sorted(diffs.items()) if d.changed]


def marking_cells(a: "MapReader", b: "MapReader", significance: float = 0.001) -> tuple[list[dict], dict]:
    """The 10 m cells whose road markings changed from A to B beyond the rasters' noise, over the tiles both hold a
    raster of, where both observed the ground (``change_tests.changed_cells``; the changelog's test)."""
    from mapformat.change_tests import changed_cells, tile_cells
    from mapformat.changelog import MARKING_CELL_M, MARKING_TOLERANCE_PX

    check_same_frame(a, b)
    cells = []
    for key in sorted(set(a.tile_keys()) & set(b.tile_keys())):
        ma, mb = a.tile_marking(*key), b.tile_marking(*key)
        if ma is None or mb is None or ma.shape[:2] != mb.shape[:2]:
            continue
        meta = b.tile_entry(*key)["marking"]
        e0, n0, cell = float(meta["origin_east_m"]), float(meta["origin_north_m"]), float(meta["cell_m"])
        box = (e0, n0, e0 + mb.shape[1] * cell, n0 + mb.shape[0] * cell)
        seen = (a.observed_window(*box)[0] > 0) & (b.observed_window(*box)[0] > 0)
        if seen.shape == mb.shape[:2]:
            cells.append(tile_cells(ma, mb, seen, (e0, n0), cell, MARKING_CELL_M, MARKING_TOLERANCE_PX))
    return changed_cells(cells, MARKING_CELL_M, significance)
