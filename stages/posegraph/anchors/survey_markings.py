"""Horizontal survey anchors from painted road markings.

The survey cloud holds road and sidewalk tops only, so a 3-D registration against it fixes height, roll and
pitch but slides horizontally (``survey_anchor.vertical_part``). Its painted markings do fix the horizontal
position: around a keyframe, the road-marking points of a few consecutive scans (per-ring adaptive threshold,
Kim et al. s.2.2, deskewed, placed with the current pose estimate) are matched against the survey's marking
mask (the shared adaptive threshold of ``stages.common.marking_raster``, Kim et al. s.2.1, with the pose graph's
own ``anchors.markings.raster`` settings) by ``marking_match.match_markings``,
whose peak shape says which directions the markings fix (lane lines: across only).
Pure functions on arrays; the scans come through the caller's loader.
"""
from __future__ import annotations

import hashlib
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from stages.common.marking_raster.elevation_grid import GridAccumulator
from stages.common.marking_raster.rasterize import halo_px_for, rasterize_grid
from stages.common.marking_raster.settings import MarkingRasterSettings
from stages.common.registration import as_indices
from stages.common.road_features import extract_road_features
from stages.posegraph.anchors.marking_match import BLUR_M, MarkingMatch, marking_kernel, match_markings
from stages.posegraph.config import MarkingAnchorConfig
from stages.posegraph.factors.drive import deskew_scan_lidar

# (drive, scan_id) list -> {(drive, scan_id): (xyz_lidar (N,3), time_offset_s (N,) or None, intensity, ring)}
FeatureLoader = Callable[[list[tuple[str, int]]], dict[tuple[str, int], tuple]]


TILE_M = 100.0  # the survey's marking mask is computed once per tile of this size and windows are cut from it
MAX_TILES = 64  # tiles a worker keeps (1 MB each at 0.1 m cells)


@dataclass
class SurveyMarkingIndex:
    points_enu_m: np.ndarray | None  # (N,3); None until ``load`` (a lazy index: ``survey_marking_index``)
    intensity: np.ndarray | None  # (N,)
    tree: cKDTree | None  # 2-D, east/north
    tiles: OrderedDict = field(default_factory=OrderedDict)  # (settings, tile east, tile north) -> mask, newest last
    source: object | None = None  # a survey source (``read() -> (points, intensity)``, ``key``, ``cache_dir``)
    cache_dir: Path | None = None  # where processes share the tiles (``pipeline.parallel.build_once``); None: not
    key: str = ""  # the source's key, in the shared tiles' names

    def load(self) -> None:
        """Read the survey from ``source`` and index it (a lazy index does so for the first tile it computes)."""
        if self.tree is None:
            self._index(*self.source.read())

    def _index(self, points_enu_m: np.ndarray, intensity: np.ndarray) -> None:
        self.points_enu_m, self.intensity = np.asarray(points_enu_m, float), np.asarray(intensity, float)
        self.tree = cKDTree(self.points_enu_m[:, :2])


def build_survey_marking_index(points_enu_m: np.ndarray, intensity: np.ndarray) -> SurveyMarkingIndex:
    index = SurveyMarkingIndex(None, None, None)
    index._index(points_enu_m, intensity)
    return index


def survey_marking_index(source) -> SurveyMarkingIndex:
    """A lazy index of a survey source: the survey is read and indexed only if this process computes a tile; the
    tiles are computed once among the processes sharing the source's ``cache_dir`` (each process rasterized every
    tile its keyframes needed: on demo each of 13 tiles twice, 0.18 s each, plus the index, 1.4 s a process)."""
    return SurveyMarkingIndex(None, None, None, source=source, cache_dir=getattr(source, "cache_dir", None),
                              key=str(source.key))


def survey_marking_window(index: SurveyMarkingIndex, centre_en_m: np.ndarray, half_size_m: float,
                          raster: MarkingRasterSettings) -> tuple[np.ndarray, tuple[float, float]]:
    """The survey's marking mask (rows north-first) over a square window around ``centre_en_m``; returns (mask,
    south-west origin). The mask is the survey's, not the window's: it is computed with the shared marking rasterizer
    (elevation grid + adaptive threshold) and the pose graph's own raster settings (``anchors.markings.raster``) once
    per ``TILE_M`` tile of a fixed grid (each with the rasterizer's halo, so that tiles agree at their borders), kept
    in the index (the ``MAX_TILES`` last used), and cut out here. Every keyframe and every anchoring round sees the
    same mask where their windows overlap (windows of 96 m every 10 m of travel: each place was rasterized about 10
    times a round)."""
    cell = raster.cell_m
    tile_px = int(round(TILE_M / cell))
    n_px = int(round(2 * half_size_m / cell))
    i0 = int(np.floor((centre_en_m[0] - half_size_m) / cell))
    j0 = int(np.floor((centre_en_m[1] - half_size_m) / cell))
    out = np.zeros((n_px, n_px), bool)  # rows south-up here, flipped at the end
    settings = raster.model_dump_json()
    for ty in range(j0 // tile_px, (j0 + n_px - 1) // tile_px + 1):
        for tx in range(i0 // tile_px, (i0 + n_px - 1) // tile_px + 1):
            tile = _tile(index, settings, tx, ty, tile_px, raster)[::-1]
            ja, jb = max(j0, ty * tile_px), min(j0 + n_px, (ty + 1) * tile_px)
            ia, ib = max(i0, tx * tile_px), min(i0 + n_px, (tx + 1) * tile_px)
            out[ja - j0:jb - j0, ia - i0:ib - i0] = tile[ja - ty * tile_px:jb - ty * tile_px,
                                                         ia - tx * tile_px:ib - tx * tile_px]
    return out[::-1], (i0 * cell, j0 * cell)


def _tile(index: SurveyMarkingIndex, settings: str, tx: int, ty: int, tile_px: int,
          raster: MarkingRasterSettings) -> np.ndarray:
    from pipeline.parallel import build_once

    key = (settings, tx, ty)
    if key in index.tiles:
        index.tiles.move_to_end(key)
        return index.tiles[key]
    digest = hashlib.sha1(settings.encode()).hexdigest()[:12]
    mask = build_once(index.cache_dir, f"survey-{index.key}-marking-{digest}-{tx}-{ty}.npy",
                      lambda: marking_mask(index, tx * tile_px, ty * tile_px, tile_px, raster),
                      lambda m, fh: np.save(fh, np.packbits(m), allow_pickle=False),
                      lambda path: np.unpackbits(np.load(path, allow_pickle=False),
                                                 count=tile_px * tile_px).reshape(tile_px, tile_px).astype(bool))
    index.tiles[key] = mask
    while len(index.tiles) > MAX_TILES:
        index.tiles.popitem(last=False)
    return mask


def marking_mask(index: SurveyMarkingIndex, i0: int, j0: int, n_px: int, raster: MarkingRasterSettings
                 ) -> np.ndarray:
    """The marking mask (rows north-first) of the ``n_px`` square cells whose south-west cell is (``i0``, ``j0``)
    (cell indices: east = i * cell_m), from the survey points within it and the rasterizer's halo around it."""
    index.load()
    cell = raster.cell_m
    halo_px = halo_px_for(cell, raster.threshold_block_m, raster.ground_window_m)
    acc = GridAccumulator((i0 - halo_px) * cell, (j0 - halo_px) * cell, cell, (n_px + 2 * halo_px, n_px + 2 * halo_px))
    centre = (np.array([i0, j0]) + n_px / 2.0) * cell
    idx = as_indices(index.tree.query_ball_point(centre, (n_px / 2.0 + halo_px) * cell * np.sqrt(2)))
    if len(idx):
        acc.add(index.points_enu_m[idx], index.intensity[idx])
    return rasterize_grid(acc.finish(raster.min_points_per_cell), halo_px, **raster.rasterize_kwargs()).marking


def submap_scan_indices(positions_m: np.ndarray, k: int, half_travel_m: float, max_scans: int, step: int = 1
                        ) -> np.ndarray:
    """Scans of one drive within ``half_travel_m`` of travel before and after scan ``k`` (at most ``max_scans``
    positions on each side); with ``step`` > 1 only every ``step``-th scan of the drive among them (indices divisible
    by ``step``: neighbouring keyframes and later rounds use the same scans) and scan ``k`` itself."""
    step_m = np.r_[0.0, np.linalg.norm(np.diff(positions_m[:, :2], axis=0), axis=1)]
    travel = np.cumsum(step_m)
    lo = max(int(np.searchsorted(travel, travel[k] - half_travel_m, side="left")), k - max_scans)
    hi = min(int(np.searchsorted(travel, travel[k] + half_travel_m, side="right")), k + max_scans + 1)
    ks = np.arange(lo, hi)
    return ks if step <= 1 else ks[(ks % step == 0) | (ks == k)]


def marking_anchor(k_local: int, drive, poses_drive: np.ndarray, increments_drive: np.ndarray,
                   load: FeatureLoader, index: SurveyMarkingIndex, cfg: MarkingAnchorConfig, *,
                   window_margin_m: float = 6.0, feature_cache: dict | None = None,
                   known_features: dict | None = None) -> MarkingMatch:
    """Match the marking submap around scan ``k_local`` of ``drive`` (poses = current estimate) to the survey.
    ``feature_cache`` ({scan index: vehicle-frame features}) carries the scans shared with the previous
    keyframe's submap (consecutive submaps overlap); it is left holding this submap's scans only.
    ``known_features`` ({scan index: features}, read only) are scans' features from an earlier call (a previous
    anchoring round): a scan's features depend on its points and the drive's increments, not on the estimate.

    With ``cfg.yaw_search_deg`` > 0 the submap is also turned about the keyframe (``best_yaw_match``): the estimate's
    heading error turns the submap, and a translation-only match of a turned submap is biased by the lever arm of
    its paint (measured on tiny: the anchors inherited about half of the estimate's 0.42 deg rotation)."""
    half_travel_m, raster = cfg.half_travel_m, cfg.raster
    ks = submap_scan_indices(poses_drive[:, :3, 3], k_local, half_travel_m, cfg.max_scans, cfg.scan_step)
    cache = {} if feature_cache is None else feature_cache
    for j in set(cache) - set(ks.tolist()):
        del cache[j]
    known = known_features or {}
    for j in ks.tolist():
        if j not in cache and j in known:
            cache[j] = known[j]
    todo = [j for j in ks.tolist() if j not in cache]
    got = load([(drive.name, int(drive.scan_ids[j])) for j in todo]) if todo else {}
    for j in todo:
        xyz, toff, intensity, ring = got[(drive.name, int(drive.scan_ids[j]))]
        pts = deskew_scan_lidar(drive, increments_drive, j, np.asarray(xyz, float),
                                None if toff is None else np.asarray(toff, float))
        cache[j] = extract_road_features(pts, intensity, ring, drive.T_vehicle_lidar)
    feats = _place([cache[j] for j in ks.tolist()], poses_drive[ks])
    centre = poses_drive[k_local, :2, 3]
    half = half_travel_m + 30.0 + window_margin_m  # features reach ~30 m from their scan
    mask, origin = survey_marking_window(index, centre, half, raster)
    kernel = marking_kernel(mask, raster.cell_m, BLUR_M) if len(feats) else None  # shared by every heading

    def match_at(yaw_rad: float) -> MarkingMatch:
        c, s_ = np.cos(yaw_rad), np.sin(yaw_rad)
        turned = (feats - centre) @ np.array([[c, s_], [-s_, c]]) + centre
        return match_markings(turned, mask, origin, raster.cell_m, search_m=cfg.search_m, blur_m=BLUR_M,
                              sigma_scale=cfg.sigma_scale, min_sigma_m=cfg.min_sigma_m, kernel_image=kernel)
    if cfg.yaw_search_deg <= 0 or len(feats) == 0:
        return match_at(0.0)
    return best_yaw_match(match_at, np.deg2rad(cfg.yaw_search_deg), np.deg2rad(cfg.yaw_step_deg))


def best_yaw_match(match_at: Callable[[float], MarkingMatch], search_rad: float, step_rad: float) -> MarkingMatch:
    """The match at the submap heading that scores best: on a grid of ``step_rad`` over +-``search_rad``, climbed from
    the estimate's heading (0) to the neighbouring grid value that scores more until none does, then a parabola
    through that grid value and its neighbours, and the match at its vertex. Where the scores over the grid rise to
    one peak and fall (a submap turned by a fraction of a degree), that is the grid's best value, found with 3 to 5
    matches instead of all 7; where a second, lower peak lies beyond a dip, the climb keeps the one nearer the
    estimate. The vertex is the heading estimate even where its own score comes out a little under the grid's best
    (the raster's sampling noise): keeping the grid value instead quantizes the heading to the grid step, and a later
    anchoring round, started near the right heading, then reads exactly 0 and holds the estimate where it is. The
    returned match carries that heading correction in ``yaw_rad``."""
    from dataclasses import replace

    n = int(np.ceil(search_rad / step_rad))
    yaws = np.arange(-n, n + 1) * step_rad
    found: dict[int, MarkingMatch] = {}

    def score(k: int) -> float:
        if not 0 <= k <= 2 * n:
            return -np.inf
        if k not in found:
            found[k] = match_at(float(yaws[k]))
        return found[k].score

    b = n
    while True:
        here, lo, hi = score(b), score(b - 1), score(b + 1)
        step = -1 if lo > here and lo >= hi else (1 if hi > here else 0)
        if step == 0:
            break
        b += step
    best, best_yaw = found[b], float(yaws[b])
    if 0 < b < 2 * n:
        lo, mid, hi = score(b - 1), score(b), score(b + 1)
        den = lo - 2 * mid + hi
        if den < 0:
            y = best_yaw + float(np.clip(0.5 * (lo - hi) / den, -0.5, 0.5)) * step_rad
            best, best_yaw = match_at(y), y
    return replace(best, yaw_rad=best_yaw)


def _place(features_vehicle: list[np.ndarray], T_map_vehicle: np.ndarray) -> np.ndarray:
    out = [f @ T[:2, :2].T + T[:2, 3] for f, T in zip(features_vehicle, T_map_vehicle) if len(f)]
    return np.concatenate(out) if out else np.zeros((0, 2))


def horizontal_information_body(information_en: np.ndarray, R_map_vehicle: np.ndarray) -> np.ndarray:
    """6x6 gtsam-order (rot, trans) body-frame information holding only the ENU horizontal 2x2 block."""
    I3 = np.zeros((3, 3))
    I3[:2, :2] = information_en
    out = np.zeros((6, 6))
    out[3:, 3:] = R_map_vehicle.T @ I3 @ R_map_vehicle
    return out
