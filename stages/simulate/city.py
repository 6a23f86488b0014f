"""The synthetic city as plain numpy records: a street grid with kinked (non-orthogonal) streets, curbs and
sidewalks, building footprints (rectangles, L-shapes, chamfered corners, recessed facades) with glass walls,
roadside trees, poles and parked cars. Road markings are in ``markings.py``.

Frame: the map's ENU (east, north, up) metres; the road surface is z = 0, sidewalks are 0.15 m higher.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from stages.simulate.geom2d import bilinear, offset_polygon_inward, signed_area_m2
from stages.simulate.presets import Preset

LANE_W_M = 3.5
SHOULDER_M = 2.0  # parking strip between the outer lane and the curb
CURB_H_M = 0.15


@dataclass(frozen=True)
class Building:
    footprint_en: np.ndarray  # (n, 2) counter-clockwise; vertices are the walls' intersections
    height_m: float
    glass: np.ndarray  # (n,) bool, wall k joins vertex k and k+1
    reflectance: float
    outline_en: np.ndarray | None = None  # (m, 2) ccw with rounded/chamfered corners (corner_shapes.py)
    outline_glass: np.ndarray | None = None  # (m,) bool per outline segment
    corner_shape: np.ndarray | None = None  # (n,) 0 sharp, 1 rounded, 2 chamfered
    shape_size_m: np.ndarray | None = None  # (n,) arc radius or cut length along each wall (0 when sharp)
    facade: object | None = None  # facades.FacadeDetail: windows, shop fronts, balconies, hedges (None: flat walls)

    def walls(self) -> tuple[np.ndarray, np.ndarray]:
        """The outline as built (rounded/chamfered where shaped) and its per-segment glass flags."""
        if self.outline_en is None:
            return self.footprint_en, self.glass
        return self.outline_en, self.outline_glass


@dataclass
class City:
    nodes_en: np.ndarray  # (rows+1, cols+1, 2) street intersections
    hw_row_m: float  # road half-width (kerb to centreline) of east-west streets
    hw_col_m: float
    lanes_row: int
    lanes_col: int
    curbs_en: list[np.ndarray]  # one (4, 2) kerb polygon per block
    buildings: list[Building]
    trees: np.ndarray  # (T, 5) east, north, trunk_h_m, crown_radius_m, crown_half_height_m
    poles: np.ndarray  # (P, 2)
    parked: np.ndarray  # (C, 5) east, north, yaw_enu_rad, length_m, width_m
    congested: set = field(default_factory=set)  # street edges with queues: ((j, i), (j2, i2))
    furniture: list = field(default_factory=list)  # furniture.Furniture: shelters, kiosks, fences
    parked_top_m: np.ndarray | None = None  # (C,) roof height of each parked vehicle (None: all cars, 1.5 m)

    @property
    def bounds_en(self) -> tuple[float, float, float, float]:
        lo = self.nodes_en.reshape(-1, 2).min(0) - 40.0
        hi = self.nodes_en.reshape(-1, 2).max(0) + 40.0
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def street_edges(city: City) -> list[tuple[tuple[int, int], tuple[int, int], float, int]]:
    """Every street segment between adjacent intersections: (node_a, node_b, half_width_m, lanes_per_dir)."""
    rows, cols = city.nodes_en.shape[0] - 1, city.nodes_en.shape[1] - 1
    edges = [((j, i), (j, i + 1), city.hw_row_m, city.lanes_row) for j in range(rows + 1) for i in range(cols)]
    edges += [((j, i), (j + 1, i), city.hw_col_m, city.lanes_col) for j in range(rows) for i in range(cols + 1)]
    return edges


def generate_city(preset: Preset, rng: np.random.Generator) -> City:
    nodes = _generate_nodes(preset, rng)
    hw_row = preset.lanes_row * LANE_W_M + SHOULDER_M
    hw_col = preset.lanes_col * LANE_W_M + SHOULDER_M
    curbs, buildings = [], []
    for j in range(preset.n_rows):
        for i in range(preset.n_cols):
            quad = np.array([nodes[j, i], nodes[j, i + 1], nodes[j + 1, i + 1], nodes[j + 1, i]])
            curb = offset_polygon_inward(quad, np.array([hw_row, hw_col, hw_row, hw_col]))
            curbs.append(curb)
            zone = offset_polygon_inward(curb, preset.sidewalk_m)
            buildings += _generate_block_buildings(zone, preset, rng)
    trees, poles, parked = _generate_street_furniture(curbs, preset, rng)
    city = City(nodes, hw_row, hw_col, preset.lanes_row, preset.lanes_col, curbs, buildings, trees, poles, parked)
    edges = street_edges(city)
    n_cong = int(round(preset.congested_street_share * len(edges)))
    if n_cong:
        pick = rng.choice(len(edges), size=n_cong, replace=False)
        city.congested = {(edges[k][0], edges[k][1]) for k in sorted(pick)}
    return city


def _generate_nodes(preset: Preset, rng: np.random.Generator) -> np.ndarray:
    xs = np.concatenate([[0.0], np.cumsum(preset.block_w_m * rng.uniform(0.85, 1.15, preset.n_cols))])
    ys = np.concatenate([[0.0], np.cumsum(preset.block_h_m * rng.uniform(0.85, 1.15, preset.n_rows))])
    xs -= xs.mean()
    ys -= ys.mean()
    gx, gy = np.meshgrid(xs, ys)  # (rows+1, cols+1)
    col_jitter = rng.random(preset.n_cols + 1) < preset.jitter_share
    row_jitter = rng.random(preset.n_rows + 1) < preset.jitter_share * 0.5
    dx = rng.uniform(-preset.jitter_m, preset.jitter_m, gx.shape) * col_jitter[None, :]
    dy = rng.uniform(-0.5, 0.5, gy.shape) * preset.jitter_m * row_jitter[:, None]
    return np.stack([gx + dx, gy + dy], axis=-1)


def _shape_unit(kind: str, rng: np.random.Generator) -> np.ndarray:
    """A footprint in the lot's unit square, counter-clockwise, front (street) side at v = 0."""
    if kind == "L":
        a, b = rng.uniform(0.35, 0.65, 2)
        return np.array([[0, 0], [1, 0], [1, a], [b, a], [b, 1], [0, 1]], float)
    if kind == "chamfer":
        c = rng.uniform(0.15, 0.3)
        return np.array([[c, 0], [1, 0], [1, 1], [0, 1], [0, c]], float)
    if kind == "recess":
        a = rng.uniform(0.15, 0.4)
        b = a + rng.uniform(0.2, 0.4)
        r = rng.uniform(0.06, 0.15)
        return np.array([[0, 0], [a, 0], [a, r], [b, r], [b, 0], [1, 0], [1, 1], [0, 1]], float)
    return np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)


def _generate_block_buildings(zone: np.ndarray, preset: Preset, rng: np.random.Generator) -> list[Building]:
    len_u = 0.5 * (np.linalg.norm(zone[1] - zone[0]) + np.linalg.norm(zone[2] - zone[3]))
    len_v = 0.5 * (np.linalg.norm(zone[3] - zone[0]) + np.linalg.norm(zone[2] - zone[1]))
    if len_u < 8 or len_v < 8:
        return []
    n_u = max(1, int(round(len_u / rng.uniform(24.0, 40.0))))
    n_v = 2 if len_v > 50 else 1
    cuts = np.linspace(0, 1, n_u + 1)
    out = []
    for iu in range(n_u):
        for iv in range(n_v):
            gap = rng.uniform(1.5, 5.0) / len_u / 2
            u0, u1 = cuts[iu] + (gap if iu else 0), cuts[iu + 1] - (gap if iu < n_u - 1 else 0)
            depth = min(1.0, rng.uniform(18.0, 32.0) / (len_v / n_v)) / n_v
            v0, v1 = (0.0, depth) if iv == 0 else (1.0 - depth, 1.0)
            kind = rng.choice(["rect", "L", "chamfer", "recess"], p=[0.35, 0.25, 0.2, 0.2])
            unit = _shape_unit(str(kind), rng)
            if rng.random() < 0.5:
                unit[:, 0] = 1 - unit[:, 0]  # mirror left/right
            if iv == 1:
                unit[:, 1] = 1 - unit[:, 1]  # the back row faces the far street
            uv = np.column_stack([u0 + unit[:, 0] * (u1 - u0), v0 + unit[:, 1] * (v1 - v0)])
            poly = bilinear(zone, uv)
            if signed_area_m2(poly) < 0:
                poly = poly[::-1].copy()
            if abs(signed_area_m2(poly)) < 40.0:
                continue
            n = len(poly)
            glass = np.zeros(n, bool)
            if rng.random() < preset.glass_building_share:
                glass = rng.random(n) < 0.6
                glass[rng.integers(n)] = True
            lo, hi = preset.height_range_m
            out.append(Building(poly, float(rng.uniform(lo, hi)), glass, float(rng.uniform(0.15, 0.6))))
    return out


def _generate_street_furniture(curbs: list[np.ndarray], preset: Preset, rng: np.random.Generator):
    trees, poles, parked = [], [], []
    for curb in curbs:
        for k in range(4):
            a, b = curb[k], curb[(k + 1) % 4]
            length = float(np.linalg.norm(b - a))
            t = (b - a) / length
            inward = np.array([-t[1], t[0]])
            if rng.random() < preset.tree_side_share and length > 20:
                s = np.arange(8.0, length - 8.0, rng.uniform(8.0, 11.0))
                s = s + rng.uniform(-0.8, 0.8, len(s))
                for si in s:
                    p = a + t * si + inward * 1.2
                    trees.append([p[0], p[1], rng.uniform(2.4, 3.4), rng.uniform(1.8, 2.8), rng.uniform(1.6, 2.4)])
            for si in np.arange(rng.uniform(5.0, 15.0), length - 5.0, rng.uniform(28.0, 40.0)):
                poles.append(a + t * si + inward * 0.5)
            if rng.random() < preset.parked_side_share and length > 30:
                yaw = float(np.arctan2(t[1], t[0]))
                for si in np.arange(12.0, length - 12.0, 7.5):
                    if rng.random() < 0.7:
                        p = a + t * (si + rng.uniform(-0.6, 0.6)) - inward * 1.05
                        parked.append([p[0], p[1], yaw + rng.normal(0, 0.02), rng.uniform(4.2, 4.9),
                                       rng.uniform(1.75, 1.9)])
    trees_a = np.array(trees, float).reshape(-1, 5)
    poles_a = np.array(poles, float).reshape(-1, 2)
    if len(trees_a) and len(poles_a):  # keep poles out of the tree trunks and crowns
        d = np.linalg.norm(poles_a[:, None] - trees_a[None, :, :2], axis=-1).min(axis=1)
        poles_a = poles_a[d > 3.0]
    return trees_a, poles_a, np.array(parked, float).reshape(-1, 5)
