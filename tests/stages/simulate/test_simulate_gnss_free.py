"""The simulator's drives without GNSS (a start pose, a prior trajectory), keyframe drives and its Ouster: what the
drive file says is what the files hold, against the simulator's own truth."""
from __future__ import annotations

import numpy as np
import yaml

from stages.common.records import Trajectory
from stages.ingest.drive_check import check_drive
from stages.simulate.core import simulate
from stages.simulate.presets import get_preset


def _yaw(T):
    return np.arctan2(T[..., 1, 0], T[..., 0, 0])


def test_a_drive_without_gnss_with_a_local_prior_and_keyframes(tmp_path):
    p = get_preset("tiny", gnss=False, prior="local", keyframe_spacing_m=4.0, survey=False, prior_std_m=0.3)
    simulate(p, 331, tmp_path, 1, True, 25)
    d = tmp_path / "drive_0"
    doc = yaml.safe_load((d / "drive.yaml").read_text())
    assert "gnss" not in doc and not (d / "gnss_inspva.csv").exists()
    assert doc["prior"]["frame"] == "local" and doc["start"]["std_heading_deg"] == 0.3
    truth = Trajectory.from_tum(tmp_path / "truth" / "drive_0_poses_tum.txt").T
    step = np.linalg.norm(np.diff(truth[:, :2, 3], axis=0), axis=1)
    assert len(truth) == 25 and step.min() > 1.9 and step.max() < 6.5 and step.std() > 0.3  # 2-6 m, irregular
    prior = Trajectory.from_tum(d / "prior.txt").T
    assert np.allclose(prior[0], np.eye(4), atol=1e-6)  # the SLAM frame: the first pose
    in_map = truth[0] @ prior
    err = np.linalg.norm(in_map[:, :2, 3] - truth[:, :2, 3], axis=1)
    assert 0.0 < err.max() < 2.0  # the prior's drift (0.3 m stationary, heading 0.1 deg) over ~100 m
    # the start heading: the truth's within 4 sigma of its stated std
    heading = np.radians(90.0 - doc["start"]["heading_deg"])
    assert abs(np.degrees(np.angle(np.exp(1j * (heading - _yaw(truth[0])))))) < 4 * 0.3
    check = check_drive(d / "drive.yaml")
    assert check.problems == [] and check.warnings == [], (check.problems, check.warnings)
    assert any("frame: no GNSS; the local prior trajectory prior.txt" in s for s in check.summary), check.summary


def test_the_ouster_and_a_start_pose_alone(tmp_path):
    p = get_preset("tiny", gnss=False, sensor="os1-64", survey=False)
    simulate(p, 332, tmp_path, 1, True, 3)
    d = tmp_path / "drive_0"
    doc = yaml.safe_load((d / "drive.yaml").read_text())
    assert doc["sensor"] == "os1-64" and "prior" not in doc and "start" in doc
    check = check_drive(d / "drive.yaml")
    assert check.problems == [] and check.warnings == [], (check.problems, check.warnings)
    summary = "\n".join(check.summary)
    assert "frame: no GNSS; the start heading" in summary and "rings per scan 6" in summary, summary
