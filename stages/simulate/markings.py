"""Painted road markings (solid and dashed lane lines, centre lines, stop lines, crosswalks, arrows) as ENU
polygons, their 0.1 m raster, and a spatially varying asphalt albedo. Vehicles keep to the right.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.simulate.city import LANE_W_M, City, street_edges

WHITE, YELLOW = 1, 2
REFLECTANCE = {WHITE: 0.78, YELLOW: 0.55}


@dataclass(frozen=True)
class Raster:
    """A north-up raster: pixel (row, col) centre = (west + (col + 0.5) res, north - (row + 0.5) res)."""

    data: np.ndarray
    west_m: float
    north_m: float
    res_m: float

    def lookup(self, east_m: np.ndarray, north_m: np.ndarray) -> np.ndarray:
        col = np.floor((east_m - self.west_m) / self.res_m).astype(np.int64)
        row = np.floor((self.north_m - north_m) / self.res_m).astype(np.int64)
        ok = (row >= 0) & (row < self.data.shape[0]) & (col >= 0) & (col < self.data.shape[1])
        out = np.zeros(len(east_m), self.data.dtype)
        out[ok] = self.data[row[ok], col[ok]]
        return out


def _rect(s0: float, s1: float, d0: float, d1: float) -> np.ndarray:
    return np.array([[s0, d0], [s1, d0], [s1, d1], [s0, d1]])


def _arrow(s_tip: float, d: float, sign: float) -> np.ndarray:
    """A straight-ahead arrow 5 m long pointing towards increasing s (sign=+1) or decreasing s (sign=-1)."""
    pts = np.array([[-5.0, -0.1], [-1.5, -0.1], [-1.5, -0.35], [0.0, 0.0], [-1.5, 0.35], [-1.5, 0.1], [-5.0, 0.1]])
    return np.column_stack([s_tip + sign * pts[:, 0], d + pts[:, 1]])


def generate_markings(city: City) -> list[tuple[int, np.ndarray]]:
    """(class, (n, 2) ENU polygon) for every painted element."""
    out: list[tuple[int, np.ndarray]] = []
    for a, b, hw, lanes in street_edges(city):
        pa, pb = city.nodes_en[a], city.nodes_en[b]
        length = float(np.linalg.norm(pb - pa))
        t = (pb - pa) / length
        n = np.array([-t[1], t[0]])  # left of travel from a to b
        hw_cross = city.hw_col_m if a[0] == b[0] else city.hw_row_m
        c = 1.25 * hw_cross + 1.0  # intersection clearance
        s0, s1 = c + 5.5, length - c - 5.5
        if s1 - s0 < 6:
            continue
        local: list[tuple[int, np.ndarray]] = [(YELLOW, _rect(s0, s1, 0.1, 0.25)), (YELLOW, _rect(s0, s1, -0.25, -0.1))]
        edge_d = lanes * LANE_W_M
        for side in (-1.0, 1.0):
            local.append((WHITE, _rect(s0, s1, side * edge_d - 0.075, side * edge_d + 0.075)))
            for k in range(1, lanes):
                for ds in np.arange(s0, s1 - 3.0, 8.0):
                    local.append((WHITE, _rect(ds, ds + 3.0, side * k * LANE_W_M - 0.075, side * k * LANE_W_M + 0.075)))
        for s_cw in (c, length - c - 4.0):  # crosswalks, zebra stripes parallel to the street
            for d in np.arange(-hw + 1.0, hw - 1.0, 1.0):
                local.append((WHITE, _rect(s_cw, s_cw + 4.0, d, d + 0.5)))
        # approach to node b: right-hand traffic runs at d < 0; approach to node a at d > 0
        local.append((WHITE, _rect(length - c - 4.95, length - c - 4.5, -edge_d, -0.3)))
        local.append((WHITE, _rect(c + 4.5, c + 4.95, 0.3, edge_d)))
        if s1 - s0 > 25:
            for k in range(lanes):
                dk = (k + 0.5) * LANE_W_M
                local.append((WHITE, _arrow(length - c - 12.0, -dk, 1.0)))
                local.append((WHITE, _arrow(c + 12.0, dk, -1.0)))
        for cls, poly in local:
            out.append((cls, pa + poly[:, :1] * t + poly[:, 1:2] * n))
    return out


def rasterize_markings(markings: list[tuple[int, np.ndarray]], bounds_en, res_m: float = 0.1) -> Raster:
    import cv2

    west, south, east, north = bounds_en
    width, height = int(np.ceil((east - west) / res_m)), int(np.ceil((north - south) / res_m))
    data = np.zeros((height, width), np.uint8)
    shift = 4
    for cls, poly in markings:
        px = np.column_stack([(poly[:, 0] - west) / res_m - 0.5, (north - poly[:, 1]) / res_m - 0.5])
        cv2.fillPoly(data, [np.round(px * (1 << shift)).astype(np.int32)], int(cls), lineType=cv2.LINE_8, shift=shift)
    return Raster(data, west, north, res_m)


def asphalt_albedo(bounds_en, rng: np.random.Generator, res_m: float = 2.0) -> Raster:
    """Asphalt reflectance 0.05-0.16 with patches (repairs, wear) at tens of metres."""
    from scipy.ndimage import gaussian_filter

    west, south, east, north = bounds_en
    shape = (int(np.ceil((north - south) / res_m)), int(np.ceil((east - west) / res_m)))
    field_ = gaussian_filter(rng.normal(size=shape), sigma=4.0)
    field_ /= field_.std() + 1e-12
    patches = gaussian_filter((rng.random(shape) < 0.01).astype(float), sigma=3.0)
    patches = np.clip(patches / (patches.max() + 1e-12) * 3, 0, 1)
    albedo = np.clip(0.10 + 0.018 * field_ + 0.04 * patches, 0.05, 0.16).astype(np.float32)
    return Raster(albedo, west, north, res_m)


def marking_truth_features(city: City) -> list[tuple[str, np.ndarray]]:
    """Typed truth geometry of ``generate_markings``' paint, ENU: (type, coordinates) with type one of
    lane_solid / lane_dashed / stop_line (centrelines, (2, 2); the double centre line is one line along its
    middle, Lanelet2's solid_solid), crosswalk (outer rectangle of its stripes) and
    arrow (outline). A dashed line runs from its first dash's start to its last dash's end."""
    out: list[tuple[str, np.ndarray]] = []
    for a, b, hw, lanes in street_edges(city):
        pa, pb = city.nodes_en[a], city.nodes_en[b]
        length = float(np.linalg.norm(pb - pa))
        t = (pb - pa) / length
        n = np.array([-t[1], t[0]])
        hw_cross = city.hw_col_m if a[0] == b[0] else city.hw_row_m
        c = 1.25 * hw_cross + 1.0
        s0, s1 = c + 5.5, length - c - 5.5
        if s1 - s0 < 6:
            continue
        local: list[tuple[str, np.ndarray]] = [("lane_solid", np.array([[s0, 0.0], [s1, 0.0]]))]  # double line
        edge_d = lanes * LANE_W_M
        for side in (-1.0, 1.0):
            local.append(("lane_solid", np.array([[s0, side * edge_d], [s1, side * edge_d]])))
            for k in range(1, lanes):
                starts = np.arange(s0, s1 - 3.0, 8.0)
                local.append(("lane_dashed", np.array([[starts[0], side * k * LANE_W_M],
                                                       [starts[-1] + 3.0, side * k * LANE_W_M]])))
        for s_cw in (c, length - c - 4.0):
            d = np.arange(-hw + 1.0, hw - 1.0, 1.0)
            local.append(("crosswalk", _rect(s_cw, s_cw + 4.0, float(d[0]), float(d[-1]) + 0.5)))
        local.append(("stop_line", np.array([[length - c - 4.725, -edge_d], [length - c - 4.725, -0.3]])))
        local.append(("stop_line", np.array([[c + 4.725, 0.3], [c + 4.725, edge_d]])))
        if s1 - s0 > 25:
            for k in range(lanes):
                dk = (k + 0.5) * LANE_W_M
                local.append(("arrow", _arrow(length - c - 12.0, -dk, 1.0)))
                local.append(("arrow", _arrow(c + 12.0, dk, -1.0)))
        for kind, geom in local:
            out.append((kind, pa + geom[:, :1] * t + geom[:, 1:2] * n))
    return out


def city_from_description(doc: dict) -> City:
    """The street layout of a ``truth/city.json`` (intersections, half widths, lanes) as a City, enough for
    ``generate_markings`` / ``marking_truth_features`` (no buildings, trees, poles or cars)."""
    return City(nodes_en=np.asarray(doc["intersections_en"], float),
                hw_row_m=float(doc["road_half_width_m"]["east_west"]),
                hw_col_m=float(doc["road_half_width_m"]["north_south"]),
                lanes_row=int(doc["lanes_per_direction"]["east_west"]),
                lanes_col=int(doc["lanes_per_direction"]["north_south"]),
                curbs_en=[], buildings=[], trees=np.zeros((0, 5)), poles=np.zeros((0, 2)), parked=np.zeros((0, 5)))
