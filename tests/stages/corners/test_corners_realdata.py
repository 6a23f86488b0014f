"""Real scans in ../shared/data: corners are found on building facades (nuScenes HDL-32E, KITTI HDL-64E).

Tiny local readers: the ingest stage's readers are not used here so this stage can be tested on its own.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stages.corners.core import trace_corners, wall_lengths_m
from stages.corners.lines import LINE
from stages.corners.params import CornerParams

pytestmark = pytest.mark.realdata


def read_nuscenes(path: Path):
    rec = np.fromfile(path, np.float32).reshape(-1, 5)
    return rec[:, :3], rec[:, 4].astype(np.int16)


def read_kitti(path: Path):
    raw = path.read_bytes()
    end = raw.index(b"DATA binary\n") + len(b"DATA binary\n")
    n = int(next(ln.split()[1] for ln in raw[:end].decode().splitlines() if ln.startswith("POINTS")))
    pts = np.frombuffer(raw, np.float32, count=4 * n, offset=end).reshape(n, 4)[:, :3]
    pts = pts[np.any(pts != 0, axis=1)]
    az = np.arctan2(pts[:, 1], pts[:, 0])
    order_ring = np.cumsum(np.r_[False, (az[:-1] < 0) & (az[1:] >= 0)])
    return pts, (order_ring.max() - order_ring).astype(np.int16)  # first laser in the file is the top one


NO_WALL_GATE = CornerParams(
    checks={"min_wall_length_m": 0.0, "min_long_wall_length_m": 0.0, "min_obtuse_wall_length_m": 0.0}
)  # the extraction chain itself, without the small-structure gate


def check_trace(trace, n_min, n_max):
    c = trace.corners
    assert n_min <= len(c) <= n_max, f"{len(c)} corners"
    assert np.all(c.n_layers >= 3)
    assert np.all((c.range_m > 2.0) & (c.range_m < 80.0))
    assert np.all(np.linalg.eigvalsh(c.cov_m2) > 0)
    # every corner lies on extracted facade lines: near the end of a retained line
    ends = np.r_[trace.xy_m[trace.lines.start[trace.line_label == LINE]],
                 trace.xy_m[trace.lines.stop[trace.line_label == LINE]]]
    d = np.linalg.norm(np.column_stack([c.x_m, c.y_m])[:, None] - ends[None], axis=2).min(axis=1)
    assert d.max(initial=0.0) < 0.6


def test_nuscenes_hdl32e_sweep_has_facade_corners(shared_data):
    files = sorted((shared_data / "nuscenes_hdl32e_sweep").glob("*.pcd.bin"))
    if not files:
        pytest.skip("no nuScenes sweep in shared data")
    pts, ring = read_nuscenes(files[0])
    trace = trace_corners(pts, ring, NO_WALL_GATE)
    np.testing.assert_array_equal(trace.layers_used, np.arange(31, 23, -1))  # the eight upper HDL-32E beams
    check_trace(trace, 3, 20)
    # the paper's corners are right-angled facades mostly: most corners here are 90 +- 5 deg
    assert np.mean(np.abs(np.degrees(trace.corners.interior_angle_rad) - 90.0) < 5.0) >= 0.5


def test_kitti_city_scans_have_facade_corners(shared_data):
    files = sorted((shared_data / "kitti_raw_0048_city").glob("*.pcd"))[::7]
    if not files:
        pytest.skip("no KITTI scans in shared data")
    counts = []
    for f in files:
        pts, ring = read_kitti(f)
        assert ring.max() == 63
        trace = trace_corners(pts, ring, NO_WALL_GATE)
        assert trace.layers_used.size == 8 and trace.layers_used.min() >= 54
        check_trace(trace, 0, 20)
        counts.append(len(trace.corners))
    assert sum(counts) >= len(files)  # on average at least one corner per scan in this street


def test_kitti_corners_kept_by_the_wall_length_gate_have_long_walls(shared_data):
    """The default gate keeps a subset: every survivor's longer wall is >= 2 m as its best layer saw it; in this
    street it removes the corners that stay 8-11 m ahead in every scan (the rear of the car driving ahead:
    walls 1.0-1.4 m)."""
    files = sorted((shared_data / "kitti_raw_0048_city").glob("*.pcd"))[::3]
    if not files:
        pytest.skip("no KITTI scans in shared data")
    kept = loose = 0
    for f in files:
        pts, ring = read_kitti(f)
        trace = trace_corners(pts, ring)
        c = trace.candidates
        walls = wall_lengths_m(trace.candidate_corner, trace.lines.length_m[c.line_a],
                               trace.lines.length_m[c.line_b], len(trace.corners))
        assert np.all(walls.max(axis=1) >= 2.0)
        assert not np.any((trace.corners.range_m > 8.0) & (trace.corners.range_m < 11.0))
        kept += len(trace.corners)
        loose += len(trace_corners(pts, ring, NO_WALL_GATE).corners)
    assert 1 <= kept < loose
