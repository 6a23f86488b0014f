"""Change detection's statistics (mapformat/change_tests.py): the chi-square test keeps its false-alarm rate on
unchanged corners and finds a move of a few sigma; the marking test ignores edge noise and finds a moved crosswalk."""
from __future__ import annotations

import numpy as np
import pytest

from mapformat.change_tests import changed_cells, chi2_threshold, corner_chi2, seen_from, tile_cells


def test_unchanged_corners_are_flagged_at_the_stated_rate_and_a_real_move_is_found():
    rng = np.random.default_rng(4)
    n = 200_000
    A = rng.normal(size=(n, 2, 2)) * 0.03
    Ca = A @ A.transpose(0, 2, 1) + 1e-4 * np.eye(2)
    Cb = 0.5 * Ca + 2e-4 * np.eye(2)
    L = np.linalg.cholesky(Ca + Cb)
    d = np.einsum("kij,kj->ki", L, rng.normal(size=(n, 2)))  # unchanged: d ~ N(0, Ca + Cb)
    stat, p = corner_chi2(d, Ca, Cb)
    rate = float((stat > chi2_threshold(0.001)).mean())
    assert rate == pytest.approx(0.001, abs=0.0003)  # the significance is the false-alarm rate
    np.testing.assert_allclose(p, np.exp(-stat / 2), rtol=1e-9)  # chi-square 2 dof survival
    sigma = np.sqrt(np.linalg.eigvalsh(Ca[:1000] + Cb[:1000]).max(axis=1))
    stat_m, _ = corner_chi2(np.column_stack([6 * sigma, np.zeros(1000)]), Ca[:1000], Cb[:1000])
    assert (stat_m > chi2_threshold(0.001)).all()  # a move of 6 sigma (largest axis) is always found
    assert chi2_threshold(0.001) == pytest.approx(13.8155, abs=1e-3)


def _crosswalk(shape, e0_px: int) -> np.ndarray:
    m = np.zeros(shape, np.uint8)
    for k in range(8):  # 0.5 m stripes every 1 m, 4 m long, across the road
        m[300 + 10 * k:305 + 10 * k, e0_px:e0_px + 40] = 255
    return m


def test_edge_noise_is_not_a_change_and_a_moved_crosswalk_is_one_region():
    rng = np.random.default_rng(1)
    shape = (1000, 1000)  # a 100 m tile at 0.1 m
    base = np.zeros(shape, np.uint8)
    for r in (200, 500, 800):  # three lane lines along east, 0.15 m wide
        base[r:r + 2, :] = 255
    base = base | _crosswalk(shape, 100)

    def survey(img: np.ndarray) -> np.ndarray:  # a re-survey: a cell flips where paint has an edge, now and then
        import cv2

        edge = cv2.morphologyEx(img, cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
        flip = edge & (rng.random(shape) < 0.3)
        out = img.copy()
        out[flip] = 255 - out[flip]
        return out

    seen = np.ones(shape, bool)
    same = tile_cells(survey(base), survey(base), seen, (0.0, 0.0), 0.1, 10.0, 2)
    cells, test = changed_cells([same], 10.0)
    assert cells == [] and test["cells_compared"] == len(same.n) > 20
    moved = base & ~_crosswalk(shape, 100) | _crosswalk(shape, 120)  # the crosswalk 2 m east
    diff = tile_cells(survey(base), survey(moved), seen, (0.0, 0.0), 0.1, 10.0, 2)
    cells, _ = changed_cells([diff], 10.0)
    # the crosswalk spans east 10-16 m, north 60-68 m (rows 300-375 from the north edge of a 100 m tile)
    assert {tuple(c["cell"]) for c in cells} <= {(1, 6), (0, 6)} and (1, 6) in {tuple(c["cell"]) for c in cells}
    unseen = tile_cells(survey(base), survey(moved), np.zeros(shape, bool), (0.0, 0.0), 0.1, 10.0, 2)
    assert changed_cells([unseen], 10.0)[0] == []  # where one version saw no ground nothing is compared


def test_seen_from_needs_range_and_the_walls_seen_side():
    corners = np.array([[10.0, 10.0], [10.0, 10.0], [200.0, 10.0]])
    theta = np.array([[0.0, np.pi / 2], [np.pi, -np.pi / 2], [0.0, np.pi / 2]])  # NE building / SW building / far
    path = [np.column_stack([np.linspace(-50, 50, 101), np.zeros(101)])]
    assert seen_from(path, corners, theta, np.ones(3, bool)).tolist() == [True, False, False]
