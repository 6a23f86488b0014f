"""Dated variants of a city: what changes between drives (``simulate --changes``).

Between drive ``from_drive - 1`` and drive ``from_drive`` three things happen to the city:
  - a building next to the driven loop is demolished (its lot stays empty);
  - a new building is built on vacant land across an outer street of the loop;
  - a crosswalk of a loop street is repainted ``CROSSWALK_SHIFT_M`` closer to its intersection.
Drives before ``from_drive`` see the city as generated, later ones the changed city. The truth of the change
(removed and added building corners, the crosswalk's old and new outline, changed marking pixels) goes to
``truth/changes.json``; ``truth/corners.csv`` stays the city as of drive 0 and ``truth/corners_after.csv`` is
the changed city's corners. Later drives' drive.yaml reference ``survey_changed/survey.las``, a survey of
the changed city (same route and noise stream as ``survey/``), so maps built from them see the new paint.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from stages.simulate.city import Building, City
from stages.simulate.markings import WHITE, Raster

SURVEY_DIR = "survey_changed"  # the changed city's survey cloud; drives that see the change reference it
CROSSWALK_SHIFT_M = -2.0  # along the street, towards its first intersection
NEW_BUILDING_M = (22.0, 14.0)  # frontage along the street, depth
REACH_M = 6.0  # a building "faces the loop" when a vertex is this close to the loop's sidewalk line


@dataclass(frozen=True)
class CityChanges:
    from_drive: int
    demolished: int  # index into the original city's buildings
    built: Building
    crosswalk_edge: tuple[tuple[int, int], tuple[int, int]]  # street edge (node a, node b), (row, col) nodes
    crosswalk_old_en: list[np.ndarray]  # stripe polygons before
    crosswalk_new_en: list[np.ndarray]  # stripe polygons after


def _loop_edges(loop: list[tuple[int, int]]) -> list[tuple[tuple[int, int], tuple[int, int]]]:
    return [(loop[k], loop[(k + 1) % len(loop)]) for k in range(len(loop))]


def _seg_dist(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = b - a
    t = np.clip(((p - a) @ d) / max(float(d @ d), 1e-12), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * d), axis=1)


def _edge_geometry(city: City, a: tuple[int, int], b: tuple[int, int]):
    """Street a->b as markings.py lays it out: start, unit tangent, left normal, length, half width, clearance."""
    pa, pb = city.nodes_en[a], city.nodes_en[b]
    length = float(np.linalg.norm(pb - pa))
    t = (pb - pa) / length
    hw = city.hw_row_m if a[0] == b[0] else city.hw_col_m
    hw_cross = city.hw_col_m if a[0] == b[0] else city.hw_row_m
    return pa, t, np.array([-t[1], t[0]]), length, hw, 1.25 * hw_cross + 1.0


def crosswalk_stripes(city: City, a: tuple[int, int], b: tuple[int, int], shift_m: float = 0.0) -> list[np.ndarray]:
    """ENU stripe polygons of the crosswalk at node a of street a-b (``generate_markings``' layout), shifted."""
    if (a, b) not in {(e[0], e[1]) for e in _street_keys(city)}:
        a, b = b, a
    pa, t, n, _, hw, c = _edge_geometry(city, a, b)
    s_cw = c + shift_m
    out = []
    for d in np.arange(-hw + 1.0, hw - 1.0, 1.0):
        rect = np.array([[s_cw, d], [s_cw + 4.0, d], [s_cw + 4.0, d + 0.5], [s_cw, d + 0.5]])
        out.append(pa + rect[:, :1] * t + rect[:, 1:2] * n)
    return out


def _street_keys(city: City):
    from stages.simulate.city import street_edges

    return street_edges(city)


def plan_changes(city: City, loop: list[tuple[int, int]], sidewalk_m: float, from_drive: int,
                 rng: np.random.Generator) -> CityChanges:
    """Pick what changes: the building with most vertices facing the loop, vacant land across an outer loop
    street, and a crosswalk of a loop street (marked streets only)."""
    edges = _loop_edges(loop)
    rows, cols = city.nodes_en.shape[0] - 1, city.nodes_en.shape[1] - 1
    score = np.zeros(len(city.buildings))
    for bi, bld in enumerate(city.buildings):
        for a, b in edges:
            hw = city.hw_row_m if a[0] == b[0] else city.hw_col_m
            near = _seg_dist(bld.footprint_en, city.nodes_en[a], city.nodes_en[b]) < hw + sidewalk_m + REACH_M
            score[bi] += near.sum()
    best = np.flatnonzero(score == score.max())
    demolished = int(best[rng.integers(len(best))])

    outer = [(a, b) for a, b in edges if (a[0] == b[0] and a[0] in (0, rows)) or (a[1] == b[1] and a[1] in (0, cols))]
    a, b = outer[rng.integers(len(outer))] if outer else edges[0]
    pa, t, n, length, hw, _ = _edge_geometry(city, a, b)
    centre = city.nodes_en.reshape(-1, 2).mean(axis=0)
    mid = pa + t * length / 2
    away = n if (mid - centre) @ n > 0 else -n
    front, depth = NEW_BUILDING_M
    s0 = length / 2 - front / 2 + rng.uniform(-3.0, 3.0)
    base = mid + (s0 - length / 2) * t + away * (hw + sidewalk_m)
    poly = np.array([base, base + front * t, base + front * t + depth * away, base + depth * away])
    if (poly[1, 0] - poly[0, 0]) * (poly[2, 1] - poly[0, 1]) - (poly[1, 1] - poly[0, 1]) * (
        poly[2, 0] - poly[0, 0]
    ) < 0:
        poly = poly[::-1].copy()  # counter-clockwise
    built = Building(poly, float(rng.uniform(15.0, 30.0)), np.zeros(4, bool), float(rng.uniform(0.2, 0.5)))

    marked = [(a, b) for a, b in edges if _edge_geometry(city, a, b)[3] - 2 * _edge_geometry(city, a, b)[5] > 17.0]
    cw = marked[rng.integers(len(marked))] if marked else edges[0]
    return CityChanges(from_drive, demolished, built, cw, crosswalk_stripes(city, *cw),
                       crosswalk_stripes(city, *cw, shift_m=CROSSWALK_SHIFT_M))


def changed_city(city: City, ch: CityChanges) -> City:
    buildings = [b for k, b in enumerate(city.buildings) if k != ch.demolished] + [ch.built]
    return replace(city, buildings=buildings)


def _fill(data: np.ndarray, raster: Raster, polys: list[np.ndarray], value: int) -> None:
    import cv2

    shift = 4
    for poly in polys:
        px = np.column_stack([(poly[:, 0] - raster.west_m) / raster.res_m - 0.5,
                              (raster.north_m - poly[:, 1]) / raster.res_m - 0.5])
        cv2.fillPoly(data, [np.round(px * (1 << shift)).astype(np.int32)], int(value), lineType=cv2.LINE_8, shift=shift)


def repainted(marks: Raster, ch: CityChanges) -> Raster:
    """The marking raster after the crosswalk moved: old stripes painted over, new ones painted."""
    data = marks.data.copy()
    _fill(data, marks, ch.crosswalk_old_en, 0)
    _fill(data, marks, ch.crosswalk_new_en, WHITE)
    return Raster(data, marks.west_m, marks.north_m, marks.res_m)


def _corner_rows(corners: dict[str, np.ndarray], idx: np.ndarray) -> list[dict]:
    return [{"id": int(corners["id"][k]), "east_m": round(float(corners["east_m"][k]), 4),
             "north_m": round(float(corners["north_m"][k]), 4), "theta1_deg": round(float(corners["theta1_deg"][k]), 4),
             "theta2_deg": round(float(corners["theta2_deg"][k]), 4)} for k in idx]


def changes_truth(ch: CityChanges, city: City, before: dict[str, np.ndarray], after: dict[str, np.ndarray],
                  marks_before: Raster, marks_after: Raster, tol_m: float = 0.01) -> dict:
    """``truth/changes.json``: corners of the before city with no corner of the after city within ``tol_m``
    (removed; ids of truth/corners.csv) and the reverse (added; ids of truth/corners_after.csv), plus the
    crosswalk's move and the marking pixels it changed."""
    from scipy.spatial import cKDTree

    en_b = np.column_stack([before["east_m"], before["north_m"]])
    en_a = np.column_stack([after["east_m"], after["north_m"]])
    removed = np.flatnonzero(np.isinf(cKDTree(en_a).query(en_b, distance_upper_bound=tol_m)[0]))
    added = np.flatnonzero(np.isinf(cKDTree(en_b).query(en_a, distance_upper_bound=tol_m)[0]))
    changed = (marks_before.data > 0) != (marks_after.data > 0)
    return {
        "frame": "ENU metres about the simulation's origin (simulation.json)",
        "from_drive": ch.from_drive,
        "drives_before": f"drive_0 .. drive_{ch.from_drive - 1} see the city of truth/corners.csv",
        "drives_after": f"drive_{ch.from_drive} and later see the city of truth/corners_after.csv",
        "buildings": {
            "demolished": {"index": ch.demolished, "footprint_en": _round(city.buildings[ch.demolished].footprint_en)},
            "built": {"footprint_en": _round(ch.built.footprint_en), "height_m": round(ch.built.height_m, 3)},
        },
        "corners": {
            "removed": _corner_rows(before, removed),
            "added": _corner_rows(after, added),
            "n_before": int(len(en_b)),
            "n_after": int(len(en_a)),
            "match_tolerance_m": tol_m,
        },
        "markings": [
            {
                "kind": "crosswalk_moved",
                "street": [list(ch.crosswalk_edge[0]), list(ch.crosswalk_edge[1])],
                "shift_m": CROSSWALK_SHIFT_M,
                "old_stripes_en": [_round(p) for p in ch.crosswalk_old_en],
                "new_stripes_en": [_round(p) for p in ch.crosswalk_new_en],
                "pixels_changed": int(changed.sum()),
                "resolution_m": marks_before.res_m,
            }
        ],
    }


def _round(a: np.ndarray) -> list:
    return np.round(np.asarray(a, float), 3).tolist()


def changed_world(city: City, loop: list[tuple[int, int]], sidewalk_m: float, marks: Raster, n_drives: int,
                  from_drive: int | None, rng_plan: np.random.Generator, rng_mesh: np.random.Generator):
    """(plan, changed city, its static scene, its building scene, its marking raster). ``rng_mesh`` must be a
    fresh generator of the same stream the original static scene was built from (same trees, cars, poles)."""
    from pipeline.errors import ConfigError
    from stages.simulate.mesh import Scene, build_building_soup, build_static_soup

    from_drive = n_drives - 1 if from_drive is None else int(from_drive)
    if not 1 <= from_drive <= n_drives - 1:
        raise ConfigError("simulate --changes", [f"the changed city must start at a drive 1..{n_drives - 1} so "
                                                 f"drives see it before and after; got from drive {from_drive} "
                                                 f"with {n_drives} drive(s) (hint: --drives 2 or more)"])
    plan = plan_changes(city, loop, sidewalk_m, from_drive, rng_plan)
    after = changed_city(city, plan)
    return (plan, after, Scene(build_static_soup(after, rng_mesh)), Scene(build_building_soup(after)),
            repainted(marks, plan))


def write_changes_truth(truth_dir, plan: CityChanges, city: City, after: City, marks: Raster,
                        marks_after: Raster) -> dict:
    """Write truth/changes.json and truth/corners_after.csv; return the changes document."""
    from pathlib import Path

    from stages.simulate import writers
    from stages.simulate.truth import building_corners

    truth_dir = Path(truth_dir)
    before, corners_after = building_corners(city), building_corners(after)
    header = ["id", "east_m", "north_m", "theta1_deg", "theta2_deg", "interior_angle_deg", "glass_walls", "height_m"]
    writers.write_csv(truth_dir / "corners_after.csv", header, [corners_after[h] for h in header],
                      ["%d", "%.4f", "%.4f", "%.4f", "%.4f", "%.4f", "%d", "%.3f"])
    doc = changes_truth(plan, city, before, corners_after, marks, marks_after)
    writers.write_json(truth_dir / "changes.json", doc)
    return doc
