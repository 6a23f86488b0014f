"""drive init tells sensors apart on scans written as the sensors write them (fixtures.ingest.write_sensor_scans: a
unit's table a few 0.01 deg off its model's) and says which it guessed and why; a calibration file in the folder
decides."""
from __future__ import annotations

import json

import pytest

from fixtures.ingest import write_sensor_scans
from stages.ingest.drive_init import draft_drive_file
from stages.ingest.sensors import SENSORS


def _sensor_line(folder) -> str:
    return next(line for line in draft_drive_file(folder).lines if line.startswith("sensor:"))


@pytest.mark.parametrize("sensor, organised, ring, why", [
    ("os1-64", True, False, "an organised cloud of 64 rows"),  # Ouster's driver: HEIGHT = beams, no ring field
    ("os2-128", False, True, "128 distinct ring ids"),
    ("os1-32-gradient", True, True, "32 distinct ring ids"),
    ("pandar64", False, True, "64 distinct ring ids"),
    ("pandarxt32", False, True, "32 distinct ring ids"),
    ("vlp32c", False, True, "32 distinct ring ids"),
])
def test_drive_init_guesses_the_sensor_and_says_why(tmp_path, sensor, organised, ring, why):
    write_sensor_scans(tmp_path, SENSORS[sensor].elevations_deg, organised=organised, ring=ring, seed=len(sensor))
    line = _sensor_line(tmp_path)
    assert line.startswith(f"sensor: {sensor}  # CHECK: guessed from the scans ("), line
    assert why in line and f"{sensor} ({SENSORS[sensor].label}) table RMS" in line and "next " in line, line


def test_beams_without_points_still_count(tmp_path):
    """Scans whose 4 lowest beams return nothing (the vehicle's roof) have 28 distinct ring ids of 0..31 (found on a
    keyframe drive of tiny seed 851: 'generic, no model has 28 beams')."""
    write_sensor_scans(tmp_path, SENSORS["hdl32e"].elevations_deg, body_beams=4)
    line = _sensor_line(tmp_path)
    assert line.startswith("sensor: hdl32e") and "28 distinct ring ids of 0..31" in line, line


def test_too_many_points_for_few_beams_is_no_vlp16(tmp_path):
    """16 beams of 5,000 points each: more than a sensor gives per beam and sweep (4,500), so no 16-beam model fits
    and the draft says generic instead of forcing VLP-16."""
    write_sensor_scans(tmp_path, SENSORS["vlp16"].elevations_deg, columns=5000, ring=True)
    assert _sensor_line(tmp_path).startswith("sensor: generic"), _sensor_line(tmp_path)


def test_a_metadata_file_in_the_folder_decides_and_is_named(tmp_path):
    write_sensor_scans(tmp_path, SENSORS["os1-64-uniform"].elevations_deg, organised=True, ring=False)
    (tmp_path / "os1_metadata.json").write_text(json.dumps({
        "beam_intrinsics": {"beam_altitude_angles": list(SENSORS["os1-64-uniform"].elevations_deg)[::-1]},
        "sensor_info": {"prod_line": "OS-1-64-U02"}}))
    lines = draft_drive_file(tmp_path).lines
    assert "sensor: os1-64-uniform  # from os1_metadata.json: prod_line OS-1-64-U02" in lines, lines
    assert any(line.startswith("calibration_file: os1_metadata.json") for line in lines)
