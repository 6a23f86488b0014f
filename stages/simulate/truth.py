"""Ground truth derived from the city: vertical corners of the building footprints, their visibility from a
drive's scans, and a JSON description of the city."""
from __future__ import annotations

import numpy as np

from stages.simulate.city import City
from stages.simulate.geom2d import polygon_corners
from stages.simulate.mesh import Scene

VISIBLE_RANGE_M = 60.0


def building_corners(city: City) -> dict[str, np.ndarray]:
    """One row per footprint vertex: id, east, north, theta1/theta2 (deg, ENU ccw from east, along the two
    walls away from the corner), interior angle (deg), glass walls (0-2), height, bisector (unit, inward)."""
    rows = []
    for b in city.buildings:
        ang = polygon_corners(b.footprint_en)
        glass = b.glass.astype(int) + np.roll(b.glass, 1).astype(int)  # wall k-1 and wall k meet at vertex k
        for k, p in enumerate(b.footprint_en):
            inward = ang[k, 1] + ang[k, 2] / 2.0
            rows.append([p[0], p[1], ang[k, 0], ang[k, 1], ang[k, 2], glass[k], b.height_m,
                         np.cos(inward), np.sin(inward)])
    a = np.array(rows, float).reshape(-1, 9)
    deg = lambda r: (np.degrees(r) + 180.0) % 360.0 - 180.0  # noqa: E731
    return {"id": np.arange(len(a)), "east_m": a[:, 0], "north_m": a[:, 1], "theta1_deg": deg(a[:, 2]),
            "theta2_deg": deg(a[:, 3]), "interior_angle_deg": np.degrees(a[:, 4]),
            "glass_walls": a[:, 5].astype(int), "height_m": a[:, 6], "inward_en": a[:, 7:9]}


def count_visible_scans(corners: dict[str, np.ndarray], static: Scene, lidar_en: np.ndarray,
                        lidar_z_m: float) -> np.ndarray:
    """Per corner: number of scan positions within 60 m with an unobstructed line of sight to a point of the
    vertical edge 0.15 m outside the corner, 1.5 m above the lidar (the upper layers' height)."""
    from scipy.spatial import cKDTree

    target = np.column_stack([np.column_stack([corners["east_m"], corners["north_m"]]) - 0.15 * corners["inward_en"],
                              np.minimum(lidar_z_m + 1.5, corners["height_m"] - 0.5)])
    pairs = cKDTree(lidar_en).query_ball_point(target[:, :2], VISIBLE_RANGE_M)
    ci = np.repeat(np.arange(len(target)), [len(p) for p in pairs])
    si = np.concatenate([np.asarray(p, np.int64) for p in pairs]) if len(ci) else np.zeros(0, np.int64)
    counts = np.zeros(len(target), np.int64)
    for start in range(0, len(ci), 1_000_000):
        c, s = ci[start:start + 1_000_000], si[start:start + 1_000_000]
        origin = np.column_stack([lidar_en[s], np.full(len(s), lidar_z_m)])
        vec = target[c] - origin
        dist = np.linalg.norm(vec, axis=1)
        t_hit, _ = static.cast(origin, vec / dist[:, None])
        np.add.at(counts, c, (t_hit >= dist - 0.05).astype(np.int64))
    return counts


def city_description(city: City, origin: dict, epsg: int) -> dict:
    return {
        "origin": origin,
        "utm_epsg": epsg,
        "frame": "ENU metres about origin; road surface z=0, sidewalks z=0.15",
        "bounds_en": list(city.bounds_en),
        "road_half_width_m": {"east_west": city.hw_row_m, "north_south": city.hw_col_m},
        "lanes_per_direction": {"east_west": city.lanes_row, "north_south": city.lanes_col},
        "intersections_en": np.round(city.nodes_en, 3).tolist(),
        "buildings": [{"footprint_en": np.round(b.footprint_en, 3).tolist(), "height_m": round(b.height_m, 3),
                       "glass_walls": b.glass.astype(int).tolist(), "reflectance": round(b.reflectance, 4)}
                      for b in city.buildings],
        "trees": [{"east_m": round(t[0], 3), "north_m": round(t[1], 3), "trunk_height_m": round(t[2], 3),
                   "crown_radius_m": round(t[3], 3), "crown_half_height_m": round(t[4], 3)} for t in city.trees],
        "poles_en": np.round(city.poles, 3).tolist(),
        "parked_cars": [{"east_m": round(p[0], 3), "north_m": round(p[1], 3), "yaw_enu_rad": round(p[2], 5),
                         "length_m": round(p[3], 3), "width_m": round(p[4], 3)} for p in city.parked],
    }
