"""Corner truth as a sensor sees it: union walls where buildings touch, and scans that see two walls."""
from __future__ import annotations

import numpy as np
import pytest

from stages.simulate.mesh import Scene, TriangleSoup, vertical_quads
from stages.simulate.truth import building_corners, count_corner_views, union_corner_walls


def _rect(x0, y0, x1, y1):  # counter-clockwise
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], float)


def _own_walls(poly):
    to_prev = np.roll(poly, 1, axis=0) - poly
    to_next = np.roll(poly, -1, axis=0) - poly
    return np.column_stack([np.arctan2(to_prev[:, 1], to_prev[:, 0]), np.arctan2(to_next[:, 1], to_next[:, 0])])


def _assert_same_angles(a, b):
    np.testing.assert_allclose(np.angle(np.exp(1j * (np.asarray(a) - np.asarray(b)))), 0.0, atol=1e-9)


def _angle_set_deg(theta):
    return sorted(np.round(np.degrees(theta)) % 360)


def test_lone_building_keeps_its_own_walls():
    a = _rect(0, 0, 10, 6)
    theta, inward, not_corner = union_corner_walls([a], a, _own_walls(a))
    _assert_same_angles(theta, _own_walls(a))
    assert not not_corner.any()
    np.testing.assert_allclose(inward[0], np.array([1, 1]) / np.sqrt(2), atol=0.01)


def test_party_wall_vertex_takes_the_union_walls():
    # B sits on A's north wall and ends at x=6; A's north wall continues east of B
    a, b = _rect(0, 0, 10, 6), _rect(-4, 6, 6, 12)
    verts = np.vstack([a, b])
    own = np.vstack([_own_walls(a), _own_walls(b)])
    theta, inward, not_corner = union_corner_walls([a, b], verts, own)
    # B's south-east vertex (6,6): own walls west (hidden in the party wall) + north; the union shows
    # A's roof line going east + B's east wall going north (a concave corner of the union)
    k = 4 + 1
    assert _angle_set_deg(own[k]) == [90, 180]
    assert _angle_set_deg(theta[k]) == [0, 90]
    assert not not_corner[k]
    np.testing.assert_allclose(inward[k], -np.array([1, 1]) / np.sqrt(2), atol=0.01)
    # A's north-west vertex (0,6) lies on B's south wall: the union turns there (west along B, south along A)
    assert _angle_set_deg(own[3]) == [0, 270] and _angle_set_deg(theta[3]) == [180, 270]
    assert not not_corner[3]
    # unaffected vertices keep their walls
    for k in (0, 1, 6, 7):
        _assert_same_angles(theta[k], own[k])


def test_small_step_between_facades_is_not_a_corner():
    # two buildings whose facades continue each other with a 0.15 m step
    a, b = _rect(0, 0, 10, 6), _rect(0.15, 6, 10.15, 12)
    verts = np.vstack([a, b])
    _, _, not_corner = union_corner_walls([a, b], verts, np.vstack([_own_walls(a), _own_walls(b)]))
    assert not_corner[2] and not_corner[4 + 1]  # (10,6) / (10.15,6): east facades
    assert not_corner[3] and not_corner[4 + 0]  # (0,6) / (0.15,6): west facades
    assert not not_corner[0] and not not_corner[4 + 2]


def _walls_scene(polys, glass=()):
    tris = []
    for i, p in enumerate(polys):
        q = np.roll(p, -1, axis=0)
        keep = np.array([(i, k) not in glass for k in range(len(p))])
        tris.append(vertical_quads(p[keep], q[keep], 0.0, 20.0))
    t = np.concatenate(tris).astype(np.float32)
    return Scene(TriangleSoup(t, np.zeros(len(t), np.uint8), np.full(len(t), 0.5, np.float32)))


class _City:
    def __init__(self, polys, glass):
        self.buildings = [
            type("B", (), {"footprint_en": p, "glass": g, "height_m": 20.0})() for p, g in zip(polys, glass)
        ]


@pytest.mark.parametrize("glass_wall", [False, True])
def test_corner_views_need_both_faces_in_sight(glass_wall):
    a = _rect(0, 0, 10, 10)
    glass = np.zeros(4, bool)
    glass[0] = glass_wall  # wall 0: (0,0)->(10,0), one wall of corners 0 and 1
    corners = building_corners(_City([a], [glass]))
    scene = _walls_scene([a], glass={(0, 0)} if glass_wall else set())
    sensors = np.array([[-15.0, -15.0],  # diagonal in front of corner 0: both walls of it in view
                        [-20.0, 5.0],  # west of the building: only the west wall of corner 0
                        [-3.0, -3.0],  # too near (8 m minimum)
                        [25.0, -15.0]])  # diagonal in front of corner 1
    counts = count_corner_views(corners, scene, sensors, 1.9)
    k0 = int(np.argmin(np.linalg.norm(np.column_stack([corners["east_m"], corners["north_m"]]) - [0, 0], axis=1)))
    k1 = int(np.argmin(np.linalg.norm(np.column_stack([corners["east_m"], corners["north_m"]]) - [10, 0], axis=1)))
    assert counts[k0] == (0 if glass_wall else 1)
    assert counts[k1] == (0 if glass_wall else 1)
    assert counts.sum() == counts[k0] + counts[k1]


def test_corner_views_blocked_by_an_occluder():
    a = _rect(0, 0, 10, 10)
    wall = _rect(-8.0, -8.5, -6.0, -6.0)  # a kiosk between the sensor and corner 0
    corners = building_corners(_City([a], [np.zeros(4, bool)]))
    free = count_corner_views(corners, _walls_scene([a]), np.array([[-15.0, -15.0]]), 1.9)
    blocked = count_corner_views(corners, _walls_scene([a, wall]), np.array([[-15.0, -15.0]]), 1.9)
    assert free.sum() == 1 and blocked.sum() == 0


def test_a_glass_neighbour_hides_nothing():
    # as in test_party_wall_vertex_takes_the_union_walls, but A's north wall (wall 2: (10,6)->(0,6)) is glass:
    # the sensor sees through A, so B's south-east vertex keeps B's own walls (west + north)
    a, b = _rect(0, 0, 10, 6), _rect(-4, 6, 6, 12)
    own = np.vstack([_own_walls(a), _own_walls(b)])
    glass = [np.array([False, False, True, False]), np.zeros(4, bool)]
    owner = np.repeat([0, 1], 4)
    theta, _, not_corner = union_corner_walls([a, b], np.vstack([a, b]), own, glass=glass, owner=owner)
    assert _angle_set_deg(theta[5]) == [90, 180] and not not_corner[5]
    theta_opaque, _, _ = union_corner_walls([a, b], np.vstack([a, b]), own)
    assert _angle_set_deg(theta_opaque[5]) == [0, 90]
