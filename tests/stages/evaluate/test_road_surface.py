"""Oracle tests of the road surface the marking features are cut from (``estimate_ground_plane``): a scripted
scan of a tilted road (the body rolled in a turn) with a sidewalk one curb above it on one side."""
from __future__ import annotations

import numpy as np

from fixtures.evaluate import ground_ring_scan, paint_markings
from stages.common.road_features import estimate_ground_plane, extract_road_features

CELL = 0.1
CURB_M = 0.15
T_VEHICLE_LIDAR = np.eye(4)
T_VEHICLE_LIDAR[2, 3] = 1.8


def _tilted_scan(roll_rad: float, pitch_rad: float, seed: int = 4):
    """Ground rings in the vehicle frame of a body rolled by ``roll_rad`` and pitched by ``pitch_rad`` over a flat
    road (z = -1.8 - x tan(pitch) + y tan(roll) in the lidar frame, to first order); beyond y = 6 m (left) the
    ground is a sidewalk 0.15 m up whose concrete is brighter than the asphalt. Returns the scan, the sidewalk
    mask and the true plane [a, b, c] of the road in the vehicle frame."""
    rng = np.random.default_rng(seed)
    mask, origin = paint_markings(200.0, 40.0, CELL, road_y_m=20.0, crosswalks_x_m=(60.0, 130.0))
    xyz, inten, ring = ground_ring_scan(np.array([95.0, 18.0, 0.0]), mask, origin, CELL, rng)
    b, c = -np.tan(pitch_rad), np.tan(roll_rad)
    xyz[:, 2] += b * xyz[:, 0] + c * xyz[:, 1]
    walk = xyz[:, 1] > 6.0
    xyz[walk, 2] += CURB_M
    inten = inten.copy()
    inten[walk] += 15.0 * (rng.random(walk.sum()) < 0.3)  # speckled concrete: bright along the ring
    return xyz, inten, ring, walk, np.array([0.0, b, c])


def test_the_road_plane_of_a_rolled_body_is_found_beside_a_sidewalk():
    for roll_deg, pitch_deg in ((0.0, 0.0), (0.6, 0.0), (-0.8, 0.4), (1.5, -1.0)):
        xyz, _, _, _, truth = _tilted_scan(np.deg2rad(roll_deg), np.deg2rad(pitch_deg))
        v = xyz + T_VEHICLE_LIDAR[:3, 3]
        plane = estimate_ground_plane(v)
        assert abs(plane[0] - truth[0]) < 0.005, (roll_deg, pitch_deg, plane)
        assert np.all(np.abs(np.rad2deg(np.arctan(plane[1:])) - np.rad2deg(np.arctan(truth[1:]))) < 0.02)


def test_a_level_band_lets_the_sidewalk_in_under_roll_and_the_plane_keeps_it_out():
    # rolled towards the sidewalk (left side down): 10 m left it sits 0.15 - 10 tan(0.6 deg) = 0.045 m over the
    # road level
    xyz, inten, ring, walk, _ = _tilted_scan(np.deg2rad(-0.6), 0.0)
    on_walk = lambda f: np.mean(f[:, 1] > 6.0) if len(f) else 0.0  # noqa: E731
    level = extract_road_features(xyz, inten, ring, T_VEHICLE_LIDAR, ground_model="level")
    plane = extract_road_features(xyz, inten, ring, T_VEHICLE_LIDAR, ground_model="plane", ground_band_m=0.1)
    assert on_walk(level) > 0.2
    assert on_walk(plane) < 0.02
    # the paint on the road is kept
    road = lambda f: int(np.sum(f[:, 1] <= 6.0))  # noqa: E731
    assert road(plane) >= 0.95 * road(level) and road(plane) > 100


def test_too_few_points_give_a_level_plane_at_the_mode():
    pts = np.array([[1.0, 0.0, 0.1], [2.0, 0.0, 0.1], [3.0, 1.0, 0.1]])
    plane = estimate_ground_plane(pts)
    assert plane[1] == 0.0 and plane[2] == 0.0 and abs(plane[0] - 0.1) < 0.05
