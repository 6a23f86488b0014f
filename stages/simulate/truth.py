"""Ground truth derived from the city: vertical corners of the building footprints, their visibility from a
drive's scans, and a JSON description of the city."""
from __future__ import annotations

import numpy as np

from stages.common.geometry import wrap_angle_rad
from stages.simulate.city import City
from stages.simulate.corner_shapes import SHAPE_NAMES
from stages.simulate.geom2d import point_in_polygon, point_segment_distance_m, polygon_corners
from stages.simulate.mesh import Scene

VISIBLE_RANGE_M = 60.0


def building_corners(city: City) -> dict[str, np.ndarray]:
    """One row per footprint vertex: id, east, north, theta1/theta2 (deg, ENU ccw from east, along the two
    walls away from the corner), interior angle (deg), glass walls (0-2), height, bisector (unit, inward), and
    the corner's shape (0 sharp, 1 rounded, 2 chamfered; the vertex is then the walls' intersection, outside
    the built outline) with its size (arc radius or cut length, m)."""
    rows, shape, size = [], [], []
    for b in city.buildings:
        n = len(b.footprint_en)
        kind, radius = getattr(b, "corner_shape", None), getattr(b, "shape_size_m", None)  # None: all sharp
        shape.append(np.zeros(n, int) if kind is None else np.asarray(kind, int))
        size.append(np.zeros(n) if radius is None else np.asarray(radius, float))
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
            "glass_walls": a[:, 5].astype(int), "height_m": a[:, 6], "inward_en": a[:, 7:9],
            "corner_shape": np.concatenate(shape) if shape else np.zeros(0, int),
            "shape_size_m": np.concatenate(size) if size else np.zeros(0)}


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


def union_corner_walls(footprints_en: list[np.ndarray], corners_en: np.ndarray, theta_rad: np.ndarray, *,
                       glass: list[np.ndarray] | None = None, owner: np.ndarray | None = None,
                       radius_m: float = 0.5, n_dirs: int = 720, snap_deg: float = 5.0,
                       straight_deg: float = 20.0
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The corners as the union of the footprints shows them. Where buildings touch (a shared party wall), a
    footprint vertex's own walls are not what a sensor sees: one may be hidden inside the neighbour and the
    neighbour's wall continue past the vertex. Around each vertex, occupancy (inside any footprint) is
    sampled on a circle of ``radius_m``; with exactly two occupied/free transitions the walls are the
    transition directions (snapped to the direction of a footprint edge passing within ``radius_m / 2``,
    within ``snap_deg``), and the inward direction is the occupied sector's mean. Returns theta (K,2) rad,
    inward (K,2) unit, and not_corner (K,) bool: the vertex lies inside the union, or its union walls are
    within ``straight_deg`` of a straight line (two facades continuing each other with a small step), or a
    wall is not straight within ``radius_m`` (a step shorter than that: no line for an extractor).
    Vertices with more than two transitions keep their own walls. With ``glass`` (per building, per wall k from
    vertex k to k+1) and ``owner`` (building of each corner), a neighbouring building whose glass wall passes
    the vertex does not hide anything there: the sensor sees through it (the simulator's glass is transparent)."""
    polys = [np.asarray(f, float) for f in footprints_en]
    lo = np.array([p.min(axis=0) for p in polys]) - radius_m
    hi = np.array([p.max(axis=0) for p in polys]) + radius_m
    phi = (np.arange(n_dirs) + 0.5) * 2 * np.pi / n_dirs
    ring = radius_m * np.column_stack([np.cos(phi), np.sin(phi)])
    theta = np.array(theta_rad, float).reshape(-1, 2).copy()
    inward = np.zeros((len(theta), 2))
    hidden = np.zeros(len(theta), bool)
    for c, v in enumerate(np.asarray(corners_en, float)):
        near = np.flatnonzero(np.all((lo <= v) & (v <= hi), axis=1))
        if glass is not None and owner is not None:
            near = [b for b in near if b == owner[c] or not _glass_wall_near(polys[b], glass[b], v, radius_m)]
        occ = np.zeros(n_dirs, bool)
        edge_dirs = list(theta[c])
        for b in near:
            occ |= point_in_polygon(v + ring, polys[b])
            q = polys[b]
            for a, e in zip(q, np.roll(q, -1, axis=0)):
                if point_segment_distance_m(v, a, e) < radius_m / 2:
                    ang = np.arctan2(e[1] - a[1], e[0] - a[0])
                    edge_dirs += [ang, ang + np.pi]
        if not occ.any() or occ.all():
            hidden[c] = occ.all()
            continue
        trans = np.flatnonzero(occ != np.roll(occ, 1))
        mean = np.array([np.cos(phi[occ]).sum(), np.sin(phi[occ]).sum()])
        inward[c] = mean / max(np.linalg.norm(mean), 1e-12)
        if len(trans) != 2:
            continue
        walls = phi[trans] - np.pi / n_dirs  # the boundary between sample j-1 and j
        cand = np.asarray(edge_dirs)
        snapped = 0
        for w in range(2):
            diff = np.abs(wrap_angle_rad(cand - walls[w]))
            if diff.min() <= np.radians(snap_deg):
                walls[w] = cand[np.argmin(diff)]
                snapped += 1
        own = theta[c]
        d_keep = np.abs(wrap_angle_rad(walls - own)).sum()
        d_swap = np.abs(wrap_angle_rad(walls[::-1] - own)).sum()
        theta[c] = wrap_angle_rad(walls if d_keep <= d_swap else walls[::-1])
        bend = abs((walls[0] - walls[1]) % (2 * np.pi) - np.pi)
        hidden[c] = bend < np.radians(straight_deg) or snapped < 2
    return theta, inward, hidden


def _glass_wall_near(poly: np.ndarray, glass: np.ndarray, v: np.ndarray, radius_m: float) -> bool:
    return any(point_segment_distance_m(v, poly[k], poly[(k + 1) % len(poly)]) < radius_m
               for k in np.flatnonzero(np.asarray(glass, bool)))


def count_corner_views(corners: dict[str, np.ndarray], static: Scene, lidar_en: np.ndarray, lidar_z_m: float, *,
                       min_range_m: float = 8.0, max_range_m: float = VISIBLE_RANGE_M,
                       along_m: tuple[float, ...] = (0.3, 1.0), outside_m: float = 0.05) -> np.ndarray:
    """Per corner: number of scan positions that see it *as a corner* (Im et al. extract a corner from two
    walls): both walls opaque (a glass wall returns nothing), the sensor in front of both wall faces, within
    [min_range_m, max_range_m], and an unobstructed line of sight to points ``along_m`` along each wall
    (``outside_m`` in front of it) at the upper layers' height. ``count_visible_scans`` counts a line of
    sight to the corner point alone, which a scan looking along one wall also has."""
    from scipy.spatial import cKDTree

    en = np.column_stack([corners["east_m"], corners["north_m"]])
    th = np.radians(np.column_stack([corners["theta1_deg"], corners["theta2_deg"]]))
    inward = np.asarray(corners["inward_en"], float)
    z_t = np.minimum(lidar_z_m + 1.5, np.asarray(corners["height_m"], float) - 0.5)
    counts = np.zeros(len(en), np.int64)
    tree = cKDTree(lidar_en)
    for c in np.flatnonzero(np.asarray(corners["glass_walls"]) == 0):
        scans = np.asarray(tree.query_ball_point(en[c], max_range_m), np.int64)
        if not len(scans):
            continue
        view = lidar_en[scans] - en[c]
        rng = np.linalg.norm(view, axis=1)
        ok = rng >= min_range_m
        targets = []
        for t in th[c]:
            d = np.array([np.cos(t), np.sin(t)])
            n = np.array([-d[1], d[0]])
            n = -n if n @ inward[c] > 0 else n  # outward normal of this wall
            ok &= view @ n > 0
            targets += [en[c] + a * d + outside_m * n for a in along_m]
        scans = scans[ok]
        if not len(scans):
            continue
        origin = np.column_stack([lidar_en[scans], np.full(len(scans), lidar_z_m)])
        clear = np.ones(len(scans), bool)
        for tgt in targets:
            vec = np.r_[tgt, z_t[c]] - origin
            dist = np.linalg.norm(vec, axis=1)
            t_hit, _ = static.cast(origin, vec / dist[:, None])
            clear &= t_hit >= dist - 0.05
        counts[c] = int(clear.sum())
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
                       "glass_walls": b.glass.astype(int).tolist(), "reflectance": round(b.reflectance, 4),
                       "outline_en": np.round(b.walls()[0], 3).tolist(),
                       "corner_shape": [SHAPE_NAMES[k] for k in (b.corner_shape if b.corner_shape is not None
                                                                 else np.zeros(len(b.footprint_en), int))]}
                      for b in city.buildings],
        "furniture": [{"kind": f.kind, "height_m": round(f.height_m, 3),
                       "boxes_en": np.round(f.boxes, 4).tolist()} for f in city.furniture],
        "trees": [{"east_m": round(t[0], 3), "north_m": round(t[1], 3), "trunk_height_m": round(t[2], 3),
                   "crown_radius_m": round(t[3], 3), "crown_half_height_m": round(t[4], 3)} for t in city.trees],
        "poles_en": np.round(city.poles, 3).tolist(),
        "parked_cars": [{"east_m": round(p[0], 3), "north_m": round(p[1], 3), "yaw_enu_rad": round(p[2], 5),
                         "length_m": round(p[3], 3), "width_m": round(p[4], 3),
                         **({} if city.parked_top_m is None else {"height_m": round(float(city.parked_top_m[k]), 3)})}
                        for k, p in enumerate(city.parked)],
    }
