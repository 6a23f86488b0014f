"""Issue 62: the lidar with a horizontal lever arm and a mount yaw (the drive file states T_vehicle_lidar, the truth
stays in the vehicle frame), the HDL-64E, a drive without a survey and a consumer GNSS receiver."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import yaml

from stages.simulate.gnss import COG_MIN_SPEED_MPS, COG_VELOCITY_SIGMA_MPS, course_over_ground_errors
from stages.simulate.presets import get_preset
from stages.simulate.sensor import LIDARS, build_beam_table, mount_matrix

MOUNT = dict(lidar_x_m=1.2, lidar_y_m=-0.4, lidar_z_m=1.8, lidar_yaw_deg=35.0)


def _outline_distance_m(points_en: np.ndarray, city: dict) -> np.ndarray:
    a = np.vstack([np.asarray(b["outline_en"]) for b in city["buildings"]])
    e = np.vstack([np.roll(np.asarray(b["outline_en"]), -1, axis=0) for b in city["buildings"]])
    ab = e - a
    t = np.clip(np.einsum("pkj,kj->pk", points_en[:, None] - a, ab) / np.einsum("kj,kj->k", ab, ab), 0.0, 1.0)
    return np.linalg.norm(points_en[:, None] - (a + t[..., None] * ab), axis=-1).min(axis=1)


@pytest.fixture(scope="module")
def mounted_sim(tmp_path_factory):
    from stages.simulate.core import simulate

    out = tmp_path_factory.mktemp("sim_mount")
    simulate(get_preset("tiny", survey=False, gnss_attitude=False, **MOUNT), 4, out, n_drives=1, scan_limit=6,
             motion_distortion=False)
    return out


def test_drive_file_states_the_mount_and_points_land_on_the_walls_through_it(mounted_sim):
    from stages.common.records import Trajectory
    from tests.stages.simulate.test_simulate_outputs import read_pcd

    doc = yaml.safe_load((mounted_sim / "drive_0/drive.yaml").read_text())
    T_vl = np.asarray(doc["T_vehicle_lidar"], float)
    np.testing.assert_allclose(T_vl, mount_matrix(1.2, -0.4, 1.8, 35.0))
    assert json.loads((mounted_sim / "simulation.json").read_text())["T_vehicle_lidar"] == T_vl.tolist()
    T = Trajectory.from_tum(mounted_sim / "truth/drive_0_poses_tum.txt").T  # T_enu_vehicle, as documented
    city = json.loads((mounted_sim / "truth/city.json").read_text())
    pts = read_pcd(mounted_sim / "drive_0/scans/000003.pcd")
    xyz1 = np.column_stack([pts["x"], pts["y"], pts["z"], np.ones(len(pts))]).astype(float)
    high = lambda en_z: (en_z[:, 2] > 4.5) & (en_z[:, 2] < 9.0)  # noqa: E731  above cars, trunks and most crowns
    on = xyz1 @ (T[3] @ T_vl).T
    assert high(on).sum() > 200
    assert np.median(_outline_distance_m(on[high(on), :2], city)) < 0.05
    # the same points through the lidar's height alone (no lever arm, no yaw) miss the walls by metres
    naive = xyz1 @ (T[3] @ mount_matrix(0.0, 0.0, 1.8, 0.0)).T
    assert np.median(_outline_distance_m(naive[high(naive), :2], city)) > 0.5


def test_no_survey_and_a_receiver_without_ins(mounted_sim):
    doc = yaml.safe_load((mounted_sim / "drive_0/drive.yaml").read_text())
    assert "survey" not in doc and not (mounted_sim / "survey").exists()
    assert set(doc["gnss"]["columns"]) == {"lat", "lon", "height", "heading", "std_east", "std_north", "std_up",
                                           "std_heading"}
    header = next(csv.reader(open(mounted_sim / "drive_0/gnss_inspva.csv")))
    assert "roll_deg" not in header and "pitch_deg" not in header and "azimuth_deg" in header
    from stages.ingest.drive_check import check_drive

    assert check_drive(mounted_sim / "drive_0/drive.yaml").problems == []


def test_course_over_ground_error_follows_speed_and_is_held_while_standing():
    rng = np.random.default_rng(0)
    speed = np.r_[np.full(20000, 10.0), np.full(20000, 2.0), np.zeros(500), np.full(100, 5.0)]
    err, std = course_over_ground_errors(speed, rng)
    assert np.std(err[:20000]) == pytest.approx(COG_VELOCITY_SIGMA_MPS / 10.0, rel=0.05)
    assert np.std(err[20000:40000]) == pytest.approx(COG_VELOCITY_SIGMA_MPS / 2.0, rel=0.05)
    assert np.all(err[40000:40500] == err[39999]) and np.all(std[40000:40500] > np.radians(30))
    assert np.all(std[:40000] < np.radians(2.0)) and COG_MIN_SPEED_MPS > 0


def test_consumer_grade_gnss_has_metres_of_slow_bias_and_long_outages():
    from stages.simulate.gnss import simulate_gnss_errors

    p = get_preset("demo_consumer")
    n = 20 * 1800
    t = np.arange(n) / 20.0
    err = simulate_gnss_errors(t, np.full(n, 0.4), t * 9.0, p.gnss_target_rms_m, p.gnss_bias_open_m,
                               p.gnss_bias_canyon_m, p.multipath_per_km, p.outage_per_km, np.random.default_rng(5),
                               bias_tau_s=p.gnss_bias_tau_s, multipath_m=p.gnss_multipath_m,
                               outage_s=p.gnss_outage_s, std_share=p.gnss_std_share)
    h = err.err_enu_m[:, :2]
    assert 2.5 < np.sqrt(np.mean(np.sum(h ** 2, axis=1))) < 6.0
    step_10s = np.linalg.norm(h[200:] - h[:-200], axis=1)  # slowly varying: 10 s apart it barely moves
    assert np.median(step_10s) < 0.25 * np.sqrt(np.mean(np.sum(h ** 2, axis=1)))
    gaps = np.diff(np.flatnonzero(np.diff(err.valid.astype(int)) != 0))
    assert (~err.valid).any() and gaps.max() >= 20 * 5.0  # outages of 5 s or more
    reported = np.hypot(err.std_enu_m[:, 0], err.std_enu_m[:, 1])
    assert 0.3 < np.median(reported) / np.sqrt(np.mean(np.sum(h ** 2, axis=1))) < 1.5  # of the bias' order


def test_hdl64e_model_and_a_mounted_beam_table():
    m = LIDARS["hdl64e"]
    assert m.n_rings == 64 and m.n_azimuth == 2000
    assert m.elevation_deg[-1] == pytest.approx(2.84) and m.elevation_deg[0] == pytest.approx(-23.66)  # KITTI's unit
    assert np.all(np.diff(m.elevation_deg) > 0) and sorted(m.laser_to_ring) == list(range(64))
    T = mount_matrix(1.0, 0.5, 1.73, -90.0)
    beams = build_beam_table(m, T)
    assert len(beams.ring) == 64 * 2000 and beams.n_lasers == 64
    np.testing.assert_allclose(beams.T_vehicle_lidar, T)
    # rays that reach the ego body: the body lies behind the lidar (vehicle -x), the lidar's -y under this mount
    blocked = np.isfinite(beams.ego_range_m)
    assert blocked.any() and np.median(beams.dirs_lidar[blocked, 1]) < -0.3


def test_new_presets_and_typed_overrides():
    from pipeline.errors import ConfigError

    tc = get_preset("tiny_consumer")
    assert not tc.survey and not tc.gnss_attitude and tc.lidar_yaw_deg == -90.0 and tc.gnss_target_rms_m >= 2.0
    assert tc.n_cols == get_preset("tiny").n_cols and tc.max_scans_per_drive == 250  # the tiny city and drives
    kc = get_preset("kitti_city")
    assert kc.sensor == "hdl64e" and not kc.survey and kc.max_scans_per_drive == 154 and kc.lidar_z_m == 1.73
    p = get_preset("tiny", survey=0.0, sensor="hdl64e")
    assert p.survey is False and p.sensor == "hdl64e"
    with pytest.raises(ConfigError) as err:
        get_preset("tiny", survey=0.5, sensor="vlp16", lidar_x_m="a")
    text = str(err.value)
    assert "survey must be 0 or 1" in text and "sensor must be one of" in text and "lidar_x_m must be a number" in text
    for name in ("tiny", "demo", "gangnam"):  # the existing presets keep their meaning
        q = get_preset(name)
        assert q.survey and q.gnss_attitude and q.sensor == "hdl32e" and q.window_share == 0.0
        assert (q.lidar_x_m, q.lidar_y_m, q.lidar_z_m, q.lidar_yaw_deg) == (0.0, 0.0, 1.9, 0.0)


@pytest.mark.parametrize("name", ["tiny_consumer", "demo_consumer", "kitti_city"])
def test_packaged_workflows_of_the_new_presets_plan_from_any_folder(name, tmp_path):
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-m", "mapservice", "run", name, "--root", str(tmp_path / "r"), "--dry-run"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-800:]
    for stage in ("simulate", "ingest", "odometry", "posegraph", "corners", "cornermap", "markings", "evaluate"):
        assert stage in run.stdout
