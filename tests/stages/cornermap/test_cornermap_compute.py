"""compute() on in-memory tables: lidar-frame observations from two drives -> the known corners."""
from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest

from pipeline.errors import DataQualityError
from pipeline.testing import make_context
from schemas import SCHEMAS
from stages.cornermap.angles import canonicalize_pairs, pair_difference_rad
from stages.cornermap.decl import STAGE
from stages.cornermap.export import format_im2016_text, parse_im2016_text
from stages.cornermap.params import CornerMapParams
from tests.stages.cornermap.cornermap_synth import observe, true_corners


@pytest.fixture(scope="module")
def tables():
    return observe(true_corners(), {"drive_a": 0.0, "drive_b": 2.0}, n_scans=90, seed=41)


def _run(tables, **settings):
    corners, poses, info = tables
    with tempfile.TemporaryDirectory(prefix="cornermap-test-") as workdir:
        ctx = make_context("cornermap", CornerMapParams(cell_size_m=100.0),
                           {"corners": corners, "poses": poses, "drive_info": info}, settings=settings,
                           workdir=Path(workdir))
        return STAGE.load_compute()(ctx)


def _match(out: pa.Table, truth: np.ndarray) -> np.ndarray:
    en = np.column_stack([out["east_m"].to_numpy(), out["north_m"].to_numpy()])
    d = np.linalg.norm(en[:, None, :] - truth[None, :, :2], axis=2)
    return d.argmin(axis=1), d.min(axis=1)


def test_two_drives_recover_every_corner(tables):
    result = _run(tables)
    out = result["corner_map"]
    assert out.schema.equals(SCHEMAS["corner_map"]) and result["rejected"].schema.equals(SCHEMAS["corner_map_rejected"])
    truth = true_corners()
    nearest, dist = _match(out, truth)
    assert out.num_rows == len(truth) and sorted(nearest) == list(range(len(truth)))
    assert dist.max() < 0.03
    theta = np.column_stack([out["theta1_rad"].to_numpy(), out["theta2_rad"].to_numpy()])
    diff, swapped = pair_difference_rad(theta, canonicalize_pairs(truth[nearest, 2:]))
    assert np.degrees(diff).max() < 0.5 and not swapped.any()
    assert set(out["drives"].to_pylist()) == {"drive_a,drive_b"}
    cov = np.stack([np.stack([out["cov_ee_m2"].to_numpy(), out["cov_en_m2"].to_numpy()], 1),
                    np.stack([out["cov_en_m2"].to_numpy(), out["cov_nn_m2"].to_numpy()], 1)], 1)
    assert np.all(np.linalg.eigvalsh(cov)[:, 0] > 0)
    assert result["_extra"]["cornermap"]["n_partition_conflicts"] == 0
    back = parse_im2016_text(format_im2016_text(out))
    np.testing.assert_allclose(back["north_m"], out["north_m"].to_numpy(), atol=5e-4)


def test_map_drives_limits_the_contributors(tables):
    out = _run(tables, map_drives=["drive_b"])["corner_map"]
    assert set(out["drives"].to_pylist()) == {"drive_b"}
    assert pc.sum(out["n_obs"]).as_py() == pc.sum(pc.equal(tables[0]["drive"], "drive_b")).as_py()


def test_rare_corner_is_rejected_with_its_reason(tables):
    corners, poses, info = tables
    lonely = corners.slice(0, 1).to_pylist() * 3  # one scan sees the same stray corner three times
    for i in range(3):
        lonely[i] = {**lonely[i], "x_m": -30.0, "y_m": -30.0 + 0.01 * i, "corner_idx": 99 + i}
    corners = pa.concat_tables([corners, pa.Table.from_pylist(lonely, schema=corners.schema)])
    result = _run((corners, poses, info))
    rejected = result["rejected"]
    assert rejected.num_rows == 1 and rejected["reason"][0].as_py().startswith("few_observations: 3 <")
    assert result["corner_map"].num_rows == len(true_corners())


def test_missing_extrinsics_is_a_named_error(tables):
    corners, poses, info = tables
    with pytest.raises(DataQualityError, match="drive_b.*no drive_info row"):
        _run((corners, poses, info.filter(pc.equal(info["drive"], "drive_a"))))


def test_scans_without_pose_are_dropped_and_counted(tables):
    corners, poses, info = tables
    poses = poses.filter(pc.greater(poses["scan_id"], 5))
    result = _run((corners, poses, info))
    n_dropped = pc.sum(pc.less_equal(corners["scan_id"], 5)).as_py()
    assert n_dropped > 0 and result["_extra"]["cornermap"]["n_dropped_no_pose"] == n_dropped


def test_empty_input_gives_empty_tables(tables):
    corners, poses, info = tables
    result = _run((corners.slice(0, 0), poses, info))
    assert result["corner_map"].num_rows == 0 and result["corner_map"].schema.equals(SCHEMAS["corner_map"])


def test_layer_vs_poses_measures_a_drive_whose_poses_sit_in_another_frame(tables):
    """The map from drive_a; drive_b's optimized poses moved 0.4 m east (a pose graph whose reference drive is
    not tied to the map drive's frame): the check reports that offset for drive_b and none for drive_a."""
    corners, poses, info = tables
    is_b = pc.equal(poses["drive"], "drive_b")
    moved = poses.set_column(poses.schema.get_field_index("x_m"), "x_m",
                             pc.if_else(is_b, pc.add(poses["x_m"], 0.4), poses["x_m"]))
    result = _run((corners, moved, info), map_drives=["drive_a"])
    check = result["_extra"]["cornermap"]["layer_vs_poses"]
    assert np.hypot(*check["drive_a"]["median_offset_en_m"]) < 0.02 and check["drive_a"]["rms_m"] < 0.05
    np.testing.assert_allclose(check["drive_b"]["median_offset_en_m"], [0.4, 0.0], atol=0.02)
    assert check["drive_b"]["n_matched"] > 0.9 * check["drive_b"]["n_observations"]
    assert abs(check["drive_b"]["fit_rotation_deg"]) < 0.1
