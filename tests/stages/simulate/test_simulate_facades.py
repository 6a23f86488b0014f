"""Issue 62: facades with windows, shop fronts, entrances, balconies and hedges. Rays through a window reach the
room behind, a pier returns at the wall plane, an entrance returns from its door, a balcony stands out of the wall;
the facade-detail truth corners have material on their stated side; the footprint truth does not move."""
from __future__ import annotations

import numpy as np
import pytest

from stages.simulate.city import Building
from stages.simulate.facades import _Opening, _Wall, facade_corner_rows, generate_facades
from stages.simulate.geom2d import point_in_polygon
from stages.simulate.mesh import Scene, TriangleSoup

SQUARE = np.array([[0.0, 0.0], [30.0, 0.0], [30.0, 20.0], [0.0, 20.0]])  # ccw: the front wall y = 0 faces -y


def _building(**shares) -> tuple[Building, Scene]:
    b = Building(SQUARE, 18.0, np.zeros(4, bool), 0.4)
    detail = generate_facades([b], rng=np.random.default_rng(3), **shares)[0]
    soup = TriangleSoup(detail.tris, np.zeros(len(detail.tris), np.uint8), detail.refl)
    return b, detail, Scene(soup)


def _cast_north(scene: Scene, x: np.ndarray, z: float) -> np.ndarray:
    """Range along +y from y = -10 at the given x and height (inf: no hit)."""
    origins = np.column_stack([x, np.full(len(x), -10.0), np.full(len(x), z)])
    return scene.cast(origins, np.tile([0.0, 1.0, 0.0], (len(x), 1)))[0] - 10.0  # depth behind the wall plane


def test_a_wall_with_openings_has_holes_reveals_and_panes():
    wall = _Wall(np.array([0.0, 0.0]), np.array([10.0, 0.0]), 6.0)  # building on the left: +y
    openings = [_Opening(2.0, 3.0, 1.0, 2.0, 0.25, "open"), _Opening(5.0, 6.0, 1.0, 2.0, 0.2, "pane"),
                _Opening(7.0, 9.0, 0.0, 2.5, 1.5, "pane", mullion_pitch_m=0.0)]
    scene = Scene(TriangleSoup(wall.with_openings(openings).astype(np.float32), np.zeros(0, np.uint8),
                               np.zeros(0, np.float32)))
    depth = _cast_north(scene, np.array([1.0, 2.5, 5.5, 8.0, 4.0, 2.5]), 1.5)
    assert depth[0] == pytest.approx(0.0, abs=1e-4) and depth[4] == pytest.approx(0.0, abs=1e-4)  # piers
    assert np.isinf(depth[1])  # open glass: nothing in this scene behind it
    assert depth[2] == pytest.approx(0.2, abs=1e-4) and depth[3] == pytest.approx(1.5, abs=1e-4)  # pane, door
    assert _cast_north(scene, np.array([2.5]), 2.5)[0] == pytest.approx(0.0, abs=1e-4)  # above the window: wall


def test_facade_detail_on_a_building():
    b, detail, scene = _building(window_share=1.0, shopfront_share=1.0, balcony_share=1.0, vegetation_share=1.0)
    assert detail.replaced.all() and len(detail.slab_z_m) >= 3 and len(detail.leaves) > 100
    x = np.linspace(0.5, 29.5, 300)
    ground = _cast_north(scene, x, 2.0)  # the shop front: piers at the wall plane, glass, entrances
    assert np.mean(np.abs(ground) < 1e-3) > 0.05 and np.mean(np.abs(ground) > 0.15) > 0.5
    upper = _cast_north(scene, x, detail.slab_z_m[1] + 1.6)  # window height on an upper floor
    assert np.mean(np.abs(upper) < 1e-3) > 0.2 and np.mean(upper > 0.1) > 0.2  # piers and windows
    rows = facade_corner_rows([detail])
    kinds = set(rows["kind"])
    assert kinds == {"entrance", "balcony"} and set(rows["interior_angle_deg"]) == {90.0, 270.0}
    # balconies stand out of the wall: a ray from the street at slab height stops in front of the wall plane
    slab_z = detail.slab_z_m[1] + 0.1
    bal = rows["kind"] == "balcony"
    assert np.any(_cast_north(scene, rows["east_m"][bal] + 0.0, slab_z) < -0.5)


def test_facade_corners_have_material_on_the_stated_side():
    b, detail, scene = _building(window_share=1.0, shopfront_share=1.0, balcony_share=1.0, vegetation_share=0.0)
    rows = facade_corner_rows([detail])
    assert len(rows["id"]) >= 8
    for k in range(len(rows["id"])):
        p = np.array([rows["east_m"][k], rows["north_m"][k]])
        th = np.radians([rows["theta1_deg"][k], rows["theta2_deg"][k]])
        d1, d2 = np.array([np.cos(th[0]), np.sin(th[0])]), np.array([np.cos(th[1]), np.sin(th[1])])
        assert abs(d1 @ d2) < 1e-9
        entrance = rows["kind"][k] == "entrance"
        z = 0.5 * (rows["z_min_m"][k] + rows["z_max_m"][k]) if entrance else rows["z_min_m"][k] + 0.1
        # a ray from the free side towards the corner stops at it (within 3 cm) when aimed at the material
        inside = p + 0.1 * (d1 + d2) * (1 if rows["interior_angle_deg"][k] == 90.0 else -1)
        outside = p - 0.6 * (d1 + d2) * (1 if rows["interior_angle_deg"][k] == 90.0 else -1)
        direction = np.r_[inside - outside, 0.0]
        dist = np.linalg.norm(direction)
        t_hit, _ = scene.cast(np.r_[outside, z][None], (direction / dist)[None])
        assert t_hit[0] < dist + 0.03, (rows["kind"][k], rows["interior_angle_deg"][k])
        if rows["interior_angle_deg"][k] == 90.0:  # an edge: the building footprint is not where the material is
            assert rows["kind"][k] == "balcony" or not point_in_polygon(p[None] - 0.05 * (d1 + d2), SQUARE)[0]


def test_facades_off_by_default_and_a_city_keeps_its_footprints():
    from stages.simulate.core import build_city
    from stages.simulate.presets import get_preset

    plain = build_city(get_preset("tiny"), 5)
    assert all(b.facade is None for b in plain.buildings)
    detailed = build_city(get_preset("tiny_consumer"), 5)
    assert sum(b.facade is not None for b in detailed.buildings) >= len(detailed.buildings) // 2
    for a, c in zip(plain.buildings, detailed.buildings):
        np.testing.assert_array_equal(a.footprint_en, c.footprint_en)
