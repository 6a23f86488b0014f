"""City generator and trajectory: street angles, footprint kinds, route stays on streets, speed limit."""
from __future__ import annotations

import numpy as np

from stages.simulate.city import generate_city
from stages.simulate.core import component_rng
from stages.simulate.geom2d import point_in_polygon, polygon_corners, signed_area_m2, triangulate_polygon
from stages.simulate.presets import get_preset
from stages.simulate.trajectory import V_MAX_MPS, choose_loop_cells, lane_polyline, loop_nodes, plan_drive


def test_city_has_non_orthogonal_corners_and_shapes():
    p = get_preset("demo")
    city = generate_city(p, component_rng(0, "city"))
    interior = np.concatenate([np.degrees(polygon_corners(b.footprint_en)[:, 2]) for b in city.buildings])
    assert np.any(np.abs(interior - 90) > 5) and np.any(interior > 180)  # obtuse/acute and recessed corners
    assert {len(b.footprint_en) for b in city.buildings} >= {4, 5, 6, 8}
    assert all(signed_area_m2(b.footprint_en) > 0 for b in city.buildings)
    heights = [b.height_m for b in city.buildings]
    assert min(heights) >= 10 and max(heights) <= 60
    assert any(b.glass.any() for b in city.buildings) and len(city.trees) > 50 and len(city.parked) > 10


def test_ear_clipping_covers_an_l_shape():
    poly = np.array([[0, 0], [4, 0], [4, 1], [1, 1], [1, 3], [0, 3]], float)
    tris = triangulate_polygon(poly)
    area = sum(abs(signed_area_m2(poly[t])) for t in tris)
    assert len(tris) == 4 and area == np.float64(signed_area_m2(poly))
    assert not point_in_polygon(np.array([[2.0, 2.0]]), poly)[0]


def test_drive_follows_lanes_under_40kmh_with_turns():
    p = get_preset("demo")
    city = generate_city(p, component_rng(0, "city"))
    loop = loop_nodes(choose_loop_cells(p.n_rows, p.n_cols, city.nodes_en, p.lap_length_m, component_rng(0, "r")))
    poly, turns = lane_polyline(city, loop, 9)
    traj = plan_drive(poly, turns, 1, p.cruise_mps, 0.5, np.random.default_rng(0))
    assert traj.speed_mps.max() <= V_MAX_MPS + 1e-6
    assert 900 < traj.length_m < 1300 and len(turns) >= 4
    assert (traj.speed_mps < 0.05).sum() > 100 * 5  # stopped at least 5 s at some crossing
    turned = np.abs(traj.yaw_enu_rad[-1] - traj.yaw_enu_rad[0])
    assert abs(turned - 2 * np.pi) < 0.3  # one closed loop
    # the lane centre stays on the carriageway: within the lanes of one of the loop's streets
    nodes = np.array([city.nodes_en[n] for n in loop])
    xy = np.column_stack([traj.east_m, traj.north_m])
    dist = []
    for a, b in zip(nodes, np.roll(nodes, -1, 0)):
        u = np.clip(((xy - a) @ (b - a)) / ((b - a) @ (b - a)), 0, 1)
        dist.append(np.linalg.norm(xy - (a + u[:, None] * (b - a)), axis=1))
    lanes_m = 3.5 * min(city.lanes_row, city.lanes_col)
    assert np.min(dist, axis=0).max() < lanes_m + 0.5
