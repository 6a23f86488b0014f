"""Horizontal survey anchoring from painted road markings.

The survey cloud fixes the road height but slides horizontally along a flat road; its painted markings (lane
lines, stop lines, crosswalks, arrows) fix the horizontal position. Given road-marking feature points of a
small submap around one keyframe (map frame, ENU metres, placed with the current pose estimate) and the
survey marking mask, ``match_markings`` finds the 2-D shift that moves the features onto the markings.

Method:
1. Kernel: ``exp(-d^2 / (2 blur_m^2))`` with ``d`` the distance (``cv2.distanceTransform``) from a cell to the
   nearest painted cell. A feature on paint scores 1, a near miss a little less. (A plain Gaussian blur of the
   mask, as first suggested, scores only ~0.38 at the centre of a 15 cm line for ``blur_m`` = 0.15 m, so
   "share of features on markings" and ``min_score`` would lose their meaning.)
2. Features inside the mask shrunk by the search radius are splatted bilinearly into a float32 count image, so
   the correlation below samples the kernel at each feature's exact (sub-cell) position.
3. Correlation over every integer-cell shift within +-2 search_m (plus one ring for the peak fit):
   ``cv2.matchTemplate(kernel_crop, counts, TM_CCORR)`` on float32 (OpenCV switches to its DFT path for large
   templates). score(shift) = correlation / n_features = mean kernel value of the shifted features.
4. Sub-cell peak: least-squares quadratic on the 3x3 neighbourhood (per-axis parabolas when that fit is not a
   proper maximum).
5. Uncertainty from the peak's shape: the (score - threshold)-weighted second moment, about the peak, of all
   shifts scoring above ``(1 - min_peak_contrast) * peak``, i.e. the spread of the shifts the markings cannot
   tell from the best one. Eigen-directions: sigma floored at ``min_sigma_m``; a direction with sigma above
   ``max_sigma_m`` (along a lane line) gets zero information, and the shift along it is dropped (the markings
   do not determine it). Rejected only when both directions are weak.
Gates: too few features; score below ``min_score``; a better match outside the search window (scores are
computed out to 2 x search_m and the inside peak is below ``(1 - min_peak_contrast)`` of the best outside one);
no clear peak (both directions weak); peak on the border of the search window along a constrained direction.
Lane markings repeat every ~3.5 m, so a true shift beyond 2 x search_m can still alias onto a wrong lane.
Known limit (measured): the peak-width sigma is ~0.1 m at blur_m = 0.15 m even when the estimate is good to
a few mm, and it grows when markings that do not fix a direction dilute those that do.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class MarkingMatch:
    shift_en_m: np.ndarray      # (2,) add to the features (and so to the keyframe pose) to land on the survey
    information_en: np.ndarray  # (2,2) 1/m^2, ENU axes; zeros when rejected
    score: float                # share of features on (blurred) survey markings at the best shift
    n_features: int
    accepted: bool
    reason: str                 # "accepted" or why not (named numbers)
    yaw_rad: float = 0.0        # heading correction of the submap the match was made at (survey_markings)


def marking_kernel(survey_mask: np.ndarray, cell_m: float, blur_m: float) -> np.ndarray:
    """(H,W) float32: 1 on painted cells, ``exp(-d^2/(2 blur^2))`` at distance ``d`` from the nearest one."""
    off_paint = (~np.asarray(survey_mask, dtype=bool)).astype(np.uint8)
    if not off_paint.any():
        return np.ones(off_paint.shape, np.float32)
    if off_paint.all():
        return np.zeros(off_paint.shape, np.float32)
    d_m = cv2.distanceTransform(off_paint, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * np.float32(cell_m)
    return np.exp(-0.5 * (d_m / np.float32(blur_m)) ** 2).astype(np.float32)


def _splat_bilinear(rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    r0, c0 = np.floor(rows).astype(np.int64), np.floor(cols).astype(np.int64)
    fr, fc = rows - r0, cols - c0
    idx = np.concatenate([r0 * shape[1] + c0, r0 * shape[1] + c0 + 1, (r0 + 1) * shape[1] + c0,
                          (r0 + 1) * shape[1] + c0 + 1])
    w = np.concatenate([(1 - fr) * (1 - fc), (1 - fr) * fc, fr * (1 - fc), fr * fc])
    return np.bincount(idx, weights=w, minlength=shape[0] * shape[1]).reshape(shape).astype(np.float32)


def _subcell_peak(patch: np.ndarray) -> np.ndarray:
    """Offset (drow, dcol) in cells of the maximum of a quadratic fitted to a 3x3 patch centred on its max."""
    y, x = np.mgrid[-1:2, -1:2]
    x, y, f = x.ravel().astype(float), y.ravel().astype(float), patch.ravel().astype(float)
    A = np.column_stack([np.ones(9), x, y, x * x, x * y, y * y])
    a = np.linalg.lstsq(A, f, rcond=None)[0]
    Hs = np.array([[2 * a[5], a[4]], [a[4], 2 * a[3]]])  # (row, col) order
    if np.all(np.linalg.eigvalsh(Hs) < 0):
        off = np.linalg.solve(Hs, -np.array([a[2], a[1]]))
        if np.max(np.abs(off)) <= 1.0:
            return off
    out = np.zeros(2)
    for k, (lo, mid, hi) in enumerate([(patch[0, 1], patch[1, 1], patch[2, 1]),
                                       (patch[1, 0], patch[1, 1], patch[1, 2])]):
        den = lo - 2 * mid + hi
        out[k] = np.clip(0.5 * (lo - hi) / den, -0.5, 0.5) if den < 0 else 0.0
    return out


BLUR_M = 0.15  # the kernel's blur (``match_markings``'s default)


def match_markings(features_en_m: np.ndarray, survey_mask: np.ndarray, origin_en_m: tuple[float, float],
                   cell_m: float, *, search_m: float = 1.5, blur_m: float = BLUR_M, min_features: int = 200,
                   min_score: float = 0.4, min_sigma_m: float = 0.03, max_sigma_m: float = 0.5,
                   min_peak_contrast: float = 0.25, sigma_scale: float = 1.0,
                   kernel_image: np.ndarray | None = None) -> MarkingMatch:
    """Best 2-D shift of the submap features onto the survey markings (north-up grid, row 0 = north edge,
    origin = south-west corner), with a 2x2 information matrix from the peak shape and accept/reject gates.

    The peak's width per direction (second moment above ``1 - min_peak_contrast`` of the peak) says which
    directions the markings fix (gate: ``max_sigma_m``); the position's standard deviation is that width times
    ``sigma_scale`` (the peak of many features is located far better than its width), floored at
    ``min_sigma_m``.

    ``kernel_image``: ``marking_kernel(survey_mask, cell_m, blur_m)`` of the whole mask, when several matches share
    one mask (a keyframe's yaw search: 8 matches); the kernel is then cut from it instead of computed on a crop padded
    by 4 ``blur_m``. The two differ only where the nearest paint lies beyond that pad: by at most exp(-8) = 3.4e-4 of
    a painted cell's value."""
    feats = np.asarray(features_en_m, dtype=np.float64).reshape(-1, 2)
    mask = np.asarray(survey_mask, dtype=bool)
    H, W = mask.shape
    R = int(np.ceil(search_m / cell_m - 1e-9))
    cols = (feats[:, 0] - origin_en_m[0]) / cell_m - 0.5          # continuous cell-centre coordinates
    rows = H - (feats[:, 1] - origin_en_m[1]) / cell_m - 0.5
    m = R + 2                                                      # search radius + fit ring + bilinear
    inside = (cols >= m) & (cols < W - 1 - m) & (rows >= m) & (rows < H - 1 - m)
    n = int(inside.sum())
    zeros2 = np.zeros((2, 2))

    def reject(reason: str, shift=np.zeros(2), score=0.0) -> MarkingMatch:
        return MarkingMatch(np.asarray(shift, float), zeros2, float(score), n, False, reason)

    if n < min_features:
        return reject(f"too few features inside the survey window shrunk by search_m={search_m:g} m: "
                      f"n_features={n} < min_features={min_features} (of {len(feats)} given)")
    rows, cols = rows[inside], cols[inside]
    r0, c0 = int(np.floor(rows.min())), int(np.floor(cols.min()))
    r1, c1 = int(np.floor(rows.max())) + 1, int(np.floor(cols.max())) + 1
    counts = _splat_bilinear(rows - r0, cols - c0, (r1 - r0 + 1, c1 - c0 + 1))
    # Correlate over an outer window of +-2*search (+1 ring for the peak fit) to see a better match just
    # outside the search window. The kernel image is zero beyond the mask (unknown survey scores nothing);
    # its distance transform runs on a crop padded by 4 blur_m so that paint just outside still counts.
    Q = 2 * R
    ia, ib, ja, jb = r0 - Q - 1, r1 + Q + 2, c0 - Q - 1, c1 + Q + 2
    kernel = np.zeros((ib - ia, jb - ja), np.float32)
    ya, yb, xa, xb = max(ia, 0), min(ib, H), max(ja, 0), min(jb, W)
    if kernel_image is not None:
        kernel[ya - ia:yb - ia, xa - ja:xb - ja] = kernel_image[ya:yb, xa:xb]
    else:
        pad = int(np.ceil(4 * blur_m / cell_m))
        pa, pb, qa, qb = max(ia - pad, 0), min(ib + pad, H), max(ja - pad, 0), min(jb + pad, W)
        big = marking_kernel(mask[pa:pb, qa:qb], cell_m, blur_m)
        kernel[ya - ia:yb - ia, xa - ja:xb - ja] = big[ya - pa:yb - pa, xa - qa:xb - qa]
    corr = cv2.matchTemplate(kernel, counts, cv2.TM_CCORR) / np.float32(n)   # (2Q+3)^2, shifts -Q-1..Q+1
    outer = corr[1:-1, 1:-1].astype(np.float64)                               # shifts -Q..Q (rows, cols)
    inner = outer[Q - R:Q + R + 1, Q - R:Q + R + 1]                           # shifts -R..R
    iy, ix = np.unravel_index(int(np.argmax(inner)), inner.shape)
    peak = float(inner[iy, ix])
    cy, cx = iy + Q - R + 1, ix + Q - R + 1                                   # peak cell in ``corr``
    off = _subcell_peak(corr[cy - 1:cy + 2, cx - 1:cx + 2])
    # a row shift of +1 cell moves the features one cell south; a column shift moves them east
    peak_pos = np.array([(ix - R) * cell_m, -(iy - R) * cell_m])
    shift_raw = peak_pos + np.array([off[1] * cell_m, -off[0] * cell_m])
    if peak < min_score:
        return reject(f"score {peak:.3f} < min_score={min_score:g} (n_features={n})", shift_raw, peak)
    best_out = float(outer.max())
    if peak < (1.0 - min_peak_contrast) * best_out:
        return reject(f"better match outside the search window: score {best_out:.3f} beyond search_m="
                      f"{search_m:g} m vs {peak:.3f} inside (min_peak_contrast={min_peak_contrast:g})",
                      shift_raw, peak)

    thr = (1.0 - min_peak_contrast) * peak
    dr, dc = np.mgrid[-Q:Q + 1, -Q:Q + 1]
    above = outer > thr
    w = outer[above] - thr
    d = np.column_stack([dc[above] * cell_m, -dr[above] * cell_m]) - shift_raw
    moment = (d * w[:, None]).T @ d / w.sum()
    vals, vecs = np.linalg.eigh(moment)
    sig = np.sqrt(np.maximum(vals, min_sigma_m ** 2))
    strong = sig <= max_sigma_m
    if not strong.any():
        return reject(f"no clear peak: sigmas {sig[0]:.2f}, {sig[1]:.2f} m > max_sigma_m={max_sigma_m:g} m "
                      f"(score {peak:.3f})", shift_raw, peak)
    reach = R * cell_m
    for k in np.flatnonzero(strong):
        v = vecs[:, k]
        if abs(v @ peak_pos) >= reach / np.max(np.abs(v)) - 0.5 * cell_m:
            return reject(f"peak on the border of the search window (search_m={search_m:g} m, peak at "
                          f"e={peak_pos[0]:+.2f}, n={peak_pos[1]:+.2f} m): true shift likely outside",
                          shift_raw, peak)
    V = vecs[:, strong]
    sig_pos = np.maximum(sig[strong] * sigma_scale, min_sigma_m)
    info = (V / sig_pos ** 2) @ V.T
    shift = V @ (V.T @ shift_raw)                                  # drop the component the markings do not fix
    return MarkingMatch(shift, info, peak, n, True, "accepted")
