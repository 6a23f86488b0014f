"""drive.yaml validation: strict, every problem at once, paths fenced to the drive's parent folder."""
from __future__ import annotations

import pytest
import yaml

from fixtures.ingest import write_synthetic_drive
from pipeline.errors import ConfigError, DatasetIOError
from stages.ingest.drive_file import load_drive_file


@pytest.fixture()
def drive(tmp_path):
    return write_synthetic_drive(tmp_path, n_scans=2, n_per_ring=10)


def _rewrite(drive_file, edit):
    raw = yaml.safe_load(drive_file.read_text())
    edit(raw)
    drive_file.write_text(yaml.safe_dump(raw))


def test_valid_drive_file_loads(drive):
    spec = load_drive_file(drive.drive_file)
    assert spec.sensor == "hdl32e" and spec.gnss.heading_convention == "azimuth_cw_from_north"
    assert spec.T_vehicle_lidar_matrix[2, 3] == pytest.approx(1.9)
    assert spec.stamps_file == drive.drive_file.parent / "scans" / "stamps.csv"


def test_every_problem_listed_at_once(drive):
    def edit(raw):
        raw["sensor"] = "hdl99"
        raw["colour"] = "red"
        raw["gnss"]["heading_convention"] = "clockwise"
        raw["T_vehicle_lidar"][3] = [0, 0, 1, 1]
        del raw["scan_rate_hz"]
    _rewrite(drive.drive_file, edit)
    with pytest.raises(ConfigError) as info:
        load_drive_file(drive.drive_file)
    text = str(info.value)
    assert "5 problems in" in text and str(drive.drive_file) in text
    for fragment in ("sensor", "colour: unknown key", "heading_convention", "T_vehicle_lidar", "scan_rate_hz"):
        assert fragment in text


def test_paths_escaping_the_parent_are_refused_and_missing_files_listed(drive):
    def edit(raw):
        raw["gnss"]["file"] = "../../etc/passwd"
        raw["odometry"]["file"] = "nope.csv"
        raw["survey"] = {"file": "../survey/survey.las", "crs": "EPSG:28992"}
    _rewrite(drive.drive_file, edit)
    with pytest.raises(ConfigError) as info:
        load_drive_file(drive.drive_file)
    problems = info.value.problems
    assert len(problems) == 3
    assert "outside the drive's parent folder" in problems[0] and "refused" in problems[0]
    assert "nope.csv does not exist" in problems[1] and "survey.las does not exist" in problems[2]


def test_missing_drive_file_is_a_dataset_io_error(tmp_path):
    with pytest.raises(DatasetIOError, match="cannot read drive file"):
        load_drive_file(tmp_path / "absent" / "drive.yaml")


def test_not_yaml(tmp_path):
    bad = tmp_path / "drive.yaml"
    bad.write_text("name: [unclosed\n")
    with pytest.raises(ConfigError, match=r"line 2, column 1: expected ','"):
        load_drive_file(bad)
