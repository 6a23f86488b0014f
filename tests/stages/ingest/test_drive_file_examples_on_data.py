"""The drive-file examples of the sensors users have, the GNSS-free drive with a prior and the keyframe drive
(docs/drive-file.md) on simulated files named as the examples name them: drive check passes each and says what
places it and where its beam table comes from."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from fixtures.ingest import write_sensor_scans
from stages.common.geometry import write_kitti, write_tum
from stages.ingest.drive_check import check_drive
from stages.ingest.sensors import SENSORS

DOC = Path(__file__).resolve().parents[3] / "docs" / "drive-file.md"
T0 = 1_690_000_000.0


def _example(title: str) -> str:
    text = DOC.read_text()
    section = text[text.index(f"### {title}"):]
    return re.search(r"```yaml\n(.*?)```", section, re.S).group(1)


def _track(n: int) -> np.ndarray:
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = 5.5 * np.arange(n)
    return T


def _write(folder: Path, text: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "drive.yaml").write_text(text)
    return folder / "drive.yaml"


def _stamps(path: Path, n: int, step_s: float) -> np.ndarray:
    t = T0 + step_s * np.arange(n)
    path.write_text("".join(f"{v:.6f}\n" for v in t))
    return t


def test_the_ouster_example(tmp_path):
    d = tmp_path / "ouster_0"
    write_sensor_scans(d, SENSORS["os1-64"].elevations_deg, n_scans=4, organised=True, ring=True, subfolder="points")
    (d / "os1_metadata.json").write_text(json.dumps({
        "beam_intrinsics": {"beam_altitude_angles": list(SENSORS["os1-64"].elevations_deg)[::-1]},
        "sensor_info": {"prod_line": "OS-1-64"}}))
    _stamps(d / "points" / "stamps.txt", 4, 0.1)
    header = ["%time", "field.header.stamp", "field.latitude", "field.longitude", "field.altitude", "yaw_enu_rad"] + \
        [f"field.position_covariance{i}" for i in range(9)]
    rows = [[int(s * 1e9) + 5, int(s * 1e9), 37.5 + 1e-6 * k, 127.0, 60.0, 0.3, 0.04, 0, 0, 0, 0.04, 0, 0, 0, 0.09]
            for k, s in enumerate(T0 - 1 + 0.05 * np.arange(200))]
    (d / "ins_fix.csv").write_text(",".join(header) + "\n" + "\n".join(",".join(map(str, r)) for r in rows))
    check = check_drive(_write(d, _example("An Ouster drive with its metadata")))
    assert check.problems == [], check.problems
    summary = "\n".join(check.summary)
    assert "beam table: 64 beams -16.68..16.73 deg from os1_metadata.json (ouster_metadata; prod_line OS-1-64)" in \
        summary and "rings per scan 64-64 of 64" in summary and "covers 4 of 4 scan stamps" in summary, summary


def test_the_gnss_free_example_with_a_prior(tmp_path):
    d = tmp_path / "campus_0"
    write_sensor_scans(d, SENSORS["os1-64"].elevations_deg, n_scans=5, organised=True, ring=True)
    t = _stamps(d / "scans" / "times.txt", 5, 0.1)
    write_tum(d / "slam_poses_tum.txt", t, _track(5))
    check = check_drive(_write(d, _example("A drive without GNSS, with a prior trajectory")))
    assert check.problems == [] and check.warnings == [], (check.problems, check.warnings)
    summary = "\n".join(check.summary)
    assert "frame: no GNSS; the local prior trajectory slam_poses_tum.txt aligned at the start heading 87 deg" in \
        summary and "a pose for 5 of 5 scans" in summary, summary


def test_the_keyframe_example(tmp_path):
    d = tmp_path / "keyframes_0"
    write_sensor_scans(d, SENSORS["hdl32e"].elevations_deg, n_scans=6, ring=True, subfolder="keyframes")
    _stamps(d / "keyframes" / "times.txt", 6, 1.2)
    write_kitti(d / "keyframe_poses_kitti.txt", _track(6))
    check = check_drive(_write(d, _example("A keyframe drive")))
    assert check.problems == [] and check.warnings == [], (check.problems, check.warnings)
    summary = "\n".join(check.summary)
    assert "frame: no GNSS; the prior trajectory keyframe_poses_kitti.txt in ENU about 37.4979000" in summary
    assert "a pose for 6 of 6 scans" in summary and "time span 6.0 s" in summary, summary


@pytest.mark.parametrize("title", ["An Ouster drive with its metadata", "A drive without GNSS, with a prior trajectory",
                                   "A keyframe drive", "A KITTI raw sequence, as KITTI publishes it"])
def test_the_examples_are_drive_files(title):
    from stages.ingest.drive_file import DriveSpec

    DriveSpec.model_validate(yaml.safe_load(_example(title)))
