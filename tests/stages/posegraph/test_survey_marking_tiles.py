"""The survey's marking mask as the marking anchors see it: computed per fixed tile, windows cut from the tiles.
Synthetic survey (a flat road, painted lane lines of known place): the paint is found where it is, a window across
four tiles shows it continuously, two overlapping windows agree exactly, and tiles are computed once."""
from __future__ import annotations

import numpy as np
import pytest

from stages.posegraph.anchors import survey_markings as sm
from tests.stages.posegraph.conftest import posegraph_config

LINES_N_M = np.arange(62.0, 140.0, 3.5)  # east-west lane lines, 0.15 m wide, at these northings


@pytest.fixture(scope="module")
def survey_cloud():
    rng = np.random.default_rng(11)
    e, n = np.meshgrid(np.arange(40.0, 160.0, 0.08), np.arange(40.0, 160.0, 0.08))
    e, n = e.ravel() + rng.uniform(-0.03, 0.03, e.size), n.ravel() + rng.uniform(-0.03, 0.03, n.size)
    paint = np.min(np.abs(n[:, None] - LINES_N_M[None, :]), axis=1) < 0.075
    intensity = np.where(paint, 70.0, 20.0) + rng.normal(0.0, 2.0, e.size)
    up = 0.005 * rng.standard_normal(e.size)
    return np.column_stack([e, n, up]), intensity


@pytest.fixture(scope="module")
def survey_index(survey_cloud):
    return sm.build_survey_marking_index(*survey_cloud)


def test_windows_across_tiles_show_the_paint_where_it_is_and_agree_on_their_overlap(survey_index, monkeypatch):
    raster = posegraph_config().anchors.markings.raster
    cell = raster.cell_m
    survey_index.tiles.clear()
    computed = []
    real = sm.marking_mask
    monkeypatch.setattr(sm, "marking_mask", lambda *a, **k: computed.append(a[1:3]) or real(*a, **k))
    mask, (e0, n0) = sm.survey_marking_window(survey_index, np.array([100.0, 100.0]), 30.0, raster)  # 4 tiles
    assert len(computed) == 4 and mask.shape == (600, 600)
    rows_n = n0 + (mask.shape[0] - 1 - np.arange(mask.shape[0]) + 0.5) * cell  # cell centres, row 0 north
    inside = LINES_N_M[(LINES_N_M > n0 + 1.0) & (LINES_N_M < n0 + 59.0)]
    for line_n in inside:  # each line painted along the whole window (across the tile border at east 100 m)
        rows = np.abs(rows_n - line_n) < 0.1  # the cells the 0.15 m line covers
        assert mask[rows].any(axis=0).mean() > 0.95, line_n
    far = np.min(np.abs(rows_n[:, None] - LINES_N_M[None, :]), axis=1) > 0.4
    assert mask[far].mean() < 0.002  # bare road stays bare
    # a second window overlapping the first: the same mask on the overlap, from the tiles already computed
    mask2, (e2, n2) = sm.survey_marking_window(survey_index, np.array([113.7, 108.3]), 30.0, raster)
    assert len(computed) == 4
    di, dj = int(round((e2 - e0) / cell)), int(round((n2 - n0) / cell))
    a = mask[::-1][dj:, di:]  # south-up, from the second window's south-west corner
    b = mask2[::-1][:a.shape[0], :a.shape[1]]
    np.testing.assert_array_equal(a, b)


def test_the_tile_cache_is_bounded(survey_index, monkeypatch):
    raster = posegraph_config().anchors.markings.raster
    monkeypatch.setattr(sm, "MAX_TILES", 2)
    survey_index.tiles.clear()
    sm.survey_marking_window(survey_index, np.array([100.0, 100.0]), 30.0, raster)
    assert len(survey_index.tiles) == 2


def test_indexes_sharing_a_cache_dir_compute_each_tile_once_and_agree(survey_cloud, survey_index, tmp_path,
                                                                      monkeypatch):
    """Two processes' lazy indexes of one survey source (``survey_marking_index``): the second computes no tile and
    never reads the survey; its windows equal the first's and an unshared index's."""
    from stages.posegraph.anchors.survey_anchor import SurveyArrays

    raster = posegraph_config().anchors.markings.raster
    source = SurveyArrays(*survey_cloud)
    source.cache_dir = tmp_path
    reads = []
    real_read = source.read
    monkeypatch.setattr(source, "read", lambda: reads.append(1) or real_read())
    computed = []
    real = sm.marking_mask
    monkeypatch.setattr(sm, "marking_mask", lambda *a, **k: computed.append(a[1:3]) or real(*a, **k))
    first, second = sm.survey_marking_index(source), sm.survey_marking_index(source)
    centre = np.array([100.0, 100.0])
    mask_a, origin_a = sm.survey_marking_window(first, centre, 30.0, raster)
    assert len(computed) == 4 and len(reads) == 1
    mask_b, origin_b = sm.survey_marking_window(second, centre, 30.0, raster)
    assert len(computed) == 4 and len(reads) == 1 and second.tree is None  # loaded from the shared files
    survey_index.tiles.clear()
    mask_c, origin_c = sm.survey_marking_window(survey_index, centre, 30.0, raster)
    np.testing.assert_array_equal(mask_a, mask_b)
    np.testing.assert_array_equal(mask_a, mask_c)
    assert origin_a == origin_b == origin_c
