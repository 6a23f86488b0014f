"""Road-marking extraction from the intensity image of traversable cells (Kim et al. 2.1).

Road paint is brighter than the asphalt around it, but raw intensities vary across the road (asphalt
colour, range, sensor), so a global threshold fails. As in the paper, an adaptive threshold (OpenCV
``adaptiveThreshold``, local box mean) compares each cell with its neighbourhood:

    marking  <=>  I8 > mean_block(I8) + offset,   offset = max(k * sigma_hp, min_levels)

- I8 is the cell mean intensity normalised robustly to 8 bits (percentiles of the traversable cells).
- The threshold runs per connected traversable region (curbs split road from sidewalk): cells outside the
  region are first filled with the local mean of the region's cells around them (normalised box filter),
  so curbs, cars, empty cells and a bright sidewalk neither darken nor brighten the road's local mean.
- sigma_hp is a robust (MAD) sigma of the high-passed image I8 - mean_block(I8) on traversable cells: the
  offset adapts to the texture of the tile's road surface rather than to its raw intensity scale.
- Clean-up: optional morphological opening / closing (OpenCV), then blobs smaller than ``min_area_px`` go.
Sizes arrive in pixels; the stage converts metres with ``metres_to_odd_px`` / ``metres_to_px``.
"""
from __future__ import annotations

import cv2
import numpy as np


def metres_to_px(length_m: float, cell_m: float) -> int:
    """Length in metres -> whole pixels (>= 0)."""
    return max(0, int(round(length_m / cell_m)))


def metres_to_odd_px(length_m: float, cell_m: float, minimum: int = 3) -> int:
    """Length in metres -> an odd pixel count >= ``minimum`` (OpenCV block sizes must be odd)."""
    n = max(minimum, int(round(length_m / cell_m)))
    return n if n % 2 == 1 else n + 1


def normalise_intensity(mean_intensity: np.ndarray, mask: np.ndarray, low_pct: float = 1.0,
                        high_pct: float = 99.5) -> tuple[np.ndarray, float, float]:
    """Raw cell intensity -> uint8 (0 outside ``mask``), mapping the low/high percentiles of the masked
    cells to 0/255. Returns (image, raw_low, raw_high)."""
    image = np.zeros(mean_intensity.shape, np.uint8)
    values = mean_intensity[mask & np.isfinite(mean_intensity)]
    if values.size == 0:
        return image, 0.0, 0.0
    lo, hi = (float(v) for v in np.percentile(values, [low_pct, high_pct]))
    if not hi > lo:
        hi = lo + 1.0
    scaled = np.clip((mean_intensity - lo) / (hi - lo) * 255.0, 0, 255)
    image[mask] = np.round(np.nan_to_num(scaled[mask])).astype(np.uint8)
    return image, lo, hi


def fill_outside(image_u8: np.ndarray, mask: np.ndarray, block_px: int) -> np.ndarray:
    """Replace cells outside ``mask`` by the box mean of the masked cells around them (global median where
    none is in reach); cells inside ``mask`` are unchanged."""
    m = mask.astype(np.float32)
    values = image_u8.astype(np.float32) * m
    num = cv2.boxFilter(values, -1, (block_px, block_px), normalize=False, borderType=cv2.BORDER_CONSTANT)
    den = cv2.boxFilter(m, -1, (block_px, block_px), normalize=False, borderType=cv2.BORDER_CONSTANT)
    fallback = float(np.median(image_u8[mask])) if mask.any() else 0.0
    local = np.where(den > 0.5, num / np.maximum(den, 1e-6), fallback)
    out = np.where(mask, image_u8.astype(np.float32), local)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def highpass_sigma(image_u8: np.ndarray, mask: np.ndarray, block_px: int) -> float:
    """Robust sigma (1.4826 MAD) of image - box_mean(image) over ``mask``; 0 when the mask is empty."""
    if not mask.any():
        return 0.0
    img = image_u8.astype(np.float32)
    local = cv2.boxFilter(img, -1, (block_px, block_px), borderType=cv2.BORDER_REPLICATE)
    resid = (img - local)[mask]
    return float(1.4826 * np.median(np.abs(resid - np.median(resid))))


def remove_small_blobs(mask: np.ndarray, min_area_px: int) -> np.ndarray:
    """Drop 8-connected components with fewer than ``min_area_px`` pixels."""
    if min_area_px <= 1 or not mask.any():
        return mask.copy()
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= min_area_px
    keep[0] = False  # background
    return keep[labels]


def _threshold_region(image_u8: np.ndarray, region: np.ndarray, box: tuple[int, int, int, int],
                      block_px: int, offset: float) -> tuple[tuple[slice, slice], np.ndarray]:
    """cv2.adaptiveThreshold restricted to ``region`` (a crop at ``box`` = (row0, col0, rows, cols) of the
    image): cells outside it are filled from inside first, so the local mean only sees the region (a bright
    sidewalk across a curb does not lift or drop the road's). Returns the crop slices and its mask."""
    r0, c0, h, w = box
    pad = block_px // 2 + 1
    R0, C0 = max(r0 - pad, 0), max(c0 - pad, 0)
    R1, C1 = min(r0 + h + pad, image_u8.shape[0]), min(c0 + w + pad, image_u8.shape[1])
    sub_region = np.zeros((R1 - R0, C1 - C0), bool)
    sub_region[r0 - R0:r0 - R0 + h, c0 - C0:c0 - C0 + w] = region
    filled = fill_outside(image_u8[R0:R1, C0:C1], sub_region, block_px)
    binary = cv2.adaptiveThreshold(filled, 255, cv2.ADAPTIVE_THRESH_MEAN_C, cv2.THRESH_BINARY, block_px,
                                   -offset)
    return (slice(R0, R1), slice(C0, C1)), (binary > 0) & sub_region


def extract_markings(image_u8: np.ndarray, traversable: np.ndarray, *, block_px: int, offset_sigma: float,
                     min_offset_levels: float, open_px: int = 0, close_px: int = 0, min_area_px: int = 0,
                     min_region_px: int = 400) -> tuple[np.ndarray, float]:
    """Boolean marking mask (only on traversable cells) and the offset used, in 8-bit levels.

    The threshold runs separately on each 8-connected traversable region of at least ``min_region_px``
    cells (road, sidewalk, island: curbs separate them); smaller regions are thresholded together.
    """
    if block_px < 3 or block_px % 2 == 0:
        raise ValueError(f"adaptive threshold block must be an odd pixel count >= 3, got {block_px}")
    mask = np.zeros(traversable.shape, bool)
    if not traversable.any():
        return mask, 0.0
    filled = fill_outside(image_u8, traversable, block_px)
    offset = max(offset_sigma * highpass_sigma(filled, traversable, block_px), min_offset_levels)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(traversable.astype(np.uint8), connectivity=8)
    big = np.nonzero(stats[:, cv2.CC_STAT_AREA] >= min_region_px)[0]
    big = big[big > 0]
    regions = []
    for k in big:
        c0, r0, w, h = (int(stats[k, q]) for q in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP, cv2.CC_STAT_WIDTH,
                                                    cv2.CC_STAT_HEIGHT))
        regions.append((labels[r0:r0 + h, c0:c0 + w] == k, (r0, c0, h, w)))
    is_big = np.zeros(n, bool)
    is_big[big] = True
    small = traversable & ~is_big[labels]
    if small.any():
        regions.append((small, (0, 0) + small.shape))
    for region, box in regions:
        sl, found = _threshold_region(image_u8, region, box, block_px, offset)
        mask[sl] |= found
    if open_px > 1:
        kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (open_px, open_px))
        mask = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_OPEN, kernel).astype(bool)
    if close_px > 1:
        kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (close_px, close_px))
        mask = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_CLOSE, kernel).astype(bool) & traversable
    return remove_small_blobs(mask, min_area_px), float(offset)
