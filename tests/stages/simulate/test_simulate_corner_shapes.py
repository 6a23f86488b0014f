"""Rounded and chamfered building corners: exact outline geometry, and rays cast at a shaped corner of the
tiny city hit the arc / cut where geometry says, while truth keeps the walls' intersection."""
from __future__ import annotations

import csv

import numpy as np
import pytest

from stages.simulate.corner_shapes import CHAMFERED, ROUNDED, SHARP, shaped_outline
from stages.simulate.geom2d import point_in_polygon, signed_area_m2

SQUARE = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)


def test_rounded_square_has_the_area_and_radius_of_its_arcs():
    r = 2.0
    outline, glass = shaped_outline(SQUARE, np.zeros(4, bool), np.full(4, ROUNDED), np.full(4, r))
    assert signed_area_m2(outline) == pytest.approx(100 - (4 - np.pi) * r * r, abs=0.05)
    centre = np.array([10 - r, 10 - r])
    arc = outline[(outline[:, 0] > 10 - r + 1e-9) & (outline[:, 1] > 10 - r + 1e-9)]
    assert len(arc) >= 5 and np.allclose(np.linalg.norm(arc - centre, axis=1), r)
    # the sharp vertex (the walls' intersection) lies outside the built outline, r(sqrt2 - 1) from the arc
    assert not point_in_polygon(np.array([[10.0 - 1e-3, 10.0 - 1e-3]]), outline)[0]
    assert np.min(np.linalg.norm(outline - [10, 10], axis=1)) == pytest.approx(r * (np.sqrt(2) - 1), abs=0.03)  # facets
    assert not glass.any()


def test_chamfer_cuts_a_triangle_and_glass_needs_both_walls():
    c = 1.5
    glass_walls = np.array([True, True, False, False])  # walls 0 (bottom) and 1 (right) are glass
    shape = np.array([SHARP, CHAMFERED, CHAMFERED, SHARP])
    outline, glass = shaped_outline(SQUARE, glass_walls, shape, np.full(4, c))
    assert len(outline) == 6
    assert signed_area_m2(outline) == pytest.approx(100 - 2 * c * c / 2)
    # segments: v0->cut1a (wall 0), cut1a->cut1b (both glass), cut1b->cut2a (wall 1), cut2a->cut2b, ...
    assert glass.tolist() == [True, True, True, False, False, False]


def test_rays_hit_the_arc_or_cut_of_a_shaped_corner(tmp_path):
    from stages.simulate.core import build_city, component_rng
    from stages.simulate.mesh import Scene, build_static_soup
    from stages.simulate.presets import get_preset
    from stages.simulate.truth import building_corners

    p = get_preset("tiny", rounded_corner_share=0.4, chamfered_corner_share=0.4)
    city = build_city(p, 7)
    corners = building_corners(city)
    scene = Scene(build_static_soup(city, component_rng(7, "mesh")))
    checked = {ROUNDED: 0, CHAMFERED: 0}
    for k in np.flatnonzero((corners["corner_shape"] != SHARP) & (corners["glass_walls"] == 0)):
        v = np.array([corners["east_m"][k], corners["north_m"][k]])
        inward = corners["inward_en"][k]
        turn = np.pi - np.radians(corners["interior_angle_deg"][k])
        size = corners["shape_size_m"][k]
        expected = size / np.cos(turn / 2) - size if corners["corner_shape"][k] == ROUNDED else size * np.sin(turn / 2)
        start = v - 0.3 * inward  # 0.3 m outside the walls' intersection, aimed along the inward bisector
        t, _ = scene.cast(np.array([[*start, 5.0]]), np.array([[*inward, 0.0]]))
        assert t[0] == pytest.approx(0.3 + expected, abs=0.03)
        checked[int(corners["corner_shape"][k])] += 1
    assert checked[ROUNDED] >= 2 and checked[CHAMFERED] >= 2


def test_truth_lists_the_walls_intersection_with_its_shape(tiny_sim):
    out, _ = tiny_sim
    rows = list(csv.DictReader(open(out / "truth/corners.csv")))
    shapes = {r["corner_shape"] for r in rows}
    assert shapes <= {"sharp", "rounded", "chamfered"} and "sharp" in shapes
    for r in rows:
        size = float(r["shape_size_m"])
        assert size == 0.0 if r["corner_shape"] == "sharp" else 1.0 <= size <= 5.0
