"""The growing city (issue 59): ``route: districts`` gives drive k its own loop around one block row and two block
columns; the first drives sweep the grid west to east with each window sharing a street with an earlier one; the
survey covers every drive's route; the changes are placed along the first changed drive's window."""

from __future__ import annotations

import json

import numpy as np
import pytest

from stages.simulate.presets import get_preset
from stages.simulate.trajectory import district_loop, loop_nodes


def _edges(loop):
    return {frozenset((a, b)) for a, b in zip(loop, loop[1:] + loop[:1])}


def test_district_windows_sweep_the_grid_and_share_streets():
    p = get_preset("growing")
    n_windows = p.n_rows * (p.n_cols - 1)
    loops = [district_loop(p.n_rows, p.n_cols, k) for k in range(2 * n_windows)]
    assert len({tuple(sorted(lp)) for lp in loops[:n_windows]}) == n_windows  # the first sweep: all different
    for k in range(n_windows):  # later drives revisit the same windows
        assert sorted(loops[k + n_windows]) == sorted(loops[k])
    for k, lp in enumerate(loops[:n_windows]):
        j, i = k % p.n_rows, (k // p.n_rows) % (p.n_cols - 1)
        assert lp == loop_nodes({(j, i), (j, i + 1)}) and len(lp) == 6
        assert max(n[1] for n in lp) - min(n[1] for n in lp) == 2 and max(n[0] for n in lp) - min(n[0] for n in lp) == 1
        if k:  # the map grows: every new window shares a street with an earlier one
            assert any(_edges(lp) & _edges(old) for old in loops[:k])
    with pytest.raises(ValueError):
        district_loop(2, 1, 0)


def test_the_survey_covers_every_route_given():
    from stages.simulate.core import build_city
    from stages.simulate.markings import asphalt_albedo, generate_markings, rasterize_markings
    from stages.simulate.survey import generate_survey
    from stages.simulate.trajectory import lane_polyline

    p = get_preset("growing", n_cols=3, n_rows=1)
    city = build_city(p, 3)
    marks = rasterize_markings(generate_markings(city), city.bounds_en)
    albedo = asphalt_albedo(city.bounds_en, np.random.default_rng(0))
    routes = [lane_polyline(city, district_loop(p.n_rows, p.n_cols, k), 0)[0] for k in (0, 1)]

    def survey(route):
        return generate_survey(city, route, 6.0, marks, albedo, np.random.default_rng(1))[0]

    one, other, both = survey(routes[0]), survey(routes[1]), survey(routes)
    assert np.array_equal(survey([routes[0]]), one)  # one route as a list: the same points (presets unchanged)
    # the union of both corridors: more than either, less than their sum (the shared street once)
    assert max(len(one), len(other)) < len(both) < len(one) + len(other)

    def near(pts, route):  # within the corridor of the polyline ``route``
        a, d = route[:-1][None], np.diff(route, axis=0)[None]
        rel = pts[:, None, :2] - a
        t = np.clip((rel * d).sum(-1) / (d * d).sum(-1), 0.0, 1.0)
        return np.linalg.norm(rel - t[..., None] * d, axis=-1).min(axis=1) <= 6.0 + 0.1

    sample = both[:: max(1, len(both) // 2000)]
    assert np.all(near(sample, routes[0]) | near(sample, routes[1]))
    assert near(sample, routes[1]).mean() > 0.3 and near(sample, routes[0]).mean() > 0.3


@pytest.fixture(scope="module")
def growing_sim(tmp_path_factory):
    from stages.simulate.core import simulate

    out = tmp_path_factory.mktemp("sim_growing")
    p = get_preset("growing", n_cols=3, n_rows=2, survey=False)  # 4 windows: drives 0-3 in four places
    simulate(p, 3, out, n_drives=4, scan_limit=6, changes=True, changes_from_drive=2)
    return out, p


def test_growing_drives_take_their_own_routes(growing_sim):
    out, p = growing_sim
    city = json.loads((out / "truth" / "city.json").read_text())
    nodes = np.asarray(city["intersections_en"])
    starts = []
    for k in range(4):
        j, i = k % p.n_rows, (k // p.n_rows) % (p.n_cols - 1)
        corners = nodes[j : j + 2, i : i + 3].reshape(-1, 2)  # the window's intersections
        xy = np.loadtxt(out / "truth" / f"drive_{k}_poses_tum.txt", usecols=(1, 2), comments="#")
        lo, hi = corners.min(axis=0) - 15.0, corners.max(axis=0) + 15.0  # the lane, the rounded turns
        assert np.all((xy >= lo) & (xy <= hi)), k
        starts.append(xy[0])
    assert min(np.linalg.norm(a - b) for n, a in enumerate(starts) for b in starts[n + 1 :]) > 1.0
    doc = json.loads((out / "simulation.json").read_text())
    assert doc["preset"] == "growing" and doc["changes"]["from_drive"] == 2
