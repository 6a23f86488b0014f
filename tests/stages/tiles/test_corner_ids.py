"""Stable corner ids (mapformat/corner_ids.py): the gated one-to-one match and the id counter."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from mapformat.corner_ids import IdGates, assign_ids, match_corners, wall_angle_error_deg
from tests.stages.tiles.tiles_synth import building_corners, buildings


def _brute_force(cost: np.ndarray) -> tuple[int, float]:
    """(largest number of admissible pairs, least total cost among matchings of that size); inf = inadmissible."""
    n, m = cost.shape
    best = (0, 0.0)
    for k in range(1, min(n, m) + 1):
        for rows in itertools.combinations(range(n), k):
            for cols in itertools.permutations(range(m), k):
                c = cost[list(rows), list(cols)]
                if np.isfinite(c).all() and (k > best[0] or (k == best[0] and c.sum() < best[1] - 1e-12)):
                    best = (k, float(c.sum()))
    return best


def test_a_rebuilt_city_keeps_every_id_and_finds_the_removed_and_added_corners():
    rng = np.random.default_rng(3)
    xy, dirs, owner = building_corners(buildings())
    prev_ids = 100 + np.arange(len(xy))
    keep = owner != 7  # building 7 demolished
    new_xy = np.vstack([xy[keep] + rng.normal(0, 0.05, (keep.sum(), 2)), [[500.0, 500.0], [530.0, 500.0]]])
    new_dirs = np.vstack([dirs[keep][:, ::-1] + rng.normal(0, np.radians(2), (keep.sum(), 2)),  # walls listed swapped
                          [[0.0, np.pi / 2], [np.pi / 2, np.pi]]])
    perm = rng.permutation(len(new_xy))  # the new build lists its corners in another order
    m = match_corners(xy, dirs, new_xy[perm], new_dirs[perm])
    truth_prev = np.r_[np.flatnonzero(keep), -1, -1][perm]  # index into prev of each new corner, -1 = new
    assert len(m.i_new) == keep.sum()
    assert (truth_prev[m.i_new] == m.i_prev).all()
    ids, counter = assign_ids(prev_ids, m, len(new_xy), next_id=int(prev_ids.max()) + 1)
    assert (ids[truth_prev >= 0] == prev_ids[truth_prev[truth_prev >= 0]]).all()
    fresh = ids[truth_prev < 0]
    assert sorted(fresh) == [prev_ids.max() + 1, prev_ids.max() + 2] and counter == prev_ids.max() + 3
    assert len(np.unique(ids)) == len(ids)


def test_one_to_one_beats_nearest_neighbour():
    # new corner 0 is nearer to prev 1 than to prev 0, but only the crossing-free assignment matches both
    prev = np.array([[0.0, 0.0], [0.8, 0.0]])
    new = np.array([[0.45, 0.0], [1.3, 0.0]])
    th = np.zeros((2, 2)) + [0.0, np.pi / 2]
    m = match_corners(prev, th, new, th)
    assert m.i_prev.tolist() == [0, 1] and m.i_new.tolist() == [0, 1]
    np.testing.assert_allclose(m.dist_m, [0.45, 0.5])


def test_gates_on_distance_and_both_walls():
    prev = np.array([[0.0, 0.0]])
    th = np.array([[0.0, np.pi / 2]])
    assert len(match_corners(prev, th, prev + [1.01, 0.0], th).i_new) == 0  # beyond max_dist_m
    assert len(match_corners(prev, th, prev, th + [0.0, np.radians(20)]).i_new) == 0  # one wall off by 20 deg
    assert len(match_corners(prev, th, prev, th[:, ::-1]).i_new) == 1  # same walls, listed the other way
    assert len(match_corners(prev, th, prev, th + 2 * np.pi).i_new) == 1  # angles wrap
    assert len(match_corners(prev, th, prev, th + np.radians(10), IdGates(max_angle_deg=5.0)).i_new) == 0
    np.testing.assert_allclose(wall_angle_error_deg(th, th[:, ::-1] + np.radians([3.0, -4.0])), [4.0])
    with pytest.raises(ValueError):
        IdGates(max_dist_m=0.0)


@pytest.mark.parametrize("seed", range(25))
def test_matching_is_the_largest_then_cheapest_admissible_matching(seed):
    """Cross-check on dense clutter (several candidates per corner) against exhaustive enumeration."""
    rng = np.random.default_rng(seed)
    n, m = rng.integers(1, 6), rng.integers(1, 6)
    prev, new = rng.uniform(0, 1.5, (n, 2)), rng.uniform(0, 1.5, (m, 2))
    tp, tn = rng.normal(0, np.radians(10), (n, 2)), rng.normal(0, np.radians(10), (m, 2))
    gates = IdGates()
    d = np.linalg.norm(prev[:, None] - new[None], axis=2)
    a = wall_angle_error_deg(np.repeat(tp, m, 0), np.tile(tn, (n, 1))).reshape(n, m)
    cost = np.where((d <= gates.max_dist_m) & (a <= gates.max_angle_deg),
                    (d / gates.max_dist_m) ** 2 + (a / gates.max_angle_deg) ** 2, np.inf)
    got = match_corners(prev, tp, new, tn, gates)
    assert len(np.unique(got.i_prev)) == len(got.i_prev) and len(np.unique(got.i_new)) == len(got.i_new)
    k, best = _brute_force(cost)
    assert len(got.i_new) == k
    assert cost[got.i_prev, got.i_new].sum() == pytest.approx(best, abs=1e-9)


def test_ids_are_never_reused_after_a_corner_disappears():
    xy, dirs, owner = building_corners(buildings(2))
    ids1, c1 = assign_ids(np.zeros(0, np.int64), match_corners(xy[:0], dirs[:0], xy, dirs), len(xy), 1)
    keep = owner != 0
    m2 = match_corners(xy, dirs, xy[keep], dirs[keep])
    ids2, c2 = assign_ids(ids1, m2, keep.sum(), c1)
    assert (ids2 == ids1[keep]).all() and c2 == c1
    m3 = match_corners(xy[keep], dirs[keep], xy, dirs)  # the building is back: its corners are new ones
    ids3, c3 = assign_ids(ids2, m3, len(xy), c2)
    assert set(ids3[~keep]).isdisjoint(ids1) and c3 == c2 + (~keep).sum()
