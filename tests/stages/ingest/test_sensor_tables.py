"""The sensors users have: every beam table is a table, Ouster's configuration rule holds on a unit published in two
configurations, and a sensor's own calibration file (Ouster metadata JSON, Velodyne db.xml, Hesai CSV) gives its
model's table back; malformed calibration files are named errors."""
from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from pipeline.errors import FormatError
from stages.common import beam_tables as bt
from stages.ingest.sensor_calibration import read_beam_calibration
from stages.ingest.sensors import SENSORS

COUNTS = {"vlp32c": 32, "pandar64": 64, "pandarxt32": 32, "os1-128": 128, "os2-128": 128, "os1-64": 64,
          "os1-64-uniform": 64, "os1-64-below-horizon": 64, "os1-32-uniform": 32, "os1-32-gradient": 32,
          "os1-32-below-horizon": 32, "os2-64-uniform": 64, "os2-64-below-horizon": 64, "os2-32-uniform": 32,
          "os2-32-below-horizon": 32}


@pytest.mark.parametrize("name", sorted(COUNTS))
def test_every_table_is_ascending_unique_and_of_its_beam_count(name):
    table = np.asarray(SENSORS[name].elevations_deg)
    assert len(table) == COUNTS[name] and np.all(np.diff(table) > 0)
    assert SENSORS[name].label and SENSORS[name].source


def test_tables_of_one_beam_count_differ_by_more_than_a_units_calibration():
    for n in (32, 64, 128):
        names = [k for k, m in SENSORS.items() if m.n_rings == n]
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                rms = np.sqrt(np.mean((np.subtract(SENSORS[a].elevations_deg, SENSORS[b].elevations_deg)) ** 2))
                assert rms > 0.5, (a, b, rms)


def test_ouster_configuration_rule_on_one_unit_published_in_two_configurations():
    """OS0 882002000138's 32-U0 metadata is every 2nd beam from the lowest of its 64-U02 metadata, the rule by which
    the 64- and 32-beam tables without a published example are taken from the 128-beam ones."""
    assert bt.lasers_from_lowest(bt.OS0_64_U02_CHECK, 2) == tuple(sorted(bt.OS0_32_U0_CHECK))
    assert bt.lasers_from_lowest(bt.OS0_64_U02_CHECK, 2, start=1) != tuple(sorted(bt.OS0_32_U0_CHECK))
    below = bt.lasers_from_lowest(bt.OS1_128, 1, lower_half=True)
    assert len(below) == 64 and max(below) < 0


def _ouster_legacy(path, table, prod_line):
    path.write_text(json.dumps({"beam_altitude_angles": list(table)[::-1],
                                "beam_azimuth_angles": [1.0] * len(table), "prod_line": prod_line,
                                "lidar_mode": "1024x10"}))


def _ouster_v2(path, table, prod_line):
    path.write_text(json.dumps({"beam_intrinsics": {"beam_altitude_angles": list(table)[::-1],
                                                    "beam_azimuth_angles": [3.0] * len(table)},
                                "sensor_info": {"prod_line": prod_line}}, indent=4))


@pytest.mark.parametrize("writer", [_ouster_legacy, _ouster_v2])
@pytest.mark.parametrize("name", ["os1-64", "os2-128", "os1-32-gradient"])
def test_a_table_read_from_an_ouster_metadata_json_equals_the_models(tmp_path, writer, name):
    path = tmp_path / "metadata.json"
    writer(path, SENSORS[name].elevations_deg, SENSORS[name].label)
    cal = read_beam_calibration(path)
    assert cal.elevations_deg == pytest.approx(SENSORS[name].elevations_deg, abs=1e-12)
    assert cal.model == name and cal.kind == "ouster_metadata" and SENSORS[name].label in cal.why


def test_a_legacy_ouster_file_lists_unused_slots_as_zeros(tmp_path):
    """OS-1-32-A02 metadata (firmware 1.13) lists 64 slots, every other one (altitude 0, azimuth 0) unused."""
    table = SENSORS["os1-32-gradient"].elevations_deg
    alt, az = [], []
    for v in table[::-1]:
        alt += [0, v]
        az += [0, 0.9]
    path = tmp_path / "m.json"
    path.write_text(json.dumps({"beam_altitude_angles": alt, "beam_azimuth_angles": az, "prod_line": "OS-1-32-A02"}))
    cal = read_beam_calibration(path)
    assert len(cal.elevations_deg) == 32 and cal.model == "os1-32-gradient"  # nearest table (no such prod_line)


def test_velodyne_db_xml_and_hesai_csv_give_their_models(tmp_path):
    items = "".join(f"<item><px><id_>{i}</id_><rotCorrection_>-1.4</rotCorrection_><vertCorrection_>{v}"
                    f"</vertCorrection_></px></item>" for i, v in enumerate(list(bt.VLP32C) + [0.0] * 32))
    enabled = "".join(f"<item>{int(i < 32)}</item>" for i in range(64))
    (tmp_path / "db.xml").write_text(f'<?xml version="1.0"?><boost_serialization><DB><enabled_><count>64</count>'
                                     f"{enabled}</enabled_><points_><count>64</count>{items}</points_></DB>"
                                     "</boost_serialization>")
    cal = read_beam_calibration(tmp_path / "db.xml")
    assert cal.model == "vlp32c" and cal.elevations_deg == tuple(sorted(bt.VLP32C))
    rows = ["Channel,Elevation,Azimuth"] + [f"{i + 1},{v},0.0" for i, v in enumerate(bt.PANDAR64)]
    (tmp_path / "correction.csv").write_text("\n".join(rows) + "\n")
    cal = read_beam_calibration(tmp_path / "correction.csv")
    assert cal.model == "pandar64" and cal.kind == "hesai_csv" and "RMS 0.00" in cal.why


@pytest.mark.parametrize("name, text, match", [
    ("m.json", '{"beam_altitude_angles": [1.0, 2.0,\n  oops]}', r"m\.json: line 2: not JSON"),
    ("m.json", '{"lidar_mode": "1024x10"}', "no beam_altitude_angles"),
    ("m.json", '{"beam_altitude_angles": [1.0, "x", 3.0]}', "not a number"),
    ("m.json", '{"beam_altitude_angles": [1.0, 95.0, 3.0]}', r"beam_altitude_angles\[1\] = 95.0"),
    ("m.json", '{"beam_altitude_angles": [1.0, 1.0, 3.0]}', "share an elevation"),
    ("db.xml", "<DB><points_></points_></DB>", "no points_/px items"),
    ("db.xml", "<DB><points_>", r"db\.xml: line 1: not XML"),
    ("c.csv", "Channel,Elevation,Azimuth\n1,2.0,0\n2,abc,0\n", r"c\.csv: line 3: .* no number in the Elevation"),
    ("c.csv", "Laser,Angle\n1,2\n", r"line 1 .*expected a header naming Elevation"),
    ("m.yaml", "x: 1", "unknown calibration file type"),
])
def test_malformed_calibration_files_are_named_errors(tmp_path, name, text, match):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(FormatError, match=match):
        read_beam_calibration(path)


def test_the_drive_file_takes_the_calibration_files_table(tmp_path):
    from stages.ingest.drive_file import load_drive_file
    from stages.ingest.scan_pass import elevation_table

    (tmp_path / "scans").mkdir()
    _ouster_v2(tmp_path / "meta.json", SENSORS["os2-128"].elevations_deg, "OS-2-128")
    doc = {"name": "d", "sensor": "os2-128", "calibration_file": "meta.json", "scans": {"folder": "scans",
           "format": "pcd"}, "scan_rate_hz": 10, "T_vehicle_lidar": np.eye(4).tolist()}
    (tmp_path / "drive.yaml").write_text(yaml.safe_dump(doc))
    assert elevation_table(load_drive_file(tmp_path / "drive.yaml")) == SENSORS["os2-128"].elevations_deg
    doc["sensor"] = "os1_64"
    (tmp_path / "drive.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(Exception, match=r"unknown sensor 'os1_64'.*did you mean 'os1-64'"):
        load_drive_file(tmp_path / "drive.yaml")
