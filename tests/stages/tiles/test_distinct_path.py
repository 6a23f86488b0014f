"""The corner-density gate's driven km (``core.distinct_path_length_m``): every street once, however many drives."""
from __future__ import annotations

import numpy as np
import pytest

from stages.tiles.core import distinct_path_length_m, evaluate_gates


def _line(x0, y, x1, n=200):
    return np.column_stack([np.linspace(x0, x1, n), np.full(n, y)])


def test_one_path_is_its_length_and_repeats_add_nothing():
    a = _line(0, 0, 500)
    assert distinct_path_length_m([a], 5.0, 10.0) == pytest.approx(500.0)
    # the same street again, the other lane, the other way: nothing new
    assert distinct_path_length_m([a, _line(500, 3.5, 0), a + 0.2], 5.0, 10.0) == pytest.approx(500.0)
    # half of it again and 300 m of a parallel street 40 m away: 300 m more
    assert distinct_path_length_m([a, _line(0, 0, 250), _line(0, 40, 300)], 5.0, 10.0) == pytest.approx(800.0, abs=5)


def test_five_laps_of_one_loop_keep_a_one_lap_density():
    t = np.linspace(0, 2 * np.pi, 400)
    lap = np.column_stack([60 * np.cos(t), 60 * np.sin(t)])
    rng = np.random.default_rng(0)
    laps = [lap + rng.normal(0, 0.5, 2) for _ in range(5)]
    km = distinct_path_length_m(laps, 5.0, 10.0) / 1000.0
    assert km == pytest.approx(2 * np.pi * 0.060, rel=0.02)
    measured, failures = evaluate_gates(5, km * 1000.0, {(0, 0)}, {(0, 0)}, 10.0, 0.5)
    assert not failures and measured["corners_per_km"] > 10
    # summed laps would have failed it (5 corners over 1.9 km)
    assert evaluate_gates(5, 5 * km * 1000.0, {(0, 0)}, {(0, 0)}, 10.0, 0.5)[1]
