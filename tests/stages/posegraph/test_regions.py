"""Oracle tests of the region-wise solve (stages/posegraph/regions.py) on a synthetic city with known truth: two
drives around a block, ICP-like odometry, GNSS through a Gauss-Markov bias chain, loops between the passes."""
from __future__ import annotations

import numpy as np
import pytest

from stages.posegraph import regions
from stages.posegraph.factors.graph import Between, BiasLink, BiasPrior, PositionPrior, Problem, optimize


def _pose(x, y, yaw):
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = x, y
    return T


def _block(n_per_side: int, step_m: float, x0: float) -> list[np.ndarray]:
    out, x, y, yaw = [], x0, 0.0, 0.0
    for side in range(4):
        for _ in range(n_per_side):
            out.append(_pose(x, y, yaw))
            x, y = x + step_m * np.cos(yaw), y + step_m * np.sin(yaw)
        yaw += np.pi / 2
    return out


def _exp(d):
    import gtsam

    return gtsam.Pose3.Expmap(d).matrix()


def synthetic(seed: int = 3, drives: int = 2, n_per_side: int = 60, gnss_every: int = 5,
              bias_m: float = 0.0) -> tuple[Problem, np.ndarray]:
    """(problem, truth (N,4,4)): ``drives`` passes around a 2x2 grid of blocks (each drive its own block pair)."""
    rng = np.random.default_rng(seed)
    truth: list[np.ndarray] = []
    starts = []
    for d in range(drives):
        starts.append(len(truth))
        truth += _block(n_per_side, 1.0, x0=(d % 2) * 0.0) if d % 2 == 0 else \
            [_pose(*(T[:2, 3] + [0.0, 0.3]), np.arctan2(T[1, 0], T[0, 0])) for T in _block(n_per_side, 1.0, 0.0)]
    starts.append(len(truth))
    truth = np.array(truth)
    n = len(truth)
    p = Problem(n, np.zeros((n, 4, 4)))
    odo_info = np.diag([1e4, 1e4, 1e4, 1e4, 1e4, 1e4])
    est = []
    for d in range(drives):
        a, b = starts[d], starts[d + 1]
        T = truth[a].copy()
        T[:2, 3] += rng.normal(0, 0.5, 2)
        est.append(T)
        for i in range(a, b - 1):
            rel = np.linalg.inv(truth[i]) @ truth[i + 1] @ _exp(rng.normal(0, 0.01, 6))
            p.betweens.append(Between(i, i + 1, rel, odo_info))
            T = T @ rel @ _exp(np.r_[0, 0, 0.004, 0, 0, 0])  # drift in the initial guess
            est.append(T)
    p.initial = np.array(est)
    k = 0
    for d in range(drives):
        first = k
        for i in range(starts[d], starts[d + 1], gnss_every):
            fix = truth[i, :3, 3] + rng.normal(0, 0.05, 3) + np.array([bias_m, 0, 0])
            p.positions.append(PositionPrior(i, fix, np.array([0.05, 0.05, 0.1]), "none", 1.0, np.zeros(3), k))
            if k > first:
                p.bias_links.append(BiasLink(k - 1, k, np.full(3, 0.05), 0.95))
            p.bias_priors.append(BiasPrior(k, np.full(3, 0.5)))
            k += 1
    p.n_biases = k
    loop_info = np.diag([1e3] * 6)
    for i in range(starts[1], starts[2], 7) if drives > 1 else []:
        j = int(np.argmin(np.linalg.norm(truth[starts[0]:starts[1], :2, 3] - truth[i, :2, 3], axis=1)))
        rel = np.linalg.inv(truth[j]) @ truth[i] @ _exp(rng.normal(0, 0.01, 6))
        p.betweens.append(Between(j, i, rel, loop_info, "loop", "huber", 3.0))
    return p, truth


def serial(fn, items):
    return [fn(x) for x in items]


def test_partition_bounds_region_size_and_is_spatial():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 1000, (5000, 2))
    labels = regions.partition_poses(xy, 700)
    counts = np.bincount(labels)
    assert counts.max() <= 700 and len(counts) == 8
    for r in range(len(counts)):  # compact: each region's box is far smaller than the city
        assert np.ptp(xy[labels == r], axis=0).min() < 600
    assert np.all(regions.partition_poses(xy, 0) == 0)


def test_regions_converge_to_the_joint_solution():
    problem, truth = synthetic()
    joint = optimize(problem, relative_error_tol=1e-10)
    params = regions.RegionParams(max_poses=120, rounds=30, tol_m=1e-6)
    sol = regions.optimize_regions(problem, params, relative_error_tol=1e-10, map_fn=serial)
    assert sol.stats["regions"] >= 4 and sol.stats["largest_region_poses"] <= 120 + sol.stats["separator_poses"]
    diff = np.linalg.norm(sol.poses[:, :3, 3] - joint[:, :3, 3], axis=1)
    assert diff.max() < 1e-4, diff.max()  # the same optimum (0.1 mm)
    # and the optimum is a real one: both near the truth, far nearer than the initial guess
    err = np.linalg.norm(joint[:, :2, 3] - truth[:, :2, 3], axis=1)
    assert np.sqrt(np.mean(err ** 2)) < 0.1
    assert np.sqrt(np.mean(np.linalg.norm(problem.initial[:, :2, 3] - truth[:, :2, 3], axis=1) ** 2)) > 0.5


def test_one_round_alone_is_not_the_answer():
    """The separators' updates matter: stopping after one round (separators at the initial guess) is far off."""
    problem, _ = synthetic()
    joint = optimize(problem, relative_error_tol=1e-10)
    one = regions.optimize_regions(problem, regions.RegionParams(max_poses=120, rounds=1), map_fn=serial)
    one_poses = one.poses.copy()
    assert np.abs(one_poses[:, :3, 3] - joint[:, :3, 3]).max() > 0.01


def test_a_region_touches_only_its_poses_and_boundary():
    problem, _ = synthetic()
    labels = regions.partition_poses(problem.initial[:, :2, 3], 120)
    part = regions.partition_problem(problem, labels)
    sep = set(part.sep_poses.tolist())
    seen_interior: set[int] = set()
    for spec in part.regions:
        ids = set(spec.pose_ids.tolist())
        own = set(np.flatnonzero(labels == spec.region).tolist())
        assert ids - own <= sep  # other regions' poses only as separators
        interior = ids - sep
        assert not (interior & seen_interior)  # each interior pose in one region
        seen_interior |= interior
        res = regions.solve_region(spec, problem.initial[spec.pose_ids], np.zeros((len(spec.bias_ids), 3)),
                                   {lev: np.asarray(lev) for lev in part.levers})
        assert {k for kind, k in res.keys if kind == "x"} == {int(spec.pose_ids[i]) for i in spec.sep_poses}
        # held separators stay where they were given
        for i in spec.sep_poses:
            assert np.allclose(res.poses[i], problem.initial[spec.pose_ids[i]])
    assert seen_interior | sep == set(range(problem.n_poses))
    # every factor in exactly one region
    assert sum(len(s.problem.betweens) for s in part.regions) == len(problem.betweens)
    assert sum(len(s.problem.positions) for s in part.regions) == len(problem.positions)
    assert sum(len(s.problem.bias_links) for s in part.regions) == len(problem.bias_links)


def test_partitioned_block_routes_optimize_through_regions():
    problem, _ = synthetic(n_per_side=40)
    joint = optimize(problem, relative_error_tol=1e-10)
    with regions.partitioned(regions.RegionParams(max_poses=100, rounds=30, tol_m=1e-6, workers=1)):
        split = optimize(problem, relative_error_tol=1e-10)
    assert np.abs(split[:, :3, 3] - joint[:, :3, 3]).max() < 1e-4
    assert regions.active() is None


@pytest.mark.parametrize("max_poses", [0, 10_000])
def test_one_region_is_the_joint_solve(max_poses):
    problem, _ = synthetic(n_per_side=30)
    joint = optimize(problem)
    with regions.partitioned(regions.RegionParams(max_poses=max_poses)):
        same = optimize(problem)
    assert np.array_equal(joint, same)
