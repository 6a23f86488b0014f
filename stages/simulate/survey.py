"""The survey (mobile-mapping) cloud: dense, calibrated points on the road and sidewalks along the mapped
streets, centimetre noise, nothing under parked cars, inside buildings, tree trunks, poles or street furniture.
"""
from __future__ import annotations

import numpy as np

from stages.simulate.city import CURB_H_M, City
from stages.simulate.markings import REFLECTANCE, Raster

SIDEWALK_REFLECTANCE = 0.28


def _fill(mask: np.ndarray, polys: list[np.ndarray], west: float, north: float, res: float) -> None:
    import cv2

    shift = 4
    pts = [np.round(np.column_stack([(p[:, 0] - west) / res - 0.5, (north - p[:, 1]) / res - 0.5])
                    * (1 << shift)).astype(np.int32) for p in polys]
    if pts:
        cv2.fillPoly(mask, pts, 1, shift=shift)


def _rect_polys(boxes: np.ndarray) -> list[np.ndarray]:
    """(K, 5) east, north, yaw, length, width -> rectangle polygons."""
    out = []
    for e, n, yaw, length, width in boxes:
        c, s = np.cos(yaw), np.sin(yaw)
        loc = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * [length / 2, width / 2]
        out.append(np.column_stack([e + c * loc[:, 0] - s * loc[:, 1], n + s * loc[:, 0] + c * loc[:, 1]]))
    return out


def generate_survey(city: City, route_en: np.ndarray, corridor_m: float, markings: Raster, albedo: Raster,
                    rng: np.random.Generator, spacing_m: float = 0.095) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) ENU and calibrated reflectance (N,) within ``corridor_m`` of the route polyline (or of any of a
    list of them: ``route: districts`` surveys every drive's route)."""
    import cv2

    west, south, east, north = city.bounds_en
    res = spacing_m
    shape = (int(np.ceil((north - south) / res)), int(np.ceil((east - west) / res)))
    corridor = np.zeros(shape, np.uint8)
    routes = list(route_en) if isinstance(route_en, (list, tuple)) else [route_en]  # several drives' routes
    px = [np.round(np.column_stack([(r[:, 0] - west) / res, (north - r[:, 1]) / res]) * 16).astype(np.int32)
          for r in routes]
    cv2.polylines(corridor, px, False, 1, thickness=int(2 * corridor_m / res), shift=4)
    sidewalk = np.zeros(shape, np.uint8)
    _fill(sidewalk, city.curbs_en, west, north, res)
    blocked = np.zeros(shape, np.uint8)
    _fill(blocked, [b.walls()[0] for b in city.buildings], west, north, res)
    _fill(blocked, _rect_polys(city.parked), west, north, res)
    furniture = [item.boxes[:, :5] for item in city.furniture]
    if furniture:
        _fill(blocked, _rect_polys(np.concatenate(furniture)), west, north, res)
    posts = np.concatenate([city.trees[:, :2], city.poles]) if len(city.trees) else city.poles
    _fill(blocked, _rect_polys(np.column_stack([posts, np.zeros(len(posts)), np.full((len(posts), 2), 0.35)])),
          west, north, res)
    rows, cols = np.nonzero(corridor.astype(bool) & ~blocked.astype(bool))
    n = len(rows)
    e = west + (cols + 0.5 + rng.uniform(-0.45, 0.45, n)) * res
    nn = north - (rows + 0.5 + rng.uniform(-0.45, 0.45, n)) * res
    on_sidewalk = sidewalk[rows, cols].astype(bool)
    z = np.where(on_sidewalk, CURB_H_M, 0.0) + rng.normal(0, 0.01, n)
    refl = albedo.lookup(e, nn).astype(np.float64)
    paint = markings.lookup(e, nn)
    for cls, value in REFLECTANCE.items():
        refl = np.where(paint == cls, value, refl)
    refl = np.where(on_sidewalk, SIDEWALK_REFLECTANCE, refl) * rng.lognormal(0, 0.05, n)
    return np.column_stack([e, nn, z]), np.clip(refl, 0, 1)
