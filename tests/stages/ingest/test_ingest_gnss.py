"""GNSS/INS: ENU cross-checked against pyproj, time stamps, CSV errors, headings, pose interpolation."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from pipeline.errors import FormatError
from stages.common.geodesy import EnuOrigin, geodetic_to_enu
from stages.ingest.csv_columns import read_csv_columns
from stages.ingest.drive_file import GnssSpec
from stages.ingest.gnss_csv import monotonic_mask, read_gnss, stamps_ns
from stages.ingest.pose_interpolation import attitude_from_rpy, interpolate_poses, vehicle_origin_from_reference
from stages.ingest.survey import crs_to_enu


def _enu_via_pyproj(lat, lon, h, origin: EnuOrigin) -> np.ndarray:
    from pyproj import Transformer

    to_ecef = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
    p = np.column_stack(to_ecef.transform(lon, lat, h))
    p0 = np.array(to_ecef.transform(origin.lon_deg, origin.lat_deg, origin.h_m))
    la, lo = np.radians(origin.lat_deg), np.radians(origin.lon_deg)
    R = np.array([[-np.sin(lo), np.cos(lo), 0],
                  [-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)],
                  [np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)]])
    return (p - p0) @ R.T


@settings(max_examples=60, deadline=None)
@given(lat0=st.floats(-80, 80), lon0=st.floats(-179, 179), h0=st.floats(-100, 3000),
       bearing=st.floats(0, 2 * np.pi), dist=st.floats(0, 20_000), dh=st.floats(-200, 200))
def test_geodetic_to_enu_matches_pyproj_within_1mm_inside_20km(lat0, lon0, h0, bearing, dist, dh):
    origin = EnuOrigin(lat0, lon0, h0)
    dlat = dist * np.cos(bearing) / 111_320.0
    dlon = dist * np.sin(bearing) / (111_320.0 * np.cos(np.radians(lat0)))
    lat, lon, h = np.array([lat0 + dlat]), np.array([lon0 + dlon]), np.array([h0 + dh])
    ours = geodetic_to_enu(lat, lon, h, origin)
    np.testing.assert_allclose(ours, _enu_via_pyproj(lat, lon, h, origin), atol=1e-3, rtol=0)


def test_projected_survey_to_enu_matches_utm_geometry():
    origin = EnuOrigin(35.1, 129.0, 20.0)  # Busan, UTM 52N
    from stages.common.geodesy import geodetic_to_projected

    x0, y0, _ = geodetic_to_projected(origin.lat_deg, origin.lon_deg, origin.h_m, "EPSG:32652")[0]
    enu = crs_to_enu(np.array([x0, x0 + 100.0]), np.array([y0, y0]), np.array([20.0, 20.0]), "EPSG:32652", origin)
    np.testing.assert_allclose(enu[0], 0.0, atol=1e-6)
    assert np.hypot(*enu[1, :2]) == pytest.approx(100.0 / 0.99962, rel=2e-3)  # UTM scale near the meridian


def test_stamps_keep_nanoseconds_with_gps_week():
    ns = stamps_ns(np.array([345600.123456789]), np.array([2200.0]))
    assert ns[0] == 2200 * 604_800 * 10**9 + 345_600_123_456_789


def test_non_monotonic_and_duplicate_rows_are_reported_by_record():
    keep, issues = monotonic_mask(np.array([1, 2, 2, 5, 4, 6], np.int64))
    assert keep.tolist() == [True, True, False, True, False, True]
    assert [(i.record, i.reason.split()[0]) for i in issues] == [(2, "duplicate"), (4, "timestamp")]


def test_wrong_column_count_names_the_lines(tmp_path):
    path = tmp_path / "g.csv"
    path.write_text("t,a,b\n1,2,3\n2,3\n3,4,5,6\n")
    with pytest.raises(FormatError, match=r"2 row\(s\) with the wrong number of columns: line 3: 2 values, "
                                          r"expected 3; line 4: 4 values"):
        read_csv_columns(path, ["t", "a", "b"])
    with pytest.raises(FormatError, match="lacks column"):
        read_csv_columns(path, ["t", "c"])


@pytest.mark.parametrize("convention,heading,expected_yaw", [
    ("azimuth_cw_from_north", 0.0, np.pi / 2), ("azimuth_cw_from_north", 90.0, 0.0),
    ("azimuth_cw_from_north", 180.0, -np.pi / 2), ("enu_yaw_ccw_from_east", 30.0, np.radians(30.0))])
def test_heading_conventions(tmp_path, convention, heading, expected_yaw):
    path = tmp_path / "g.csv"
    path.write_text(f"t,lat,lon,h,hd\n1.0,37.0,127.0,10.0,{heading}\n")
    spec = GnssSpec(file="g.csv", time={"column": "t"}, heading_convention=convention,
                    columns={"lat": "lat", "lon": "lon", "height": "h", "heading": "hd"})
    fixes, _ = read_gnss(path, spec)
    assert fixes.yaw_enu_rad[0] == pytest.approx(expected_yaw)


def test_interpolation_recovers_constant_rate_motion_and_flags_gaps():
    t_ns = np.array([0, 100, 200, 300, 2300, 2400], np.int64) * 10**6
    t_s = t_ns / 1e9
    yaw = 3.0 - 0.8 * t_s  # crosses +pi -> -pi? no: stays in range; wrap tested via the +pi seam below
    yaw = np.where(t_s > 0.15, yaw + 0.5, yaw)  # any values: a constant-rate segment between 0 and 0.1 s
    pos = np.column_stack([5.0 * t_s, -2.0 * t_s, np.zeros_like(t_s)])
    att = attitude_from_rpy(np.zeros(6), np.zeros(6), np.array([3.1, 3.1 + 0.2, 3.5, 3.6, 3.7, 3.8]))
    q = np.array([50, 1300, 2350, 5000], np.int64) * 10**6
    out = interpolate_poses(t_ns, pos, att, np.ones((6, 4)), q, max_gap_s=1.0)
    np.testing.assert_allclose(out.position_enu_m[0], [0.25, -0.1, 0.0], atol=1e-12)
    yaw_q = Rotation.from_quat(out.quat_xyzw).as_euler("ZYX")[:, 0]
    assert yaw_q[0] == pytest.approx(3.2 - 2 * np.pi, abs=1e-9)  # halfway across the +pi seam
    assert out.valid.tolist() == [True, False, True, False]


def test_lever_arm_moves_the_reference_point_to_the_vehicle_origin():
    att = attitude_from_rpy(np.zeros(1), np.zeros(1), np.array([np.pi / 2]))  # heading north
    vehicle = vehicle_origin_from_reference(np.array([[10.0, 20.0, 3.0]]), att, np.array([1.0, 0.0, 2.0]))
    np.testing.assert_allclose(vehicle, [[10.0, 19.0, 1.0]], atol=1e-12)
