"""A pose graph solved region by region: spatial submaps whose boundary is a condensed separator.

The method (Tectonic SAM, Ni & Dellaert; a nested dissection of one level; multi-robot PGO solves the same split):
  1. Partition. The poses are split by recursive coordinate bisection of their horizontal positions (the median of
     the longer axis) until no region holds more than ``max_poses``: what one region costs is bounded whatever the
     city's size. Every factor belongs to the region of its first pose (a GNSS bias link to the region of its first
     bias state's fix). A variable touched by the factors of two or more regions is a *separator* (the poses at either
     end of an odometry edge or a loop across a border, the GNSS bias states whose fixes fall on both sides, the
     shared lever arm); every other variable is *interior* to one region.
  2. Rounds. Each region, side by side (``pipeline.parallel.parallel_map``: in this process, a process pool, or
     tasks of the dask cluster the stage runs on): its interior solved by Levenberg-Marquardt with its separators
     held at their current values (tight priors), then its factors linearised there and its interior eliminated
     (gtsam's partial elimination), leaving the Schur complement of the region on its separators. The sum of those
     is the whole graph's Gauss-Newton system on the separators (exact: the interior of a region appears in no other
     region's factors); its solution moves the separators, and the next round starts from there.
  3. Stop when a round moves no separator more than ``tol_m`` / ``tol_rad`` (at most ``rounds``).

At the fixed point every region's interior is optimal given the separators and the reduced gradient on the
separators is zero: the joint optimum (not an approximation of it). The separator system grows with the length of
the borders (for a city, with the square root of its area), not with the number of drives over them.
Plain data in and out (``factors.graph.Problem`` lists, numpy arrays); gtsam objects are built inside each task.
"""
from __future__ import annotations

import contextlib
import logging
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Iterator

import gtsam
import numpy as np

from stages.posegraph.config import RegionConfig, SolveConfig
from stages.posegraph.factors import graph as fg
from stages.posegraph.factors.graph import Problem

SOLVE_DEFAULTS = SolveConfig()  # the solve section's defaults, for callers that pass none (tests)

log = logging.getLogger(__name__)

_HOLD_SIGMA_M = 1e-6  # separators held in a region's interior solve
_HOLD_SIGMA_RAD = 1e-7
# A region's interior is solved to this relative decrease, not to the joint solve's (1e-5 of the whole error): warm
# started after its separators moved, an interior stopped at 1e-5 barely follows them, the Schur gradient stays, and
# the rounds creep (synthetic block city of test_regions: 30 rounds unconverged at 1e-5, 9 rounds at 1e-9, same CPU).
INTERIOR_RELATIVE_TOL = 1e-9


class RegionParams(RegionConfig):
    """The stage's region settings (``RegionConfig``: ``max_poses``, ``rounds``, ``tol_m``) and how the solve runs:
    ``workers``, regions solved at a time (None: ``parallel_map``'s default, the usable cores or the cluster); a
    round moving no separator more than ``tol_m`` nor turning one more than ``tol_rad`` (a tenth of it) ends the
    solve."""

    workers: int | None = None

    @property
    def tol_rad(self) -> float:
        return self.tol_m * 0.1


def partition_poses(xy: np.ndarray, max_poses: int) -> np.ndarray:
    """(N,) region label of each pose: recursive median bisection of the longer horizontal axis until every region
    holds at most ``max_poses`` poses (0 or N <= max_poses: one region). Labels are 0..R-1 in split order."""
    xy = np.asarray(xy, float)
    labels = np.zeros(len(xy), np.int64)
    if max_poses <= 0 or len(xy) <= max_poses:
        return labels
    out: list[np.ndarray] = []
    stack = [np.arange(len(xy))]
    while stack:
        idx = stack.pop()
        if len(idx) <= max_poses:
            out.append(idx)
            continue
        pts = xy[idx]
        axis = int(np.argmax(np.ptp(pts, axis=0)))
        order = idx[np.argsort(pts[:, axis], kind="stable")]
        half = len(order) // 2
        stack += [order[half:], order[:half]]
    for r, idx in enumerate(sorted(out, key=lambda a: int(a.min()))):
        labels[idx] = r
    return labels


@dataclass
class RegionSpec:
    """One region's sub-problem in local indices and how they map to the whole problem's."""

    region: int
    problem: Problem  # poses 0..P-1 = ``pose_ids``; biases 0..B-1 = ``bias_ids``
    pose_ids: np.ndarray
    bias_ids: np.ndarray
    levers: list[tuple[float, ...]]  # local lever index -> lever value (the shared lever variables)
    sep_poses: np.ndarray  # local pose indices that are separators
    sep_biases: np.ndarray  # local bias indices that are separators
    lever_priors: bool  # this region carries the lever arms' priors (exactly one region does)

    @property
    def n_interior_poses(self) -> int:
        return len(self.pose_ids) - len(self.sep_poses)


@dataclass
class Partition:
    labels: np.ndarray  # (N,) region of each pose
    regions: list[RegionSpec]
    sep_poses: np.ndarray  # global indices
    sep_biases: np.ndarray
    levers: list[tuple[float, ...]]
    stats: dict = field(default_factory=dict)


def _lever(p) -> tuple[float, ...]:
    return tuple(float(v) for v in np.asarray(p.lever_arm_m, float))


def partition_problem(problem: Problem, labels: np.ndarray) -> Partition:
    """The regions' sub-problems for pose labels ``labels`` (``partition_poses``)."""
    labels = np.asarray(labels, np.int64)
    n_regions = int(labels.max()) + 1 if len(labels) else 1
    bias_home = np.full(problem.n_biases, -1, np.int64)
    for g in problem.positions:
        if g.bias >= 0 and bias_home[g.bias] < 0:
            bias_home[g.bias] = labels[g.i]
    for k in range(problem.n_biases):  # a bias state no fix measures: its predecessor's region
        if bias_home[k] < 0:
            bias_home[k] = bias_home[k - 1] if k > 0 else 0
    owner = {
        "betweens": np.array([labels[b.i] for b in problem.betweens], np.int64),
        "positions": np.array([labels[g.i] for g in problem.positions], np.int64),
        "attitudes": np.array([labels[a.i] for a in problem.attitudes], np.int64),
        "pose_priors": np.array([labels[p.i] for p in problem.pose_priors], np.int64),
        "bias_links": np.array([bias_home[b.a] for b in problem.bias_links], np.int64),
        "bias_priors": np.array([bias_home[b.index] for b in problem.bias_priors], np.int64),
    }
    pose_regions: list[set[int]] = [{int(labels[i])} for i in range(problem.n_poses)]
    bias_regions: list[set[int]] = [{int(bias_home[k])} for k in range(problem.n_biases)]
    for b, r in zip(problem.betweens, owner["betweens"]):
        pose_regions[b.j].add(int(r))
    for g, r in zip(problem.positions, owner["positions"]):
        if g.bias >= 0:
            bias_regions[g.bias].add(int(r))
    for b, r in zip(problem.bias_links, owner["bias_links"]):
        bias_regions[b.b].add(int(r))
    sep_p = np.array([i for i, s in enumerate(pose_regions) if len(s) > 1], np.int64)
    sep_b = np.array([k for k, s in enumerate(bias_regions) if len(s) > 1], np.int64)
    levers = sorted({_lever(g) for g in problem.positions if g.bias >= 0})
    lever_region = next((int(r) for g, r in zip(problem.positions, owner["positions"]) if g.bias >= 0), -1)
    sep_p_set, sep_b_set = set(sep_p.tolist()), set(sep_b.tolist())
    specs = []
    for r in range(n_regions):
        poses = sorted(i for i, s in enumerate(pose_regions) if r in s)
        biases = sorted(k for k, s in enumerate(bias_regions) if r in s)
        pl = {g: n for n, g in enumerate(poses)}
        bl = {g: n for n, g in enumerate(biases)}
        sub = Problem(len(poses), problem.initial[poses] if len(poses) else np.zeros((0, 4, 4)))
        sub.betweens = [replace(b, i=pl[b.i], j=pl[b.j]) for b, o in zip(problem.betweens, owner["betweens"]) if o == r]
        sub.positions = [replace(g, i=pl[g.i], bias=bl[g.bias] if g.bias >= 0 else -1)
                         for g, o in zip(problem.positions, owner["positions"]) if o == r]
        sub.attitudes = [replace(a, i=pl[a.i]) for a, o in zip(problem.attitudes, owner["attitudes"]) if o == r]
        sub.pose_priors = [replace(p, i=pl[p.i]) for p, o in zip(problem.pose_priors, owner["pose_priors"]) if o == r]
        sub.n_biases = len(biases)
        sub.bias_links = [replace(b, a=bl[b.a], b=bl[b.b]) for b, o in zip(problem.bias_links, owner["bias_links"])
                          if o == r]
        sub.bias_priors = [replace(b, index=bl[b.index]) for b, o in zip(problem.bias_priors, owner["bias_priors"])
                           if o == r]
        local_levers = []
        for g in sub.positions:  # build_graph's order of first appearance
            if g.bias >= 0 and _lever(g) not in local_levers:
                local_levers.append(_lever(g))
        specs.append(RegionSpec(r, sub, np.asarray(poses, np.int64), np.asarray(biases, np.int64), local_levers,
                                np.array([pl[g] for g in poses if g in sep_p_set], np.int64),
                                np.array([bl[g] for g in biases if g in sep_b_set], np.int64), r == lever_region))
    stats = {"regions": n_regions, "separator_poses": len(sep_p), "separator_biases": len(sep_b),
             "levers": len(levers), "largest_region_poses": max((len(s.pose_ids) for s in specs), default=0)}
    return Partition(labels, specs, sep_p, sep_b, levers, stats)


@dataclass
class RegionResult:
    region: int
    poses: np.ndarray  # (P,4,4) local poses after the interior solve (separators as given)
    biases: np.ndarray  # (B,3) local bias values (the negated bias the graph holds)
    keys: list[tuple[str, int]]  # the Schur complement's variables in order: ("x"|"b", global), ("l", local)
    H: np.ndarray  # Schur complement on the separators (information)
    eta: np.ndarray  # its information vector: the Gauss-Newton step solves H d = eta
    error: float  # the region's factors' error after its interior solve
    n_variables: int = 0  # variables of the region's graph (what its solve touched)


def _region_graph(spec: RegionSpec, poses: np.ndarray, biases: np.ndarray, levers: dict):
    graph, values, tags = fg.build_graph(spec.problem, poses)
    if not spec.lever_priors:
        kept = gtsam.NonlinearFactorGraph()
        for f, (name, _) in enumerate(tags):
            if name != "lever_arms":
                kept.add(graph.at(f))
        graph = kept
    for k in range(spec.problem.n_biases):
        values.update(fg._bias_key(k), np.asarray(biases[k], float))
    for k, lev in enumerate(spec.levers):
        values.update(fg._lever_key(k), np.asarray(levers[lev], float))
    return graph, values


def solve_region(spec: RegionSpec, poses: np.ndarray, biases: np.ndarray, levers: dict,
                 max_iterations: int = SOLVE_DEFAULTS.max_iterations, relative_error_tol: float = 1e-7) -> RegionResult:
    """One region's round: its interior by LM with its separators held at ``poses`` / ``biases`` / ``levers``
    (local poses (P,4,4), local biases (B,3), lever value -> current (3,)), then the Schur complement of its
    linearised factors on the separators. Touches only the region's poses and its separators."""
    graph, values = _region_graph(spec, poses, biases, levers)
    sep_keys = [fg._key(int(i)) for i in spec.sep_poses] + [fg._bias_key(int(k)) for k in spec.sep_biases] \
        + [fg._lever_key(k) for k in range(len(spec.levers))]
    held = gtsam.NonlinearFactorGraph(graph)
    pose_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([_HOLD_SIGMA_RAD] * 3 + [_HOLD_SIGMA_M] * 3))
    point_noise = gtsam.noiseModel.Isotropic.Sigma(3, _HOLD_SIGMA_M)
    for i in spec.sep_poses:
        held.add(gtsam.PriorFactorPose3(fg._key(int(i)), gtsam.Pose3(poses[i]), pose_noise))
    for k in spec.sep_biases:
        held.add(gtsam.PriorFactorPoint3(fg._bias_key(int(k)), np.asarray(biases[k], float), point_noise))
    for k, lev in enumerate(spec.levers):
        held.add(gtsam.PriorFactorPoint3(fg._lever_key(k), np.asarray(levers[lev], float), point_noise))
    opts = gtsam.LevenbergMarquardtParams()
    opts.setMaxIterations(max_iterations)
    opts.setRelativeErrorTol(relative_error_tol)
    opts.setAbsoluteErrorTol(1e-9)
    result = gtsam.LevenbergMarquardtOptimizer(held, values, opts).optimize()
    for i in spec.sep_poses:  # exactly where they were held
        result.update(fg._key(int(i)), gtsam.Pose3(poses[i]))
    for k in spec.sep_biases:
        result.update(fg._bias_key(int(k)), np.asarray(biases[k], float))
    for k, lev in enumerate(spec.levers):
        result.update(fg._lever_key(k), np.asarray(levers[lev], float))
    out_poses = fg.poses_from_values(result, spec.problem.n_poses)
    out_biases = np.array([result.atPoint3(fg._bias_key(k)) for k in range(spec.problem.n_biases)]).reshape(-1, 3)
    keys = [("x", int(spec.pose_ids[i])) for i in spec.sep_poses] + \
        [("b", int(spec.bias_ids[k])) for k in spec.sep_biases] + [("l", k) for k in range(len(spec.levers))]
    if sep_keys:
        lin = graph.linearize(result)
        ordering = gtsam.Ordering.ColamdConstrainedLastGaussianFactorGraph(lin, sep_keys)
        interior = gtsam.Ordering()
        sep_set = set(sep_keys)
        for n in range(ordering.size()):
            if ordering.at(n) not in sep_set:
                interior.push_back(ordering.at(n))
        _, remaining = lin.eliminatePartialSequential(interior)
        sep_order = gtsam.Ordering()
        present = set(remaining.keys())
        for key in sep_keys:
            sep_order.push_back(key)
        dims = [6 if k[0] == "x" else 3 for k in keys]
        if all(key in present for key in sep_keys):
            H, eta = remaining.hessian(sep_order)
        else:  # defensive: each separator is named by a factor of the region, so it stays in ``remaining``
            H, eta = _partial_hessian(remaining, sep_keys, dims, present)
    else:
        H, eta = np.zeros((0, 0)), np.zeros(0)
    return RegionResult(spec.region, out_poses, out_biases, keys, np.asarray(H), np.asarray(eta).ravel(),
                        float(graph.error(result)), int(result.size()))


def _partial_hessian(remaining, sep_keys, dims, present):
    """``remaining.hessian`` over the separators it names, zero rows and columns for the others."""
    H, eta = np.zeros((sum(dims),) * 2), np.zeros(sum(dims))
    if not present:
        return H, eta
    order = gtsam.Ordering()
    for key in sep_keys:
        if key in present:
            order.push_back(key)
    h, e = remaining.hessian(order)
    offsets = np.cumsum([0] + dims)
    idx = np.concatenate([np.arange(offsets[n], offsets[n + 1]) for n, key in enumerate(sep_keys) if key in present])
    H[np.ix_(idx, idx)] = h
    eta[idx] = np.asarray(e).ravel()
    return H, eta


def _run_region(item) -> RegionResult:
    spec, poses, biases, levers, lm = item
    return solve_region(spec, poses, biases, levers, **lm)


@dataclass
class RegionSolve:
    poses: np.ndarray
    biases: np.ndarray
    rounds: list[dict]
    stats: dict


def optimize_regions(problem: Problem, params: RegionParams, *, initial: np.ndarray | None = None,
                     max_iterations: int = SOLVE_DEFAULTS.max_iterations, relative_error_tol: float = 1e-7,
                     map_fn: Callable | None = None) -> RegionSolve:
    """The joint optimum of ``problem`` (as ``factors.graph.optimize`` finds it) solved region by region (module
    docstring). ``map_fn(fn, items)``: how the regions of a round run side by side (default
    ``pipeline.parallel.parallel_map`` with ``params.workers``)."""
    t0 = time.perf_counter()
    poses = np.array(problem.initial if initial is None else initial, float)
    labels = partition_poses(poses[:, :2, 3], params.max_poses)
    part = partition_problem(problem, labels)
    if map_fn is None:
        from pipeline.parallel import parallel_map

        def map_fn(fn, items):
            return parallel_map(fn, items, workers=params.workers)
    biases = np.zeros((problem.n_biases, 3))
    levers = {lev: np.asarray(lev, float) for lev in part.levers}
    lm = {"max_iterations": max_iterations, "relative_error_tol": min(relative_error_tol, INTERIOR_RELATIVE_TOL)}
    slot: dict[tuple[str, int], int] = {}
    size = 0
    for key in [("x", int(i)) for i in part.sep_poses] + [("b", int(k)) for k in part.sep_biases] + \
            [("l", k) for k in range(len(part.levers))]:
        slot[key] = size
        size += 6 if key[0] == "x" else 3
    rounds: list[dict] = []
    for rnd in range(max(params.rounds, 1)):
        items = [(s, poses[s.pose_ids], biases[s.bias_ids], levers, lm) for s in part.regions]
        results = map_fn(_run_region, items)
        H, eta = np.zeros((size, size)), np.zeros(size)
        for spec, res in zip(part.regions, results):
            interior = np.setdiff1d(np.arange(len(spec.pose_ids)), spec.sep_poses)
            poses[spec.pose_ids[interior]] = res.poses[interior]
            ib = np.setdiff1d(np.arange(len(spec.bias_ids)), spec.sep_biases)
            biases[spec.bias_ids[ib]] = res.biases[ib]
            if not len(res.keys):
                continue
            starts = [slot[_global(k, spec, part)] for k in res.keys]
            idx = np.concatenate([np.arange(a, a + (6 if k[0] == "x" else 3)) for a, k in zip(starts, res.keys)])
            H[np.ix_(idx, idx)] += res.H
            eta[idx] += res.eta
        error = float(sum(r.error for r in results))
        if size == 0:
            rounds.append({"round": rnd + 1, "error": error, "moved_m": 0.0, "turned_rad": 0.0})
            break
        step = np.linalg.solve(H + 1e-12 * np.eye(size), eta)
        moved, turned = _apply(step, slot, poses, biases, levers, part)
        rounds.append({"round": rnd + 1, "error": error, "moved_m": moved, "turned_rad": turned})
        log.debug("regions round %d: error %.6g, separators moved %.2e m / %.2e rad", rnd + 1, error, moved, turned)
        if moved <= params.tol_m and turned <= params.tol_rad:
            break
    stats = dict(part.stats) | {"poses": problem.n_poses, "rounds": len(rounds),
                                "last_moved_m": rounds[-1]["moved_m"] if rounds else 0.0,
                                "wall_s": round(time.perf_counter() - t0, 3)}
    record(stats)
    log.info("posegraph (regions): %d poses in %d regions (largest %d), %d separator poses, %d separator bias "
             "states; %d rounds, last separator step %.1e m", problem.n_poses, stats["regions"],
             stats["largest_region_poses"], stats["separator_poses"], stats["separator_biases"], stats["rounds"],
             stats["last_moved_m"])
    return RegionSolve(poses, biases, rounds, stats)


def _global(key: tuple[str, int], spec: RegionSpec, part: Partition) -> tuple[str, int]:
    """A region's separator key in the whole problem's numbering (a lever: its index among ``part.levers``)."""
    return key if key[0] != "l" else ("l", part.levers.index(spec.levers[key[1]]))


def _apply(step, slot, poses, biases, levers, part) -> tuple[float, float]:
    moved, turned = 0.0, 0.0
    for (kind, g), s in slot.items():
        if kind == "x":
            d = step[s:s + 6]
            poses[g] = gtsam.Pose3(poses[g]).retract(d).matrix()
            moved, turned = max(moved, float(np.linalg.norm(d[3:]))), max(turned, float(np.linalg.norm(d[:3])))
        elif kind == "b":
            biases[g] += step[s:s + 3]
            moved = max(moved, float(np.linalg.norm(step[s:s + 3])))
        else:
            lev = part.levers[g]
            levers[lev] = levers[lev] + step[s:s + 3]
            moved = max(moved, float(np.linalg.norm(step[s:s + 3])))
    return moved, turned


_PARTITIONED: list[tuple[RegionParams, list[dict]]] = []


@contextlib.contextmanager
def partitioned(params: RegionParams) -> Iterator[list[dict]]:
    """Within the block, ``factors.graph.optimize`` (every solve of the pose-graph passes) runs region by region
    (``optimize_regions``) when the graph has more than ``params.max_poses`` poses; the block's value collects each
    such solve's figures (regions, separators, rounds, seconds)."""
    entry: tuple[RegionParams, list[dict]] = (params, [])
    _PARTITIONED.append(entry)
    try:
        yield entry[1]
    finally:
        _PARTITIONED.remove(entry)


def active() -> RegionParams | None:
    return _PARTITIONED[-1][0] if _PARTITIONED else None


def record(stats: dict) -> None:
    """Add one region solve's figures to the innermost ``partitioned`` block's list."""
    if _PARTITIONED:
        _PARTITIONED[-1][1].append(stats)


def solves_summary(solves: list[dict]) -> dict | None:
    """The figures of a stage's region solves, for its metadata: how many, the largest region and separator, rounds
    (total and most), and the last solve's."""
    if not solves:
        return None
    return {"solves": len(solves), "regions_max": max(s["regions"] for s in solves),
            "largest_region_poses": max(s["largest_region_poses"] for s in solves),
            "separator_poses_max": max(s["separator_poses"] for s in solves),
            "rounds_total": sum(s["rounds"] for s in solves), "rounds_max": max(s["rounds"] for s in solves),
            "last": solves[-1]}
