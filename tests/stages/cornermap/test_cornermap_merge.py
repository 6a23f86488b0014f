"""Duplicates: one physical corner split into two clusters 0.5 m apart with the same walls becomes one map
corner; two corners 0.5 m apart whose walls differ stay two."""
from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from pipeline.testing import make_context
from stages.cornermap.decl import STAGE
from stages.cornermap.merge import count_duplicates, duplicate_groups, merge_duplicates
from stages.cornermap.params import CornerMapParams
from tests.stages.cornermap.cornermap_synth import observe

WALLS = (np.radians(-90), np.radians(0))


def _corner(east, north, walls=WALLS):
    return np.array([[east, north, *walls]])


def _run(tables, **params):
    corners, poses, info = tables
    with tempfile.TemporaryDirectory(prefix="cornermap-merge-") as workdir:
        ctx = make_context("cornermap", CornerMapParams(cell_size_m=100.0, **params),
                           {"corners": corners, "poses": poses, "drive_info": info}, workdir=Path(workdir))
        return STAGE.load_compute()(ctx)


def _split_corner(offset_m: float, walls_b=WALLS, sigma_m=0.03, seed=3):
    """Drive a sees the corner at (50, 12); drive b sees 'it' ``offset_m`` further east (a split corner)."""
    a = observe(_corner(50.0, 12.0), {"drive_a": 0.0}, n_scans=60, seed=seed, sigma_m=sigma_m)
    b = observe(_corner(50.0 + offset_m, 12.0, walls_b), {"drive_b": 2.0}, n_scans=60, seed=seed + 1,
                sigma_m=sigma_m)
    return tuple(pa.concat_tables([x, y]) for x, y in zip(a, b))


@pytest.mark.parametrize("offset_m", [0.5, 0.8])
def test_two_clusters_half_a_metre_apart_with_the_same_walls_are_one_corner(offset_m):
    tables = _split_corner(offset_m)
    split = _run(tables, merge_radius_m=0.0)["corner_map"]  # without the merge step: the duplicate the map had
    assert split.num_rows == 2
    result = _run(tables)
    out = result["corner_map"]
    assert out.num_rows == 1, out.to_pylist()
    east = out["east_m"].to_numpy()[0]
    assert 50.0 - 0.05 <= east <= 50.0 + offset_m + 0.05
    stats = result["_extra"]["cornermap"]
    assert stats["n_merged_groups"] + stats["n_duplicates_rejected"] == 1
    en = np.column_stack([out["east_m"].to_numpy(), out["north_m"].to_numpy()])
    assert count_duplicates(en, np.column_stack([out["theta1_rad"].to_numpy(), out["theta2_rad"].to_numpy()])) == 0


def test_close_split_is_merged_into_one_cluster_at_the_mean():
    """0.45 m apart with 1 cm noise (beyond the 0.35 m link, so two clusters): the merged cluster's spread
    (0.225 m) passes the filter, so both drives' observations make the corner, at their mean."""
    result = _run(_split_corner(0.45, sigma_m=0.01))
    out = result["corner_map"]
    assert out.num_rows == 1 and result["_extra"]["cornermap"]["n_merged_groups"] == 1
    assert out["n_drives"].to_pylist() == [2]
    assert out["east_m"].to_numpy()[0] == pytest.approx(50.225, abs=0.05)


def test_half_a_metre_apart_with_different_walls_stay_two():
    tables = _split_corner(0.5, walls_b=(np.radians(90), np.radians(180)))
    assert _run(tables)["corner_map"].num_rows == 2


def test_groups_and_duplicate_count_on_summaries():
    en = np.array([[0.0, 0.0], [0.5, 0.0], [0.9, 0.2], [5.0, 0.0], [5.3, 0.0]])
    theta = np.array([WALLS, WALLS[::-1], WALLS, WALLS, (np.radians(90), np.radians(180))])
    group = duplicate_groups(en, theta, 1.0, np.radians(12))
    assert group[0] == group[1] == group[2] and len({group[0], group[3], group[4]}) == 3
    assert count_duplicates(en, theta, 1.0) == 3  # (0,1), (0,2), (1,2); (3,4) have different walls
    # merge_duplicates with a filter that rejects every merged cluster: the strongest member survives
    labels = np.repeat(np.arange(5), [10, 30, 5, 8, 8])
    n_obs = np.bincount(labels)
    new, dup, n_merged = merge_duplicates(labels, en, theta, n_obs, lambda lab: np.bincount(lab) < 40,
                                          merge_radius_m=1.0, angle_tol_rad=np.radians(12))
    assert n_merged == 0 and np.array_equal(new, labels) and dup.tolist() == [True, False, True, False, False]
