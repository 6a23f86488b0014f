"""PCD reader: round trips, open3d cross-check, malformed files -> FormatError, random corruption fuzz."""
from __future__ import annotations

import re

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.errors import FormatError
from stages.ingest.lzf import LzfError, decompress_lzf
from stages.ingest.pcd import decode_pcd, encode_pcd, read_pcd
from stages.ingest.scan_formats import points_from_pcd

ENCODINGS = ["ascii", "binary", "binary_compressed"]


def _columns(seed: int, n: int = 50) -> dict:
    rng = np.random.default_rng(seed)
    return {"time": rng.random(n).astype(np.float32), "ring": rng.integers(0, 64, n).astype(np.uint16),
            "z": rng.normal(size=n).astype(np.float32), "x": rng.normal(size=n).astype(np.float32),
            "normal": rng.normal(size=(n, 3)).astype(np.float64), "y": rng.normal(size=n).astype(np.float32),
            "intensity": rng.random(n).astype(np.float32), "label": rng.integers(-5, 5, n).astype(np.int8)}


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_round_trip_any_field_order_and_count(encoding):
    cols = _columns(1)
    cloud = decode_pcd(encode_pcd(cols, encoding))
    assert cloud.header.encoding == encoding and cloud.header.counts[4] == 3
    for name, values in cols.items():
        np.testing.assert_array_equal(cloud.columns[name], values)
    points = points_from_pcd(cloud)
    np.testing.assert_array_equal(points.x_m, cols["x"])
    np.testing.assert_array_equal(points.ring, cols["ring"].astype(np.int16))
    np.testing.assert_array_equal(points.time_offset_s, cols["time"])


def test_trailing_padding_is_tolerated_and_measured():
    buf = encode_pcd(_columns(2), "binary") + bytes(3906)
    cloud = decode_pcd(buf)
    assert cloud.header.points == 50 and cloud.trailing_bytes == 3906


def test_open3d_compressed_file_cross_check(tmp_path):
    o3d = pytest.importorskip("open3d")
    rng = np.random.default_rng(3)
    pc = o3d.t.geometry.PointCloud()
    xyz = np.round(rng.normal(size=(2000, 3)), 2).astype(np.float32)  # repetitive bytes -> LZF back references
    pc.point.positions = o3d.core.Tensor(xyz)
    pc.point.intensity = o3d.core.Tensor(np.zeros((2000, 1), np.float32))
    pc.point.ring = o3d.core.Tensor(rng.integers(0, 32, (2000, 1)).astype(np.uint16))
    path = tmp_path / "o3d.pcd"
    assert o3d.t.io.write_point_cloud(str(path), pc, write_ascii=False, compressed=True)
    cloud = read_pcd(path)
    assert cloud.header.encoding == "binary_compressed"
    np.testing.assert_array_equal(np.column_stack([cloud.columns[c] for c in "xyz"]), xyz)
    np.testing.assert_array_equal(cloud.columns["ring"], pc.point.ring.numpy()[:, 0])


def test_lzf_overlapping_back_reference_and_errors():
    # literal "ab", then a back reference of length 6 at distance 2 -> "abababab"
    stream = bytes([1]) + b"ab" + bytes([(4 << 5) | 0, 1])
    assert decompress_lzf(stream, 8) == b"abababab"
    with pytest.raises(LzfError, match="before the start"):
        decompress_lzf(bytes([(1 << 5), 10]), 3)
    with pytest.raises(LzfError, match="expected 9"):
        decompress_lzf(stream, 9)


def test_truncated_binary_names_the_record(tmp_path):
    buf = encode_pcd(_columns(4), "binary")
    path = tmp_path / "cut.pcd"
    path.write_bytes(buf[:-100])
    with pytest.raises(FormatError, match=r"cut.pcd: truncated binary data.*record 4\d is the first incomplete"):
        read_pcd(path)


def test_header_counts_that_lie():
    buf = encode_pcd(_columns(5), "binary").replace(b"POINTS 50", b"POINTS 60")
    with pytest.raises(FormatError, match="POINTS 60 != WIDTH 50"):
        decode_pcd(buf)
    lying = encode_pcd(_columns(5), "binary").replace(b"WIDTH 50", b"WIDTH 70").replace(b"POINTS 50", b"POINTS 70")
    with pytest.raises(FormatError, match="truncated binary data"):
        decode_pcd(lying)
    fewer_fields = encode_pcd(_columns(5), "binary").replace(b"SIZE 4 2", b"SIZE 4")
    with pytest.raises(FormatError, match="disagree in length"):
        decode_pcd(fewer_fields)


@pytest.mark.parametrize("garbage", [b"\x00\xff\x13garbage" * 10, b"", b"VERSION 0.7\nFIELDS x\n"])
def test_garbage_bytes(garbage):
    with pytest.raises(FormatError):
        decode_pcd(garbage, "junk.pcd")


def test_ascii_wrong_value_count():
    buf = encode_pcd({"x": np.arange(3, dtype=np.float32), "y": np.arange(3, dtype=np.float32)}, "ascii")
    with pytest.raises(FormatError, match="ascii record 1 has 3 values, expected 2"):
        decode_pcd(buf.replace(b"\n1.0 1.0\n", b"\n1.0 1.0 7\n"))


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(encoding=st.sampled_from(ENCODINGS), seed=st.integers(0, 2**16),
       cut=st.floats(0.0, 1.0), flips=st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(0, 255)), max_size=8),
       mode=st.sampled_from(["truncate", "flip", "insert"]))
def test_random_corruptions_raise_format_error_or_decode_consistently(encoding, seed, cut, flips, mode):
    buf = bytearray(encode_pcd(_columns(seed % 7, n=20), encoding))
    if mode == "truncate":
        buf = buf[:int(cut * len(buf))]
    elif mode == "flip":
        for where, value in flips:
            buf[min(int(where * len(buf)), len(buf) - 1)] = value
    else:
        at = int(cut * len(buf))
        buf = buf[:at] + bytes(v for _, v in flips) + buf[at:]
    try:
        cloud = decode_pcd(bytes(buf), "fuzz.pcd")
    except FormatError:
        return
    n = cloud.header.points
    assert all(len(v) == n for v in cloud.columns.values())


def _timed_cloud(time: np.ndarray):
    n = len(time)
    rng = np.random.default_rng(3)
    return decode_pcd(encode_pcd({"x": rng.normal(size=n).astype(np.float32) + 5.0,
                                  "y": rng.normal(size=n).astype(np.float32),
                                  "z": rng.normal(size=n).astype(np.float32), "time": time}, "binary"))


def test_point_times_that_are_no_sweep_offsets_are_not_used_and_say_why():
    """Microseconds written as float seconds (0 .. 99,000 for one sweep) would deskew points by kilometres: the points
    are kept without times, and the reason names the field, the first such point and the expected range."""
    micro = np.linspace(0.0, 99_000.0, 40).astype(np.float32)
    points = points_from_pcd(_timed_cloud(micro), "scan.pcd")
    assert points.time_offset_s is None and len(points) == 40
    assert re.search(r"time of point 1 lies 2538\.46 s from the scan start \(39 points beyond \+-10 s\).*not deskewed",
                     points.time_unused)
    assert points.select(np.arange(40) < 5).time_unused == points.time_unused


def test_absolute_and_integer_times_become_seconds_since_the_scan_start():
    gps_s = 1.4e9 + np.linspace(0.0, 0.1, 40)  # absolute GPS seconds (float64)
    np.testing.assert_allclose(points_from_pcd(_timed_cloud(gps_s)).time_offset_s, gps_s - gps_s[0], atol=1e-6)
    ns = np.arange(40, dtype=np.int64) * 2_500_000  # integer nanoseconds
    np.testing.assert_allclose(points_from_pcd(_timed_cloud(ns)).time_offset_s, ns * 1e-9, atol=1e-9)


def test_a_point_without_a_finite_time_is_dropped_and_counted():
    from stages.ingest.scan_formats import drop_invalid_points

    time = np.linspace(0.0, 0.1, 40).astype(np.float32)
    time[[3, 17]] = [np.nan, np.inf]
    points = points_from_pcd(_timed_cloud(time))
    kept, drops = drop_invalid_points(points)
    assert drops["nonfinite"] == 2 and len(kept) == 38
    assert np.isfinite(kept.time_offset_s).all()
