"""Inputs as they come: GNSS rows rejected one by one, std defaults instead of NaN, roll/pitch flagged when
absent, scan ids from file names (a gap stays a gap), stamps rows range-checked, truncated scans' rings."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.errors import FormatError
from stages.ingest.csv_columns import read_csv_columns
from stages.ingest.drive_file import GnssSpec
from stages.ingest.gnss_csv import GnssLimits, read_gnss, read_scan_stamps
from stages.ingest.scan_pass import scan_numbers
from stages.ingest.sensors import SENSORS, ring_coverage, rings_from_point_order

OXTS = GnssSpec.model_validate({"file": "g.csv", "time": {"column": "time", "base": "unix"},
                                "columns": {"lat": "lat", "lon": "lon", "height": "alt", "heading": "yaw"},
                                "angle_unit": "rad", "heading_convention": "enu_yaw_ccw_from_east"})


def _csv(tmp_path: Path, rows: list[str], header: str = "time,lat,lon,alt,yaw") -> Path:
    path = tmp_path / "g.csv"
    path.write_text(header + "\n" + "\n".join(rows) + "\n")
    return path


def _track(n: int = 10) -> list[str]:
    return [f"{100 + 0.1 * i:.1f},{49.0 + 1e-6 * i:.7f},8.4,115.0,0.5" for i in range(n)]


def test_oxts_without_std_or_roll_pitch_gets_defaults_and_a_flag(tmp_path):
    fixes, issues = read_gnss(_csv(tmp_path, _track()), OXTS, GnssLimits(default_std_enu_m=(1.5, 1.6, 2.5)))
    assert issues == [] and len(fixes.stamp_ns) == 10
    assert np.isfinite(fixes.std_enu_m).all() and np.allclose(fixes.std_enu_m, [1.5, 1.6, 2.5])
    assert np.isfinite(fixes.std_yaw_rad).all()
    assert fixes.roll_pitch_known is False
    assert set(fixes.defaults_used) == {"std_east", "std_north", "std_up", "std_heading"}


def test_a_non_numeric_cell_rejects_its_row_only(tmp_path):
    rows = _track()
    rows[4] = rows[4].replace("115.0", "abc")
    fixes, issues = read_gnss(_csv(tmp_path, rows), OXTS)
    assert len(fixes.stamp_ns) == 9 and 4 not in fixes.records
    assert [(i.record, "'abc' is not a number" in i.reason) for i in issues] == [(4, True)]


def test_read_csv_columns_still_names_a_bad_cell_without_a_row_sink(tmp_path):
    with pytest.raises(FormatError, match=r"record 1 \(line 3\), column 'alt': 'x'"):
        read_csv_columns(_csv(tmp_path, ["1,49,8,1,0", "2,49,8,x,0"]), ["time", "alt"])


@pytest.mark.parametrize("edit, reason", [
    (lambda r: r.replace("49.0000040", "137.5"), "latitude outside"),
    (lambda r: r.replace(",8.4,", ",208.4,"), "longitude outside"),
    (lambda r: r.replace("115.0", "25000.0"), "height outside"),
    (lambda r: r.replace("49.0000040", "49.0100000"), "position jumps"),  # 1.1 km in 0.1 s
])
def test_out_of_range_rows_are_rejected_with_a_reason(tmp_path, edit, reason):
    rows = _track()
    rows[4] = edit(rows[4])
    fixes, issues = read_gnss(_csv(tmp_path, rows), OXTS)
    assert 4 not in fixes.records and len(fixes.stamp_ns) == 9
    assert [i.record for i in issues] == [4] and reason in issues[0].reason, issues


def test_degrees_declared_as_radians_are_rejected_not_placed_thousands_of_km_away(tmp_path):
    spec = OXTS.model_copy(update={"latlon_unit": "rad"})
    fixes, issues = read_gnss(_csv(tmp_path, _track()), spec)
    assert len(fixes.stamp_ns) == 0 and len(issues) == 10 and "latlon_unit rad" in issues[0].reason


def test_a_bad_first_fix_does_not_reject_the_rest(tmp_path):
    rows = _track()
    rows[0] = rows[0].replace("49.0000000", "49.5000000")  # 55 km away
    fixes, issues = read_gnss(_csv(tmp_path, rows), OXTS)
    assert list(fixes.records) == list(range(1, 10)) and [i.record for i in issues] == [0]


def test_scan_numbers_come_from_file_names():
    names = [Path(f"{i:010d}.pcd") for i in (0, 1, 2, 4, 5)]
    assert scan_numbers(names) == [0, 1, 2, 4, 5]
    assert scan_numbers([Path("a.pcd"), Path("b.pcd")]) is None  # no numbers: the listing decides
    assert scan_numbers([Path("s_1.pcd"), Path("t_1.pcd")]) is None  # not unique


def test_stamps_rows_are_range_checked_without_allocating_to_the_largest_id(tmp_path):
    path = tmp_path / "stamps.csv"
    path.write_text("scan_id,stamp_ns\n0,1000\n1,2000\n30000000000,3000\n-1,4000\n1,5000\n2,\n")
    stamps, issues = read_scan_stamps(path, None, max_scan_id=100_000_000)
    assert stamps == {0: 1000, 1: 2000}
    assert [i.record for i in issues] == [2, 3, 4, 5]
    assert "listed twice" in issues[2].reason


def test_truncated_kitti_scan_gets_its_rings_from_the_elevation_table(shared_data):
    from stages.ingest.pcd import read_pcd
    from stages.ingest.scan_formats import drop_invalid_points, points_from_pcd

    table = SENSORS["hdl64e"].elevations_deg
    p = drop_invalid_points(points_from_pcd(read_pcd(shared_data / "kitti_raw_0048_city" / "0000000003.pcd")))[0]
    full = rings_from_point_order(p.x_m, p.y_m, p.z_m, elevations_deg=table)
    assert sorted(set(full.tolist())) == list(range(64))
    for low, high in ((11, 64), (0, 55), (5, 59)):  # only the top 53 beams; only the bottom 55; both cut
        keep = (full >= low) & (full < high)
        rings = rings_from_point_order(p.x_m[keep], p.y_m[keep], p.z_m[keep], elevations_deg=table)
        assert np.array_equal(rings, full[keep]), (low, high)
    # Without the table the rank is all a truncated scan has: shifted by the missing beams.
    keep = full >= 11
    assert np.array_equal(rings_from_point_order(p.x_m[keep], p.y_m[keep], p.z_m[keep]), full[keep] - 11)


def test_a_yaml_alias_bomb_in_a_drive_file_is_refused_at_once(tmp_path):
    """Issue 22 finding 5: a 1 kB 'billion laughs' drive file took 30 s and ~3 GB before a MemoryError."""
    from pipeline.errors import ConfigError
    from pipeline.fingerprint import drive_fingerprint
    from stages.ingest.drive_file import load_drive_file

    lines = ['a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for n in range(1, 9):
        lines.append(f"{chr(97 + n)}: &{chr(97 + n)} [" + ",".join([f"*{chr(96 + n)}"] * 9) + "]")
    bomb = tmp_path / "drive.yaml"
    bomb.write_text("\n".join(lines) + "\nname: x\n")
    with pytest.raises(ConfigError, match="alias"):  # refused at the first alias: nothing is expanded
        load_drive_file(bomb)
    assert drive_fingerprint(bomb)  # the fingerprint of such a folder is computed without expanding it


def test_a_duplicate_key_in_a_drive_file_is_named(tmp_path):
    from pipeline.errors import ConfigError
    from stages.ingest.drive_file import load_drive_file

    path = tmp_path / "drive.yaml"
    path.write_text("name: a\nsensor: hdl32e\nname: b\n")
    with pytest.raises(ConfigError, match="name"):
        load_drive_file(path)


@pytest.mark.parametrize("rings", [np.random.default_rng(3).integers(-1, 32, 45_000).astype(np.int16),
                                   np.array([], np.int16), np.array([-1, -1], np.int16),
                                   np.array([5, 70_000, 3], np.int64), np.array([0, 63, 63, 7])])
def test_ring_coverage_counts_as_np_unique(rings):
    """The counted ring coverage equals the sort-based one (np.unique), unassigned (-1) rings left out, ids beyond
    the counting range included."""
    present = np.unique(rings[rings >= 0])
    assert ring_coverage(rings, 64) == (int(present.size), sorted(set(range(64)) - set(present.tolist())))
