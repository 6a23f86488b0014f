"""Street furniture: on the sidewalk, clear of trunks and poles, in the mesh, and its truth corners sit on
the boxes' outline with the material on the stated side."""
from __future__ import annotations

import csv

import numpy as np

from stages.simulate.city import CURB_H_M
from stages.simulate.furniture import KINDS, furniture_corners, generate_furniture
from stages.simulate.geom2d import point_in_polygon

KERB = np.array([[0.0, 0.0], [200.0, 0.0], [200.0, 150.0], [0.0, 150.0]])  # one block, ccw
SIDEWALK_M = 4.0


def _box_polys(boxes: np.ndarray) -> list[np.ndarray]:
    out = []
    for e, n, yaw, length, width in boxes[:, :5]:
        c, s = np.cos(yaw), np.sin(yaw)
        loc = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * [length / 2, width / 2]
        out.append(np.column_stack([e + c * loc[:, 0] - s * loc[:, 1], n + s * loc[:, 0] + c * loc[:, 1]]))
    return out


def _in_material(p: np.ndarray, polys: list[np.ndarray]) -> bool:
    return any(point_in_polygon(p[None], q)[0] for q in polys)


def test_furniture_stands_on_the_sidewalk_clear_of_posts():
    trees = np.array([[50.0, 1.2, 3.0, 2.0, 2.0], [100.0, 1.2, 3.0, 2.0, 2.0]])
    poles = np.array([[30.0, 0.5], [148.8, 70.0]])
    items = generate_furniture([KERB], SIDEWALK_M, 60.0, trees, poles, np.random.default_rng(3))
    assert {it.kind for it in items} == set(KINDS) and len(items) >= 15
    inner = np.array([[SIDEWALK_M, SIDEWALK_M], [200 - SIDEWALK_M, SIDEWALK_M], [200 - SIDEWALK_M, 150 - SIDEWALK_M],
                      [SIDEWALK_M, 150 - SIDEWALK_M]])
    posts = np.concatenate([trees[:, :2], poles])
    for it in items:
        pts = np.concatenate(_box_polys(it.boxes))
        assert point_in_polygon(pts, KERB).all() and not point_in_polygon(pts, inner).any()  # on the sidewalk
        assert np.all(it.boxes[:, 5] >= CURB_H_M - 1e-9)
        assert np.linalg.norm(pts[:, None] - posts[None], axis=-1).min() > 0.6


def test_furniture_corners_lie_on_the_outline_with_material_on_the_stated_side():
    items = generate_furniture([KERB], SIDEWALK_M, 60.0, np.zeros((0, 5)), np.zeros((0, 2)),
                               np.random.default_rng(4))
    fc = furniture_corners(items)
    owner = np.repeat(np.arange(len(items)), [len(it.corners_en) for it in items])
    assert len(fc["id"]) == len(owner) > 20
    for k in range(len(owner)):
        polys = _box_polys(items[owner[k]].boxes[items[owner[k]].boxes[:, 5] < CURB_H_M + 0.01])  # standing boxes
        th = np.radians([fc["theta1_deg"][k], fc["theta2_deg"][k]])
        d1, d2 = np.array([np.cos(th[0]), np.sin(th[0])]), np.array([np.cos(th[1]), np.sin(th[1])])
        assert abs(d1 @ d2) < 1e-9  # right-angled
        p = np.array([fc["east_m"][k], fc["north_m"][k]])
        between = p + 0.03 * (d1 + d2)
        if fc["interior_angle_deg"][k] == 90.0:  # box corner: material between the faces, free outside
            assert _in_material(between, polys) and not _in_material(p - 0.03 * (d1 + d2), polys)
        else:  # the fence's bend seen from the street: free between the panels, material behind
            assert fc["kind"][k] == "fence" and fc["interior_angle_deg"][k] == 270.0
            assert not _in_material(between, polys) and _in_material(p - 0.03 * (d1 + d2), polys)
        for d in (d1, d2):  # a face runs from the corner along each direction
            assert _in_material(p + 0.3 * d - 0.03 * (d1 + d2 - d) * np.sign(fc["interior_angle_deg"][k] - 180), polys)


def test_furniture_is_in_the_mesh_and_in_truth(tiny_sim):
    from stages.simulate.core import build_city, component_rng
    from stages.simulate.mesh import FURNITURE, build_static_soup
    from stages.simulate.presets import get_preset

    city = build_city(get_preset("tiny", furniture_per_km=40.0), 0)
    soup = build_static_soup(city, component_rng(0, "mesh"))
    assert (soup.cls == FURNITURE).sum() == 12 * sum(len(it.boxes) for it in city.furniture) > 0
    out, _ = tiny_sim
    rows = list(csv.DictReader(open(out / "truth/furniture_corners.csv")))
    header = (out / "truth/furniture_corners.csv").read_text().splitlines()[0]
    assert header == "id,kind,east_m,north_m,theta1_deg,theta2_deg,interior_angle_deg,height_m"
    building = np.array(
        [[float(r["east_m"]), float(r["north_m"])] for r in csv.DictReader(open(out / "truth/corners.csv"))]
    )
    for r in rows:  # furniture corners are not building corners
        assert np.linalg.norm(building - [float(r["east_m"]), float(r["north_m"])], axis=1).min() > 0.5


def test_no_furniture_when_turned_off():
    assert generate_furniture([KERB], SIDEWALK_M, 0.0, np.zeros((0, 5)), np.zeros((0, 2)),
                              np.random.default_rng(0)) == []
