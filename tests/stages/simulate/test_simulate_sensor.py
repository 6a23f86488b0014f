"""HDL-32E model against its datasheet: ring elevations, range noise on a flat wall, glass gives no return."""
from __future__ import annotations

import numpy as np

from stages.simulate.markings import Raster
from stages.simulate.mesh import WALL, Scene, TriangleSoup, vertical_quads
from stages.simulate.sensor import N_AZIMUTH, LaserCalibration, build_beam_table, simulate_scan

# HDL-32E manual, elevation of lasers sorted from the lowest beam (deg)
HDL32E_ELEVATIONS_DEG = [-30.67, -29.33, -28.00, -26.67, -25.33, -24.00, -22.67, -21.33, -20.00, -18.67, -17.33,
                         -16.00, -14.67, -13.33, -12.00, -10.67, -9.33, -8.00, -6.67, -5.33, -4.00, -2.67, -1.33,
                         0.00, 1.33, 2.67, 4.00, 5.33, 6.67, 8.00, 9.33, 10.67]


def _scan(soup: TriangleSoup, seed: int = 0):
    empty = Raster(np.zeros((1, 1), np.uint8), 0.0, 0.0, 1.0)
    albedo = Raster(np.full((1, 1), 0.1, np.float32), -1e4, 1e4, 2e4)
    poses = np.zeros((N_AZIMUTH, 5))
    dynamic = Scene(TriangleSoup(np.zeros((0, 3, 3), np.float32), np.zeros(0, np.uint8), np.zeros(0, np.float32)))
    calib = LaserCalibration(np.ones(32), np.zeros(32))
    return simulate_scan(build_beam_table(), poses, Scene(soup), dynamic, empty, albedo, calib,
                         np.random.default_rng(seed))


def _walls(p0, p1, height=30.0, refl=0.4):
    tris = vertical_quads(np.asarray(p0, float), np.asarray(p1, float), 0.0, height)
    return TriangleSoup(
        tris.astype(np.float32), np.full(len(tris), WALL, np.uint8), np.full(len(tris), refl, np.float32)
    )


def test_ring_elevations_match_the_hdl32e_table(tiny_sim):
    from tests.stages.simulate.test_simulate_outputs import read_pcd

    pts = read_pcd(tiny_sim[0] / "drive_0/scans/000010.pcd")
    r = np.sqrt(pts["x"].astype(float) ** 2 + pts["y"] ** 2 + pts["z"] ** 2)
    el = np.degrees(np.arcsin(pts["z"] / r))
    seen = np.unique(pts["ring"])
    assert len(seen) >= 26  # the lowest rings hit the ego roof
    for ring in seen:
        assert abs(np.median(el[pts["ring"] == ring]) - HDL32E_ELEVATIONS_DEG[ring]) < 0.05


def test_range_noise_on_a_flat_wall_is_2cm():
    wall = _walls([[10.0, -30.0]], [[10.0, 30.0]])  # a wall 10 m ahead, facing the sensor
    pts = _scan(wall)
    on_wall = pts["x"] > 5.0
    dirs = np.column_stack([pts["x"], pts["y"], pts["z"] - 0.0]).astype(float)[on_wall]
    r_meas = np.linalg.norm(dirs, axis=1)
    r_true = 10.0 / (dirs[:, 0] / r_meas)  # distance along each beam to the plane x = 10 m (lidar frame)
    sigma = np.std(r_meas - r_true)
    assert on_wall.sum() > 3000
    assert 0.016 < sigma < 0.024


def test_glass_wall_gives_no_return_but_the_room_behind_does():
    # a box building from x=10 to x=20; its front wall (x=10) is glass, i.e. absent from the mesh
    back = _walls([[20.0, -8.0]], [[20.0, 8.0]])
    sides = _walls([[10.0, -8.0], [20.0, 8.0]], [[20.0, -8.0], [10.0, 8.0]])
    soup = TriangleSoup.concat([back, sides])
    pts = _scan(soup)
    near_glass = (np.abs(pts["x"] - 10.0) < 0.2) & (np.abs(pts["y"]) < 7.5)
    front = (pts["x"] > 0) & (np.abs(pts["y"]) < 4.0) & (pts["z"] > -1.0)
    assert near_glass.sum() == 0
    assert np.sum(front & (np.abs(pts["x"] - 20.0) < 0.2)) > 500  # the back wall is seen through the glass
    solid = _scan(TriangleSoup.concat([soup, _walls([[10.0, -8.0]], [[10.0, 8.0]])]))
    assert np.sum(np.abs(solid["x"] - 10.0) < 0.2) > 500 and np.sum(np.abs(solid["x"] - 20.0) < 0.2) == 0


def test_intensity_has_per_ring_gain_and_offset():
    wall = _walls([[10.0, -30.0]], [[10.0, 30.0]])
    empty = Raster(np.zeros((1, 1), np.uint8), 0.0, 0.0, 1.0)
    dynamic = Scene(TriangleSoup(np.zeros((0, 3, 3), np.float32), np.zeros(0, np.uint8), np.zeros(0, np.float32)))
    gain = np.where(np.arange(32) % 2 == 0, 0.6, 1.4)
    pts = simulate_scan(build_beam_table(), np.zeros((N_AZIMUTH, 5)), Scene(wall), dynamic, empty, empty,
                        LaserCalibration(gain, np.zeros(32)), np.random.default_rng(1))
    front = pts["x"] > 5
    med = {r: np.median(pts["intensity"][front & (pts["ring"] == r)]) for r in (20, 21)}
    assert med[21] / med[20] > 1.8  # neighbouring rings, same wall, different uncalibrated gain


def test_motion_distortion_uses_the_pose_at_each_firing():
    wall = _walls([[10.0, -40.0]], [[10.0, 40.0]])
    empty = Raster(np.zeros((1, 1), np.uint8), 0.0, 0.0, 1.0)
    dynamic = Scene(TriangleSoup(np.zeros((0, 3, 3), np.float32), np.zeros(0, np.uint8), np.zeros(0, np.float32)))
    beams = build_beam_table()
    poses = np.zeros((N_AZIMUTH, 5))
    poses[:, 0] = 10.0 * np.arange(N_AZIMUTH) * (0.1 / N_AZIMUTH)  # 10 m/s east, towards the wall
    pts = simulate_scan(beams, poses, Scene(wall), dynamic, empty, empty, LaserCalibration(np.ones(32), np.zeros(32)),
                        np.random.default_rng(2))
    on_wall = pts["x"] > 3.0
    expected_x = 10.0 - 10.0 * pts["time"][on_wall]  # the wall seen from where the lidar was at firing time
    assert np.abs(np.median(pts["x"][on_wall] - expected_x)) < 0.01
    assert np.ptp(pts["time"][on_wall]) > 0.03 and np.std(pts["x"][on_wall] - expected_x) < 0.05
