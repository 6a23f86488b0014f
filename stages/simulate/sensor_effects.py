"""Sensor effects beyond range noise: angular jitter of each firing, beam divergence (range spread over the
beam's footprint on oblique surfaces), mixed pixels at depth discontinuities, and scans that lose whole
azimuth sectors.

- **Angular jitter**: each firing column (the 32 lasers fired at one encoder reading) leaves the sensor turned
  off its nominal (azimuth, elevation) by N(0, ``angular_jitter_deg``) on both axes (encoder jitter, head
  wobble); the driver reports the points along the nominal directions, so the error is lateral to the ray
  (``column_jitter_rotations``).
- **Beam divergence**: the footprint radius is ``range * divergence / 2``; on a surface seen at incidence
  ``theta`` the footprint spans ``+-radius * tan(theta)`` in range and the detector's range falls anywhere in
  it: N(0, radius * min(tan(theta), 5) / 2) is added (``divergence_range_sigma_m``).
- **Mixed pixels**: where two neighbouring firings of one ring (adjacent azimuth columns) hit surfaces more
  than ``mixed_min_jump_m`` apart in range, the footprint of one of them straddles the edge with probability
  ``mixed_pixel_share``; its return is then a blend ``w * r_near + (1 - w) * r_far``, w ~ U(0, 1): a point
  floating between foreground and background (``mix_edge_ranges``).
- **Sector dropouts**: a share ``sector_dropout_scan_share`` of the scans loses one sector of
  U(``sector_dropout_deg``) of azimuth entirely (lost packets, a dirty window); ``dropped_columns``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SAFE_TAN_MAX = 5.0  # incidence beyond ~79 deg: the footprint spread stops growing (the return gets too weak)


@dataclass(frozen=True)
class SensorEffects:
    angular_jitter_deg: float = 0.0
    divergence_mrad: float = 0.0
    mixed_pixel_share: float = 0.0
    mixed_min_jump_m: float = 0.3
    sector_dropout_scan_share: float = 0.0
    sector_dropout_deg: tuple[float, float] = (5.0, 30.0)

    @property
    def active(self) -> bool:
        return bool(self.angular_jitter_deg or self.divergence_mrad or self.mixed_pixel_share
                    or self.sector_dropout_scan_share)


def column_jitter_rotations(azimuth_rad: np.ndarray, sigma_deg: float, rng: np.random.Generator) -> np.ndarray:
    """(C,) nominal azimuths of the firing columns -> (C, 3, 3) rotations (lidar frame) turning each column's
    lasers by N(0, sigma) in azimuth (about z) and in elevation (about the column's horizontal normal).
    First order in the angles (sigma ~ 1e-3 rad: the error is ~1e-6)."""
    n = len(azimuth_rad)
    step = rng.standard_normal((n, 2)) * np.radians(sigma_deg)
    # rotation vector: azimuth about z; a positive elevation step turns about -a, a = (-sin az, cos az, 0)
    w = np.column_stack([step[:, 1] * np.sin(azimuth_rad), -step[:, 1] * np.cos(azimuth_rad), step[:, 0]])
    J = np.tile(np.eye(3), (n, 1, 1))
    J[:, 0, 1], J[:, 0, 2] = -w[:, 2], w[:, 1]
    J[:, 1, 0], J[:, 1, 2] = w[:, 2], -w[:, 0]
    J[:, 2, 0], J[:, 2, 1] = -w[:, 1], w[:, 0]
    return J


def divergence_range_sigma_m(range_m: np.ndarray, cos_incidence: np.ndarray, divergence_mrad: float) -> np.ndarray:
    """Std of the range over the beam's footprint on a plane seen at the given incidence."""
    cos_i = np.clip(cos_incidence, 1e-3, 1.0)
    tan_i = np.minimum(np.sqrt(1.0 - cos_i ** 2) / cos_i, SAFE_TAN_MAX)
    return 0.5 * range_m * (divergence_mrad * 1e-3 / 2.0) * tan_i


def mix_edge_ranges(range_grid_m: np.ndarray, share: float, min_jump_m: float,
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(C, R) true ranges per azimuth column and ring (inf: no hit) -> ranges with mixed pixels and the (C, R)
    mask of mixed firings. Columns wrap around (a full revolution)."""
    nxt = np.roll(range_grid_m, -1, axis=0)
    edge = np.isfinite(range_grid_m) & np.isfinite(nxt)
    edge[edge] = np.abs(range_grid_m[edge] - nxt[edge]) > min_jump_m
    ci, ri = np.nonzero(edge)
    keep = rng.random(len(ci)) < share
    ci, ri = ci[keep], ri[keep]
    take_next = rng.random(len(ci)) < 0.5  # which of the two firings straddles the edge
    col = np.where(take_next, (ci + 1) % range_grid_m.shape[0], ci)
    other = np.where(take_next, ci, (ci + 1) % range_grid_m.shape[0])
    w = rng.random(len(ci))
    out = range_grid_m.copy()
    out[col, ri] = w * range_grid_m[col, ri] + (1.0 - w) * range_grid_m[other, ri]
    mixed = np.zeros(range_grid_m.shape, bool)
    mixed[col, ri] = True
    return out, mixed


def dropped_columns(n_columns: int, scan_share: float, width_deg: tuple[float, float],
                    rng: np.random.Generator) -> np.ndarray:
    """(C,) bool: azimuth columns lost in this scan (none for most scans)."""
    lost = np.zeros(n_columns, bool)
    if scan_share <= 0 or rng.random() >= scan_share:
        return lost
    width = int(round(rng.uniform(*width_deg) / 360.0 * n_columns))
    start = int(rng.integers(n_columns))
    lost[(start + np.arange(width)) % n_columns] = True
    return lost
