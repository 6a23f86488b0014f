"""The out-and-back route and the drifting prior (issue 63): the two passes of the street in their own lanes, in
opposite directions, joined by U-turns; a heading random walk whose positions integrate it."""
from __future__ import annotations

import numpy as np
import pytest

from pipeline.errors import ConfigError
from stages.simulate.city import LANE_W_M
from stages.simulate.core import build_city
from stages.simulate.drive import heading_walk
from stages.simulate.presets import get_preset
from stages.simulate.trajectory import lane_polyline, out_and_back_nodes, plan_drive


def test_out_and_back_nodes_go_to_the_end_of_the_street_and_back():
    assert out_and_back_nodes(3, 4) == [(1, 0), (1, 1), (1, 2), (1, 3), (1, 4), (1, 3), (1, 2), (1, 1)]


def test_the_two_passes_run_opposite_in_their_own_lanes():
    p = get_preset("demo", route="out_and_back")
    city = build_city(p, 5)
    nodes = out_and_back_nodes(p.n_rows, p.n_cols)
    poly, _ = lane_polyline(city, nodes, 9)
    traj = plan_drive(poly, [], 1, p.cruise_mps, 0.0, np.random.default_rng(0))
    xy = np.column_stack([traj.east_m, traj.north_m])
    step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    assert step.max() < 0.2  # continuous through both U-turns (100 Hz)
    heading = np.column_stack([np.cos(traj.yaw_enu_rad), np.sin(traj.yaw_enu_rad)])
    mid = city.nodes_en[nodes[2]]
    near = np.linalg.norm(xy - mid, axis=1) < 20.0
    east = near & (heading[:, 0] > 0.9)
    west = near & (heading[:, 0] < -0.9)
    assert east.any() and west.any()
    # the outer lane of a two-lane street each way: 1.5 lanes either side of the centre line, 3 lanes apart
    gap = np.median(xy[west, 1]) - np.median(xy[east, 1])
    assert gap == pytest.approx(3 * LANE_W_M, abs=1.5)


def test_route_must_be_known():
    with pytest.raises(ConfigError, match="route must be one of"):
        get_preset("tiny", route="figure_eight")


def test_heading_walk_integrates_into_positions():
    t = np.arange(0, 1000.0, 5.0)
    straight = np.column_stack([t, np.zeros_like(t)])
    walks = [heading_walk(straight, 10.0, np.random.default_rng(s)) for s in range(200)]
    e_en = np.array([w[0] for w in walks])
    yaw = np.array([w[1] for w in walks])
    assert np.all(e_en[:, 0] == 0.0) and np.all(yaw[:, 0] == 0.0)
    assert np.degrees(yaw[:, -1].std()) == pytest.approx(10.0 * np.sqrt(0.995), rel=0.15)  # per sqrt(km)
    # a straight path's cross-track error is the heading's integral: std ~ L x std(heading at L) / sqrt 3
    assert e_en[:, -1, 1].std() == pytest.approx(1000 * np.radians(10.0) / np.sqrt(3), rel=0.2)
