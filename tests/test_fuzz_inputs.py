"""Fuzz targets (hypothesis) for the readers of untrusted input: PCD, LAS, CSV, the map manifest and YAML.

Each asserts that any input ends either in a result or in a named error (a CornermapError), within a
bounded time (hypothesis ``deadline``) and bounded traced memory. Budgets are small so that the default
suite stays fast; a longer campaign: CORNERMAP_FUZZ_EXAMPLES=500 pytest tests/test_fuzz_inputs.py"""
from __future__ import annotations

import json
import os
import tracemalloc
import warnings
from contextlib import contextmanager

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.errors import CornermapError, FormatError

FUZZ = settings(max_examples=int(os.environ.get("CORNERMAP_FUZZ_EXAMPLES", 40)), deadline=10_000,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
PEAK_BYTES = 64 << 20


@contextmanager
def bounded_memory(limit: int = PEAK_BYTES):
    tracemalloc.start()
    try:
        yield
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < limit, f"peak traced memory {peak} bytes"


def _mutate(buf: bytes, data) -> bytes:
    """Truncate, overwrite or insert bytes, or rewrite a header number into a huge or negative one."""
    buf = bytearray(buf)
    mode = data.draw(st.sampled_from(["truncate", "flip", "insert", "number"]))
    at = data.draw(st.integers(0, max(0, len(buf) - 1)))
    if mode == "truncate":
        return bytes(buf[:at])
    if mode == "flip":
        for _ in range(data.draw(st.integers(1, 8))):
            buf[data.draw(st.integers(0, len(buf) - 1))] = data.draw(st.integers(0, 255))
        return bytes(buf)
    if mode == "insert":
        return bytes(buf[:at] + data.draw(st.binary(max_size=64)) + buf[at:])
    digits = [i for i, b in enumerate(buf[:400]) if chr(b).isdigit()]
    if not digits:
        return bytes(buf)
    i = data.draw(st.sampled_from(digits))
    big = str(data.draw(st.sampled_from([0, -1, 2**31, 2**40, 10**18]))).encode()
    return bytes(buf[:i] + big + buf[i + 1:])


# -- PCD --------------------------------------------------------------------------------------------------
@FUZZ
@given(encoding=st.sampled_from(["ascii", "binary", "binary_compressed"]), data=st.data())
def test_pcd_reader(encoding, data):
    from stages.ingest.pcd import decode_pcd, encode_pcd
    from stages.ingest.scan_formats import points_from_pcd

    rng = np.random.default_rng(0)
    cols = {"x": rng.normal(size=30).astype(np.float32), "y": rng.normal(size=30).astype(np.float32),
            "z": rng.normal(size=30).astype(np.float32), "intensity": rng.random(30).astype(np.float32)}
    buf = _mutate(encode_pcd(cols, encoding), data)
    with bounded_memory():
        try:
            points = points_from_pcd(decode_pcd(buf, "fuzz.pcd"), "fuzz.pcd")
        except CornermapError:
            return
    assert len(points.x_m) == len(points.y_m) == len(points.intensity)


# -- LAS --------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def las_bytes(tmp_path_factory) -> bytes:
    import laspy

    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales = np.array([0.001, 0.001, 0.001])
    las = laspy.LasData(header)
    rng = np.random.default_rng(1)
    las.x, las.y, las.z = rng.uniform(0, 100, 50), rng.uniform(0, 100, 50), rng.uniform(0, 10, 50)
    las.intensity = rng.integers(0, 255, 50)
    las.gps_time = np.arange(50) * 0.001
    path = tmp_path_factory.mktemp("las") / "a.las"
    las.write(path)
    return path.read_bytes()


@FUZZ
@given(data=st.data())
def test_las_reader(las_bytes, tmp_path, data):
    from stages.ingest.scan_formats import read_las_points

    path = tmp_path / "fuzz.las"
    path.write_bytes(_mutate(las_bytes, data))
    with bounded_memory():
        try:
            points = read_las_points(path)
        except CornermapError:
            return
    assert len(points.x_m) == len(points.z_m)


@pytest.mark.parametrize("version", ["1.2", "1.4"])
def test_las_with_a_corrupt_record_count_is_a_format_error(tmp_path, version):
    """A header announcing 4 billion (extended) variable-length records: named, with bounded memory (laspy read
    them one by one from the in-memory stream and grew without bound; the fuzz target above found it)."""
    import struct

    import laspy

    from stages.ingest.scan_formats import read_las_points

    las = laspy.LasData(laspy.LasHeader(point_format=1, version=version))
    las.x, las.y, las.z = np.arange(5.0), np.arange(5.0), np.arange(5.0)
    path = tmp_path / "a.las"
    las.write(path)
    raw = bytearray(path.read_bytes())
    fields = [(100, "<I")] + ([(243, "<I")] if version == "1.4" else [])
    for at, fmt in fields:
        bad = bytearray(raw)
        struct.pack_into(fmt, bad, at, 0xFFFFFFFF)
        path.write_bytes(bytes(bad))
        with bounded_memory(), pytest.raises(FormatError, match="variable-length records"):
            read_las_points(path)


def test_las_scan_with_a_broken_gps_time_keeps_its_points_without_times(tmp_path):
    """A LAS scan whose gps_time holds 1e233 s for one point (the fuzz target above found it: the float32 cast
    overflowed to inf with a RuntimeWarning and the point would have been deskewed to infinity): its points are kept
    without times, and the reason names the point; absolute GPS times of a sweep become offsets from its first point."""
    import laspy

    from stages.ingest.scan_formats import read_las_points

    las = laspy.LasData(laspy.LasHeader(point_format=1, version="1.2"))
    las.x, las.y, las.z = np.arange(5.0), np.arange(5.0), np.arange(5.0)
    las.gps_time = 3.1e5 + np.array([0.0, 0.025, 0.05, 0.075, 0.1])
    path = tmp_path / "a.las"
    las.write(path)
    np.testing.assert_allclose(read_las_points(path).time_offset_s, [0.0, 0.025, 0.05, 0.075, 0.1], atol=1e-6)
    las.gps_time = np.array([3.1e5, 3.1e5, 1e233, 3.1e5, 3.1e5])
    las.write(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        points = read_las_points(path)
    assert points.time_offset_s is None and len(points) == 5
    assert points.time_unused.startswith("gps_time of point 2 lies 1e+233 s from the scan start")


@pytest.mark.parametrize("version", ["1.2", "1.4"])
def test_survey_with_a_corrupt_record_count_is_a_format_error(tmp_path, version):
    """The same corrupt counts in a survey cloud, which is streamed from its file (not read into memory): laspy read
    4 billion records for 65 s and 2.4 GB before the points; now a named error from the header alone."""
    import struct

    import laspy

    from stages.common.geodesy import EnuOrigin
    from stages.ingest.survey import iter_survey_enu

    las = laspy.LasData(laspy.LasHeader(point_format=1, version=version))
    las.header.offsets = np.array([500000.0, 4000000.0, 0.0])
    las.x, las.y, las.z = 500000.0 + np.arange(5.0), 4000000.0 + np.arange(5.0), np.arange(5.0)
    path = tmp_path / "survey.las"
    las.write(path)
    raw = bytearray(path.read_bytes())
    origin = EnuOrigin(36.1, 129.0, 0.0)
    assert sum(len(e) for e, _ in iter_survey_enu(path, "EPSG:32652", origin)) == 5  # the intact file reads
    fields = [(100, "<I")] + ([(243, "<I")] if version == "1.4" else [])
    for at, fmt in fields:
        bad = bytearray(raw)
        struct.pack_into(fmt, bad, at, 0xFFFFFFFF)
        path.write_bytes(bytes(bad))
        with bounded_memory(), pytest.raises(FormatError, match=r"survey.las: header announces 4294967295"):
            list(iter_survey_enu(path, "EPSG:32652", origin))


# -- CSV --------------------------------------------------------------------------------------------------
CSV = ("gps_week,gps_seconds,latitude_deg,longitude_deg\n"
       + "".join(f"2200,{345600 + k * 0.01:.2f},37.5{k:03d},127.0{k:03d}\n" for k in range(20)))


@FUZZ
@given(data=st.data())
def test_csv_reader(tmp_path, data):
    from stages.ingest.csv_columns import read_csv_columns

    path = tmp_path / "fuzz.csv"
    path.write_bytes(_mutate(CSV.encode(), data))
    names = ["gps_week", "gps_seconds", "latitude_deg", "longitude_deg"]
    with bounded_memory():
        try:
            cols = read_csv_columns(path, names)
        except CornermapError:
            return
    assert len({len(v) for v in cols.values()}) == 1


# -- map manifest -----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def published(tmp_path_factory):
    from stages.tiles.compute import compute
    from tests.stages.tiles.tiles_synth import building_corners, buildings, city_context, corner_table

    root = tmp_path_factory.mktemp("fuzzmap")
    xy, dirs, _ = building_corners(buildings())
    compute(city_context(root, corner_table(xy, dirs, seed=3)))
    return root / "maps" / "city" / "v0001"


json_values = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
                           lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=8), c, max_size=4),
                           max_leaves=20)


@FUZZ
@given(data=st.data())
def test_manifest_reader_and_loader(published, tmp_path, data):
    import shutil

    from mapformat.loader import open_map
    from mapformat.verify import verify_map

    vdir = tmp_path / "v0001"
    if not vdir.exists():  # one copy per test run; each example rewrites only the manifest
        shutil.copytree(published, vdir)
        open_map(vdir).all_corners()  # warm imports and caches outside the memory bound
    raw = (published / "manifest.json").read_bytes()
    if data.draw(st.booleans()):
        doc = json.loads(raw)
        key = data.draw(st.sampled_from(sorted(doc)))
        path = [key]
        node = doc[key]
        while isinstance(node, (dict, list)) and node and data.draw(st.booleans()):
            k = data.draw(st.sampled_from(sorted(node) if isinstance(node, dict) else list(range(len(node)))))
            path.append(k)
            node = node[k]
        target = doc
        for k in path[:-1]:
            target = target[k]
        target[path[-1]] = data.draw(json_values)
        raw = json.dumps(doc).encode()
    else:
        raw = _mutate(raw, data)
    (vdir / "manifest.json").write_bytes(raw)
    with bounded_memory():
        assert isinstance(verify_map(vdir), list)
        try:
            reader = open_map(vdir)
            reader.all_corners()
            reader.corners_within(50.0, 50.0, 30.0)
        except CornermapError:
            return


# -- YAML -------------------------------------------------------------------------------------------------
yaml_text = st.text(alphabet=st.sampled_from(list("ab:-&*[]{}!|>'\"#,? \n\t0123456789.xyz<")), max_size=200)


@FUZZ
@given(text=yaml_text)
def test_yaml_loader(text):
    from pipeline.safe_yaml import load_yaml

    with bounded_memory(16 << 20):
        try:
            load_yaml(text, "fuzz.yaml")
        except CornermapError:
            return


@FUZZ
@given(text=yaml_text)
def test_workflow_loader(tmp_path, text):
    from pipeline.workflow import load_workflow

    path = tmp_path / "wf.yaml"
    path.write_text("name: fuzz\nstages: [ingest]\n" + text)
    try:
        load_workflow(path)
    except CornermapError:
        return
