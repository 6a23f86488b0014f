"""A synthetic painted street with known truth, for oracle tests and the throughput benchmark.

Scene (ENU metres, inside [0, 20) x [0, 20) plus an optional repeat offset):
- road: north in [4, 14), sloped 5 % along east and 2 % across; intensity varies across the road (asphalt
  colour) so a global threshold cannot separate paint;
- curbs 0.15 m high at north = 4 and north = 14, sidewalks beyond (smooth, brighter than asphalt);
- a 0.15 m lane line (north in [8.95, 9.10), east in [1, 12)) and a crosswalk of four 0.5 m stripes
  (east in [14 + k, 14.5 + k), north in [5, 13));
- a parked car (east [3, 7.5), north [4.5, 6.3)): roof 1.5 m above the road, vertical sides, no road points
  under it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ROAD_NORTH_M = (4.0, 14.0)
CURB_HEIGHT_M = 0.15
LANE_LINE = ((1.0, 12.0), (8.95, 9.10))  # (east range, north range)
CROSSWALK_STRIPES = tuple(((14.0 + k, 14.5 + k), (5.0, 13.0)) for k in range(4))
CAR = ((3.0, 7.5), (4.5, 6.3))
CAR_HEIGHT_M = 1.5


@dataclass(frozen=True)
class SyntheticStreet:
    points_enu_m: np.ndarray  # (N,3)
    intensity: np.ndarray  # (N,)


def road_height_m(east_m, north_m):
    return 0.05 * np.asarray(east_m) + 0.02 * (np.asarray(north_m) - ROAD_NORTH_M[0])


def _inside(east, north, box) -> np.ndarray:
    (e0, e1), (n0, n1) = box
    return (east >= e0) & (east < e1) & (north >= n0) & (north < n1)


def paint_mask_of(east_m: np.ndarray, north_m: np.ndarray) -> np.ndarray:
    """Truth: True where (east, north) lies on paint."""
    mask = _inside(east_m, north_m, LANE_LINE)
    for stripe in CROSSWALK_STRIPES:
        mask |= _inside(east_m, north_m, stripe)
    return mask


def make_street(rng: np.random.Generator, density_per_m2: float = 500.0, size_m: float = 20.0,
                height_noise_m: float = 0.005) -> SyntheticStreet:
    """Sample the scene (see the module docstring) as a uniform random point cloud."""
    n = int(density_per_m2 * size_m * size_m)
    east = rng.uniform(0.0, size_m, n)
    north = rng.uniform(0.0, size_m, n)
    on_road = (north >= ROAD_NORTH_M[0]) & (north < ROAD_NORTH_M[1])
    up = road_height_m(east, np.clip(north, *ROAD_NORTH_M)) + np.where(on_road, 0.0, CURB_HEIGHT_M)
    # asphalt brightness drifts across the road (20 -> 32); sidewalks 38; paint +40 over the asphalt
    intensity = np.where(on_road, 20.0 + 1.2 * (north - ROAD_NORTH_M[0]), 38.0)
    intensity = intensity + np.where(on_road & paint_mask_of(east, north), 40.0, 0.0)
    under_car = _inside(east, north, CAR)
    keep = ~under_car
    east, north, up, intensity = east[keep], north[keep], up[keep], intensity[keep]
    # the car: roof plus four vertical sides
    (ce0, ce1), (cn0, cn1) = CAR
    n_roof = int(density_per_m2 * (ce1 - ce0) * (cn1 - cn0))
    roof_e, roof_n = rng.uniform(ce0, ce1, n_roof), rng.uniform(cn0, cn1, n_roof)
    roof_u = road_height_m(roof_e, roof_n) + CAR_HEIGHT_M
    n_side = int(density_per_m2 * 2 * ((ce1 - ce0) + (cn1 - cn0)) * CAR_HEIGHT_M)
    t = rng.uniform(0.0, 1.0, n_side)
    side = rng.integers(0, 4, n_side)
    side_e = np.choose(side, [ce0 + t * (ce1 - ce0), ce0 + t * (ce1 - ce0), np.full(n_side, ce0),
                              np.full(n_side, ce1 - 1e-3)])
    side_n = np.choose(side, [np.full(n_side, cn0), np.full(n_side, cn1 - 1e-3), cn0 + t * (cn1 - cn0),
                              cn0 + t * (cn1 - cn0)])
    side_u = road_height_m(side_e, side_n) + rng.uniform(0.1, CAR_HEIGHT_M, n_side)
    east = np.concatenate([east, roof_e, side_e])
    north = np.concatenate([north, roof_n, side_n])
    up = np.concatenate([up, roof_u, side_u])
    up = up + rng.normal(0.0, height_noise_m, len(up))
    intensity = np.concatenate([intensity, np.full(n_roof + n_side, 15.0)])
    intensity = intensity + rng.normal(0.0, 2.0, len(intensity))
    return SyntheticStreet(np.column_stack([east, north, up]), intensity.astype(np.float32))


def truth_raster(rows: int, cols: int, origin_east_m: float, origin_north_m: float, cell_m: float,
                 offset_east_m: float = 0.0, offset_north_m: float = 0.0) -> np.ndarray:
    """Paint truth sampled at pixel centres of a raster (row 0 = north) whose scene starts at the offset."""
    col = np.arange(cols)
    row = np.arange(rows)
    east = origin_east_m + (col + 0.5) * cell_m - offset_east_m
    north = origin_north_m + (rows - 1 - row + 0.5) * cell_m - offset_north_m
    ee, nn = np.meshgrid(east, north)
    return paint_mask_of(ee, nn)
