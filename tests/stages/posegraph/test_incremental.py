"""The incremental pose graph (``stages/posegraph/incremental.py``) on a raycast street: a map drive d0 solved alone,
then a new drive d1 solved against d0's poses held; d1 has its own GNSS bias (0.8 m from d0's), so only the loops
onto the held map place it. Oracles: the truth's offset between the drives, and the held poses untouched."""
from __future__ import annotations

import numpy as np
import pytest

from pipeline.errors import ConfigError, DatasetIOError
from pipeline.testing import make_context
from stages.posegraph.params import PosegraphParams
from tests.stages.posegraph.test_posegraph_compute import _map_and_reference_street


def _setup(tmp_path, params: dict | None = None):
    from stages.posegraph.compute import read_drive_inputs, scan_loader

    tables, T0, T1 = _map_and_reference_street()
    p = PosegraphParams(loops={"stride_m": 4.0}, gnss={"every_s": 0.5}).updated(params or {})
    ctx = make_context("posegraph", p, tables, settings={"map_drives": ["d0", "d1"]}, outputs=("report",),
                       workdir=tmp_path)
    drives, _ = read_drive_inputs(ctx)
    return ctx, drives, p, scan_loader(ctx), T0, T1


def _offset_error_m(P0, P1, T0, T1) -> float:
    est = P1[:, :2, 3].mean(0) - P0[:, :2, 3].mean(0)
    true = T1[:, :2, 3].mean(0) - T0[:, :2, 3].mean(0)
    return float(np.linalg.norm(est - true))


def test_a_new_drive_lands_on_the_held_map_which_does_not_move(tmp_path):
    from stages.posegraph.incremental import solve_increment
    from stages.posegraph.solve import solve_map

    ctx, (d0, d1), cfg, load, T0, T1 = _setup(tmp_path)
    held = solve_map([d0], load, cfg).poses
    kept = held.copy()
    sol = solve_increment([d1], [d0], held, load, cfg, max_per_scan=1)
    assert np.array_equal(held, kept)  # the map's poses are read, never written
    assert sol.poses.shape == (d1.n, 4, 4)
    accepted = [r for r in sol.loops if r.accepted]
    assert accepted and all(min(r.i, r.j) < d1.n <= max(r.i, r.j) for r in accepted)  # new drive onto the map
    # the held map poses the loops reach are tightly held variables: the solve left them where they were
    assert sol.timings_s["n_map_poses_reached"] > 0
    # GNSS alone puts d1 0.8 m off d0 (their biases); the loops onto the held map bring it to a few cm
    assert _offset_error_m(held, sol.poses, T0, T1) < 0.05


def test_without_loops_the_new_drive_is_its_gnss_solution(tmp_path):
    """With a loop radius (0.1 m) below the lanes' 1.5 m apart no loop is sought: the drive keeps its own
    odometry + GNSS solution, its bias 0.8 m off d0's (the oracle above can fail)."""
    from stages.posegraph.incremental import solve_increment

    ctx, (d0, d1), cfg, load, T0, T1 = _setup(tmp_path, {"loops.radius_m": 0.1})
    from stages.posegraph.solve import solve_map

    held = solve_map([d0], load, cfg).poses
    sol = solve_increment([d1], [d0], held, load, cfg)
    assert not sol.loops
    assert _offset_error_m(held, sol.poses, T0, T1) > 0.3


def test_held_rows_must_match_the_held_drives(tmp_path):
    from stages.posegraph.incremental import solve_increment

    ctx, (d0, d1), cfg, load, _, _ = _setup(tmp_path)
    with pytest.raises(ValueError, match="held poses"):
        solve_increment([d1], [d0], np.tile(np.eye(4), (d0.n - 1, 1, 1)), load, cfg)


def test_a_held_solution_gone_is_named(tmp_path):
    from stages.posegraph.held import read_held

    with pytest.raises(DatasetIOError, match=r"poses_optimized/0123456789abcdef.*rebuild --full"):
        read_held(tmp_path, {"fingerprint": "0123456789abcdef" * 4, "version": 3}, [])
    with pytest.raises(ConfigError, match="held_poses"):
        read_held(tmp_path, {"version": 3}, [])


def test_nothing_new_is_nothing_to_solve(tmp_path):
    from stages.posegraph.incremental import solve_increment

    ctx, (d0, d1), cfg, load, _, _ = _setup(tmp_path)
    held = np.tile(np.eye(4), (d0.n + d1.n, 1, 1))
    sol = solve_increment([], [d0, d1], held, load, cfg)
    assert sol.poses.shape == (0, 4, 4) and not sol.loops


def test_with_a_frame_prior_the_window_moves_the_held_map_rigidly_and_the_loops_still_place_the_drive(tmp_path):
    """The window (window.py) on the raycast street: d0's frame stated loose (1 m), so the two drives' GNSS share
    the offset between them; d1 still lands on d0 through the loops (relative oracle), d0's window poses move
    rigidly (their relative geometry kept), the rows outside the window keep their values."""
    from stages.posegraph.incremental import solve_increment
    from stages.posegraph.solve import solve_map
    from stages.posegraph.window import FramePrior

    ctx, (d0, d1), cfg, load, T0, T1 = _setup(tmp_path)
    held = solve_map([d0], load, cfg).poses
    frame = FramePrior(held[:, :2, 3].mean(0), np.diag([1.0, 1.0, 1e-4]), 1.0, "map_frame")
    cov = np.tile(np.diag([1e-5, 1e-5, 1e-7]).reshape(9), (d0.n, 1))
    sol = solve_increment([d1], [d0], held, load, cfg, max_per_scan=1, frame=frame, held_cov=cov,
                          held_drive_of_row=np.zeros(d0.n, int))
    win = sol.extra["window"]
    assert win is not None and len(win["graph"].rows) > 0
    moved = win["held_T"]
    out = np.setdiff1d(np.arange(d0.n), win["graph"].rows)
    assert np.array_equal(moved[out], held[out])
    full = win["graph"].rows  # the street: d0 lies within reach of d1 from end to end (no taper)
    assert len(full) == d0.n
    d_before = np.linalg.norm(held[full, :3, 3] - held[full[0], :3, 3], axis=1)
    d_after = np.linalg.norm(moved[full, :3, 3] - moved[full[0], :3, 3], axis=1)
    assert np.max(np.abs(d_after - d_before)) < 1e-6  # rigid where the correction applies whole: distances kept
    assert _offset_error_m(moved, sol.poses, T0, T1) < 0.05
    rec = win["record"]
    assert rec["window_poses"] == len(win["graph"].rows) and rec["dof"] >= 1

