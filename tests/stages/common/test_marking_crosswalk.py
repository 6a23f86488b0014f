"""A crosswalk the raster's coverage cut at an oblique angle: its outline stays on the paint (synthetic truth,
sampled like a lidar raster), its direction is the stripes' long edges, and its corners mostly stay on the seen
side of the coverage edge."""
from __future__ import annotations

import numpy as np
import pytest

from fixtures.crosswalk_cuts import CELL_M as CELL
from fixtures.crosswalk_cuts import cut_crosswalk, random_cuts, signed_inside_m
from stages.common.marking_crosswalk import stripe_axis
from stages.common.marking_vectors import vectorize_markings


def _crosswalks(mask):
    return [f for f in vectorize_markings(mask, 0.0, 0.0, CELL) if f.type == "crosswalk"]


@pytest.mark.parametrize("angle_deg, cut_deg, cut_at_m", [(7.0, 60.0, 2.5), (33.0, 120.0, 2.0), (20.0, -40.0, 3.0),
                                                          (50.0, 75.0, 1.8), (0.0, 45.0, 2.5)])
def test_a_crosswalk_cut_obliquely_keeps_its_corners_on_the_seen_paint(angle_deg, cut_deg, cut_at_m):
    """The stripes end along the coverage edge: every corner lies on the painted crosswalk (at most 5 cm
    outside it; the principal axes of the cut stripes turned the outline 1-2 deg, which put a far corner 6 cm
    off the paint, and a side could come out NaN) and not far past the edge into what the raster did not
    observe (at most 0.2 m: a cut shaving under ~0.2 m off a corner is below what the scanlines tell from a
    ragged end), with a corner at the cut, away from the paint's corners."""
    for seed in range(3):
        mask, paint, (p0, normal) = cut_crosswalk(angle_deg, cut_deg, cut_at_m, seed)
        [cw] = _crosswalks(mask)
        assert cw.xy_m.shape == (4, 2) and np.isfinite(cw.xy_m).all()
        inside = [signed_inside_m(paint, p) for p in cw.xy_m]
        past_edge = (cw.xy_m - p0) @ normal
        assert min(inside) >= -0.05, (seed, inside)
        assert past_edge.max() <= 0.2, (seed, past_edge)
        off = [np.linalg.norm(paint - p, axis=1).min() for p in cw.xy_m]
        assert max(off) > 0.3, (seed, off)  # a corner at the cut, not at a corner of the paint


def test_crosswalks_cut_at_random_angles_stay_on_the_paint():
    """40 random cuts (angle of the crosswalk, direction and place of the edge): no corner more than 5 cm outside
    the painted crosswalk; at least 80 % of corners within 5 cm of the seen side, none over 0.2 m past it (a cut
    shaving under ~0.2 m off a corner is below what the scanlines tell from a ragged end)."""
    inside, past, n_cw = [], [], 0
    for angle, cut, at, seed in random_cuts(40, 2026):
        mask, paint, (p0, normal) = cut_crosswalk(angle, cut, at, seed)
        for cw in _crosswalks(mask):
            n_cw += 1
            assert np.isfinite(cw.xy_m).all()
            inside += [signed_inside_m(paint, p) for p in cw.xy_m]
            past += list((cw.xy_m - p0) @ normal)
    inside, past = np.array(inside), np.array(past)
    assert n_cw >= 30
    assert inside.min() >= -0.05, inside.min()
    assert (past <= 0.05).mean() >= 0.8 and past.max() <= 0.2, (np.sort(past)[-8:], (past <= 0.05).mean())


def test_stripe_axis_follows_the_long_edges_of_obliquely_cut_stripes():
    """Stripes cut at 45 deg are trapezoids: their principal axes turn (about 1 deg), the midlines of their
    full-width stretches do not (the rest is the random partial cells of the edges, as on whole stripes)."""
    from stages.common.marking_vectors import _components

    principal, refined = [], []
    for angle in (0.0, 7.0, 33.0):
        for seed in range(4):
            mask, rect, _ = cut_crosswalk(angle, 45.0, 2.5, seed)
            u = (rect[1] - rect[0]) / np.linalg.norm(rect[1] - rect[0])
            v = np.array([-u[1], u[0]])
            bars = [c for c in _components(mask, 0.0, 0.0, CELL, 0.04) if c.width_m > 0.35]
            p = np.sum([len(b.pts) * (b.axis if b.axis @ u >= 0 else -b.axis) for b in bars], axis=0)
            a = stripe_axis([(b.pts, b.axis) for b in bars], CELL)
            principal.append(np.degrees(np.arcsin(abs(p @ v) / np.linalg.norm(p))))
            refined.append(np.degrees(np.arcsin(abs(a @ v))))
    assert np.mean(principal) > 0.7, principal
    assert np.mean(refined) <= 0.3 and max(refined) <= 1.0, refined
