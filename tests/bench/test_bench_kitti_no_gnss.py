"""The shared KITTI 0048 sample (22 scans, no GNSS) built as a user without GNSS builds it: drive init, its drafted
start line filled in, cornermap build --origin (child processes). The map is published, its frame is the stated start
pose's, and every corner sits on the scans' facades (the accumulated points 1-4 m above the road)."""
from __future__ import annotations

import pytest

pytestmark = pytest.mark.realdata


def test_kitti_without_gnss_builds_from_drive_init_and_a_start_heading(shared_data, tmp_path):
    from bench.bench_kitti_no_gnss import build, measure

    root = build(tmp_path, 0.0)
    out, fig = measure(root)
    assert out["scans"] == 22 and 15.0 < out["path_m"] < 20.0
    assert out["frame"]["source"] == "start pose"
    assert out["frame"]["std_rotation_deg"] == pytest.approx(2.0, abs=0.05)  # the stated heading std
    assert out["map_corners"] >= 3, out
    assert all(c["facade_point_m"] < 0.2 for c in out["corners"]), out["corners"]
    # the path runs north from the origin (heading 0 stated): the first pose at the origin, the last 17 m north
    assert abs(fig["path"][0, 0]) < 0.01 and abs(fig["path"][0, 1]) < 0.01 and fig["path"][-1, 1] > 15.0
