"""One ENU origin type: ``LAT,LON,H`` and mappings parse to the same origin, bad input is refused with every problem
named, and every "same frame" rule (a map's pinned origin, a trajectory's two statements, a version against its
parent) answers with the one tolerance."""

from __future__ import annotations

from pathlib import Path

import pytest

from mapformat.changelog import same_frame as same_tiling
from stages.common.geodesy import ORIGIN_TOL_DEG, ORIGIN_TOL_M, EnuOrigin, OriginError

ORIGIN = EnuOrigin(37.4979, 127.0276, 57.0)


def test_text_and_mapping_round_trip():
    assert EnuOrigin.parse("37.4979, 127.0276, 57") == ORIGIN
    assert EnuOrigin.parse(ORIGIN.text()) == ORIGIN
    assert (
        EnuOrigin.validate(ORIGIN.plain())
        == ORIGIN
        == EnuOrigin.validate(ORIGIN.as_dict())
        == EnuOrigin.from_dict(ORIGIN.as_dict())
    )
    assert EnuOrigin.validate({"lat_deg": 37.4979, "lon_deg": 127.0276}) == EnuOrigin(37.4979, 127.0276, 0.0)
    assert list(ORIGIN.plain()) == ["lat_deg", "lon_deg", "h_m"] and ORIGIN.as_dict()["ellipsoid"] == "WGS84"


@pytest.mark.parametrize(
    "text, words",
    [
        ("37.5,127", ["expected LAT,LON,H"]),
        ("a,b,c", ["expected LAT,LON,H"]),
        ("91,127,0", ["latitude 91.0 is outside -90..90 degrees"]),
        ("37,181,0", ["longitude 181.0 is outside -180..180 degrees"]),
        ("37,127,20000", ["height 20000.0 m is outside -1000..10000 m"]),
        ("nan,127,0", ["latitude nan"]),
        ("91,-181,-2000", ["latitude", "longitude", "height"]),
    ],
)
def test_bad_text_names_every_problem(text, words):
    with pytest.raises(OriginError) as err:
        EnuOrigin.parse(text)
    assert len(err.value.problems) == len(words)
    for problem, word in zip(err.value.problems, words):
        assert word in problem
    assert isinstance(err.value, ValueError)


def test_bad_mapping_names_every_problem():
    with pytest.raises(OriginError) as err:
        EnuOrigin.validate({"lat": 37.5, "lon_deg": "east", "h_m": True, "ellipsoid": "GRS80"})
    got = err.value.problems
    assert any("unknown key 'lat'" in p for p in got) and any("ellipsoid 'GRS80'" in p for p in got)
    assert any(p == "lat_deg: missing" for p in got) and any("lon_deg: expected a number" in p for p in got)
    assert any("h_m: expected a number" in p for p in got)
    with pytest.raises(OriginError, match="latitude 95.0"):
        EnuOrigin.validate({"lat_deg": 95.0, "lon_deg": 1.0, "h_m": 0.0, "extra": 1})
    with pytest.raises(OriginError, match="expected a mapping"):
        EnuOrigin.validate([37.5, 127.0, 57.0])


def test_same_frame_is_one_tolerance():
    inside = [
        EnuOrigin(ORIGIN.lat_deg + 0.9 * ORIGIN_TOL_DEG, ORIGIN.lon_deg, ORIGIN.h_m),
        EnuOrigin(ORIGIN.lat_deg, ORIGIN.lon_deg - 0.9 * ORIGIN_TOL_DEG, ORIGIN.h_m),
        EnuOrigin(ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.h_m + 0.9 * ORIGIN_TOL_M),
    ]
    outside = [
        EnuOrigin(ORIGIN.lat_deg + 3 * ORIGIN_TOL_DEG, ORIGIN.lon_deg, ORIGIN.h_m),
        EnuOrigin(ORIGIN.lat_deg, ORIGIN.lon_deg + 3 * ORIGIN_TOL_DEG, ORIGIN.h_m),
        EnuOrigin(ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.h_m - 3 * ORIGIN_TOL_M),
    ]
    for other in inside:
        assert ORIGIN.same_frame(other) and other.same_frame(ORIGIN) and same_tiling(ORIGIN, 100.0, other, 100.0), other
    for other in outside:
        assert not ORIGIN.same_frame(other) and not same_tiling(ORIGIN, 100.0, other, 100.0), other
    assert not same_tiling(ORIGIN, 100.0, ORIGIN, 50.0)


def _trajectory(path: Path, header: EnuOrigin, sidecar: EnuOrigin) -> Path:
    from stages.common.trajectory_frame import frame_header, write_sidecar

    path.write_text(f"# {frame_header(header)}\n0 0 0 0 0 0 0 1\n")
    write_sidecar(path, sidecar)
    return path


def test_a_trajectorys_two_statements_agree_by_the_same_rule(tmp_path):
    from pipeline.errors import FormatError
    from stages.common.trajectory_frame import read_trajectory_origin

    near = EnuOrigin(ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.h_m + 0.5 * ORIGIN_TOL_M)
    far = EnuOrigin(ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.h_m + 3 * ORIGIN_TOL_M)
    assert read_trajectory_origin(_trajectory(tmp_path / "a.txt", ORIGIN, near)) is not None
    with pytest.raises(FormatError, match="stale"):
        read_trajectory_origin(_trajectory(tmp_path / "b.txt", ORIGIN, far))


def test_a_pinned_map_refuses_an_origin_by_the_same_rule(tmp_path):
    from mapservice.maps import create_map, pinned_frame
    from pipeline.errors import ConfigError

    create_map(tmp_path, "city", ORIGIN.plain())
    near = EnuOrigin(ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.h_m + 0.5 * ORIGIN_TOL_M)
    far = EnuOrigin(ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.h_m + 3 * ORIGIN_TOL_M)
    assert pinned_frame(tmp_path, "city", near.plain()) == (ORIGIN.plain(), 100.0)
    with pytest.raises(ConfigError, match="would move its frame"):
        pinned_frame(tmp_path, "city", far.plain())
