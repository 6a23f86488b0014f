"""Queries where the vehicle is (mapformat/query.py, MapReader.query_latlon / query_pose, `cornermap tiles query`):
by latitude / longitude the same corners as the ENU radius query, their lat/lon those of the GeoJSON export and of
pyproj, a field of view keeps the corners in its sector, the CLI's JSON and one-line errors."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from mapformat.loader import open_map
from stages.common.geodesy import enu_to_geodetic
from stages.tiles.compute import compute
from tests.stages.tiles.tiles_synth import ORIGIN, building_corners, buildings, city_context, corner_table


@pytest.fixture(scope="module")
def city(tmp_path_factory):
    root = tmp_path_factory.mktemp("query")
    xy, dirs, _ = building_corners(buildings())
    compute(city_context(root, corner_table(xy, dirs, seed=1)))
    return root, open_map(root / "maps" / "city")


def _latlon(e: float, n: float) -> tuple[float, float]:
    lat, lon, _ = enu_to_geodetic(np.array([[e, n, 0.0]]), ORIGIN)[0]
    return float(lat), float(lon)


def test_a_latlon_query_is_the_enu_radius_query_with_wgs84_positions(city, tmp_path):
    from pyproj import Transformer

    from mapformat.export import export_map

    _, m = city
    lat, lon = _latlon(150.0, 120.0)
    q = m.query_latlon(lat, lon, 60.0)
    assert q.east_m == pytest.approx(150.0, abs=1e-3) and q.north_m == pytest.approx(120.0, abs=1e-3)
    ref = m.corners_within(150.0, 120.0, 60.0)
    assert sorted(q.corners["corner_id"].to_pylist()) == sorted(ref["corner_id"].to_pylist()) and ref.num_rows > 10
    # lat/lon of each corner: the GeoJSON export's, and pyproj's ENU (topocentric) -> WGS84 of the same point
    export_map(m, "geojson", tmp_path / "c.geojson")
    gj = {f["properties"]["corner_id"]: f["geometry"]["coordinates"] for f in
          json.loads((tmp_path / "c.geojson").read_text())["features"]}
    topo = Transformer.from_pipeline(
        f"+proj=pipeline +step +inv +proj=topocentric +ellps=WGS84 +lat_0={ORIGIN.lat_deg} +lon_0={ORIGIN.lon_deg} "
        f"+h_0={ORIGIN.h_m} +step +inv +proj=cart +ellps=WGS84")
    for c in q.corners.to_pylist():
        assert gj[c["corner_id"]][:2] == pytest.approx([c["lon_deg"], c["lat_deg"]], abs=1e-9)
        lon_p, lat_p, _ = topo.transform(c["east_m"], c["north_m"], 0.0)
        assert (lat_p, lon_p) == pytest.approx((c["lat_deg"], c["lon_deg"]), abs=1e-9)
    mask, (e_sw, n_sw), cell = q.marking
    assert mask.shape[0] in (240, 241) and mask.shape[1] in (240, 241)  # 120 m at 0.5 m, to whole cells
    assert (e_sw, n_sw) == pytest.approx((90.0, 60.0), abs=cell)
    cells = q.localizability
    assert cells.num_rows and (np.hypot(cells["east_m"].to_numpy() - q.east_m, cells["north_m"].to_numpy()
                                        - q.north_m) <= 60.0).all()


def test_a_pose_with_a_field_of_view_keeps_the_corners_in_its_sector(city):
    _, m = city
    q = m.query_pose(150.0, 150.0, np.pi / 2, np.radians(90.0), 80.0)  # looking north, 90 deg wide
    ref = m.corners_within(150.0, 150.0, 80.0)
    d_e, d_n = ref["east_m"].to_numpy() - 150.0, ref["north_m"].to_numpy() - 150.0
    inside = np.abs(np.degrees(np.arctan2(d_n, d_e)) - 90.0) <= 45.0
    assert sorted(q.corners["corner_id"].to_pylist()) == sorted(ref["corner_id"].to_numpy()[inside].tolist())
    assert 0 < q.corners.num_rows < ref.num_rows
    q_all = m.query_latlon(*_latlon(150.0, 150.0), 80.0, heading_deg=90.0, fov_deg=360.0)
    assert q_all.corners.num_rows == ref.num_rows


def test_the_cli_answers_in_json_and_refuses_bad_input_in_one_line(city):
    root, m = city
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    lat, lon = _latlon(150.0, 120.0)
    cli = [sys.executable, "-m", "mapservice", "tiles", "query", "--root", str(root), "--map", "city"]
    res = subprocess.run(cli + ["--at", f"{lat:.10f},{lon:.10f}", "--radius", "60", "--json"], capture_output=True,
                         text=True, env=env)
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    assert doc["version"] == m.version and doc["at"]["east_m"] == pytest.approx(150.0, abs=1e-3)
    assert sorted(c["corner_id"] for c in doc["corners"]) == sorted(m.corners_within(150.0, 120.0, 60.0)[
        "corner_id"].to_pylist())
    assert {"lat_deg", "lon_deg", "theta1_deg", "cov_en_m2"} <= set(doc["corners"][0])
    assert doc["marking_window"]["cell_m"] == 0.5 and doc["localizability"]
    for args, want in ((["--at", "37.5"], "--at"), (["--at", f"{lat},{lon}", "--radius", "0"], "radius 0.0 m"),
                       (["--at", "95,127", "--radius", "5"], "latitude 95.0")):
        bad = subprocess.run(cli + args, capture_output=True, text=True, env=env)
        assert bad.returncode != 0 and want in bad.stderr and len(bad.stderr.strip().splitlines()) == 1 \
            and "Traceback" not in bad.stderr, bad.stderr
