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


# Traffic standing on the paint: one car on the lane line, one on the crosswalk (east range, north range).
TRAFFIC_CARS = (((4.0, 8.5), (8.1, 9.9)), ((13.8, 18.3), (6.0, 7.8)))


def _car_points(rng: np.random.Generator, box, density_per_m2: float) -> tuple[np.ndarray, np.ndarray]:
    """A box car's roof and four sides (0.1 m up to CAR_HEIGHT_M above the road), intensity 15."""
    (e0, e1), (n0, n1) = box
    n_roof = int(density_per_m2 * (e1 - e0) * (n1 - n0))
    roof = np.column_stack([rng.uniform(e0, e1, n_roof), rng.uniform(n0, n1, n_roof)])
    n_side = int(density_per_m2 * 2 * ((e1 - e0) + (n1 - n0)) * CAR_HEIGHT_M)
    t, side = rng.uniform(0.0, 1.0, n_side), rng.integers(0, 4, n_side)
    se = np.choose(side, [e0 + t * (e1 - e0), e0 + t * (e1 - e0), np.full(n_side, e0), np.full(n_side, e1 - 1e-3)])
    sn = np.choose(side, [np.full(n_side, n0), np.full(n_side, n1 - 1e-3), n0 + t * (n1 - n0), n0 + t * (n1 - n0)])
    en = np.vstack([roof, np.column_stack([se, sn])])
    up = road_height_m(en[:, 0], en[:, 1]) + np.r_[np.full(n_roof, CAR_HEIGHT_M),
                                                   rng.uniform(0.1, CAR_HEIGHT_M, n_side)]
    return np.column_stack([en, up]), np.full(len(up), 15.0)


def traffic_scans(rng: np.random.Generator, n_scans: int = 10, traffic_share: float = 0.8,
                  density_per_m2: float = 500.0, size_m: float = 20.0, height_noise_m: float = 0.005
                  ) -> list[SyntheticStreet]:
    """The painted street (no parked car) seen in ``n_scans`` scans of ``density_per_m2 / n_scans`` each; in
    the first ``round(traffic_share * n_scans)`` scans the ``TRAFFIC_CARS`` stand on the lane line and the
    crosswalk and hide the road under them. Together the scans hold ``density_per_m2`` road points per m^2."""
    with_cars = int(round(traffic_share * n_scans))
    scans = []
    for k in range(n_scans):
        street = make_street(rng, density_per_m2 / n_scans, size_m, height_noise_m)
        pts, inten = street.points_enu_m, street.intensity.astype(float)
        parked = _inside(pts[:, 0], pts[:, 1], ((CAR[0][0] - 0.01, CAR[0][1]), (CAR[1][0] - 0.01, CAR[1][1])))
        pts, inten = pts[~parked], inten[~parked]  # make_street's parked car: replaced by road below
        (pe0, pe1), (pn0, pn1) = CAR
        n_fill = int(density_per_m2 / n_scans * (pe1 - pe0) * (pn1 - pn0))
        fill = np.column_stack([rng.uniform(pe0, pe1, n_fill), rng.uniform(pn0, pn1, n_fill)])
        fill_up = road_height_m(fill[:, 0], fill[:, 1]) + rng.normal(0.0, height_noise_m, n_fill)
        fill_int = 20.0 + 1.2 * (fill[:, 1] - ROAD_NORTH_M[0]) + rng.normal(0.0, 2.0, n_fill)
        pts, inten = np.vstack([pts, np.column_stack([fill, fill_up])]), np.r_[inten, fill_int]
        if k < with_cars:
            for box in TRAFFIC_CARS:
                hidden = _inside(pts[:, 0], pts[:, 1], box)
                car_pts, car_int = _car_points(rng, box, density_per_m2 / n_scans)
                pts, inten = np.vstack([pts[~hidden], car_pts]), np.r_[inten[~hidden], car_int]
        scans.append(SyntheticStreet(pts, inten.astype(np.float32)))
    return scans
