"""The pose graph in GTSAM: Pose3 per scan, between factors (ICP odometry, loops), GNSS position factors,
INS attitude priors, absolute pose priors (survey anchors, fixed map poses); LM or GNC; marginals.

Pose indices are plain ints 0..N-1 (the caller maps (drive, scan_id) to them). Information matrices are 6x6
in gtsam order (rx ry rz tx ty tz) for a body-frame perturbation. ``T_a_b`` maps frame b into frame a.
"""
from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field

import gtsam
import numpy as np

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Between:
    i: int
    j: int
    T_i_j: np.ndarray
    information: np.ndarray
    kind: str = "odometry"  # odometry | span | wheel | wheel_fused | bridge | loop
    robust: str = "none"  # none | huber | cauchy
    kernel_k: float = 1.0


@dataclass(frozen=True)
class PositionPrior:
    i: int
    position_enu_m: np.ndarray  # antenna position
    sigma_enu_m: np.ndarray  # (3,)
    robust: str = "huber"
    kernel_k: float = 1.345
    lever_arm_m: np.ndarray = field(default_factory=lambda: np.zeros(3))  # antenna in the vehicle frame
    bias: int = -1  # index of the GNSS bias state this fix measures through (-1: none, white noise only)


@dataclass(frozen=True)
class BiasLink:
    """First-order Gauss-Markov step between consecutive GNSS bias states: b_b - decay * b_a ~ N(0, sigma^2)."""

    a: int
    b: int
    sigma_m: np.ndarray  # (3,)
    decay: float = 1.0  # exp(-dt / tau); 1 = random walk


@dataclass(frozen=True)
class BiasPrior:
    """Zero-mean prior on one GNSS bias state (the process is stationary)."""

    index: int
    sigma_m: np.ndarray  # (3,)


@dataclass(frozen=True)
class AttitudePrior:
    """INS attitude at pose i. ``with_yaw`` false: gravity direction only (roll/pitch, ``sigma_rad[0]``
    isotropic), heading left to odometry, loops and the GNSS track."""

    i: int
    R_map_vehicle: np.ndarray
    sigma_rad: np.ndarray  # (3,) body-frame (roll, pitch, yaw-ish) axes
    with_yaw: bool = True


@dataclass(frozen=True)
class PosePrior:
    i: int
    T_map_vehicle: np.ndarray
    information: np.ndarray
    kind: str = "survey"  # survey | fixed
    robust: str = "none"
    kernel_k: float = 1.0


@dataclass
class Problem:
    n_poses: int
    initial: np.ndarray  # (N,4,4)
    betweens: list[Between] = field(default_factory=list)
    positions: list[PositionPrior] = field(default_factory=list)
    attitudes: list[AttitudePrior] = field(default_factory=list)
    pose_priors: list[PosePrior] = field(default_factory=list)
    n_biases: int = 0
    bias_links: list[BiasLink] = field(default_factory=list)
    bias_priors: list[BiasPrior] = field(default_factory=list)


_UP = np.array([0.0, 0.0, 1.0])


def _key(i: int) -> int:
    return gtsam.symbol("x", i)


def _bias_key(j: int) -> int:
    return gtsam.symbol("b", j)


def _antenna_key(n: int) -> int:
    return gtsam.symbol("a", n)


def _lever_key(n: int) -> int:
    return gtsam.symbol("l", n)


# The GNSS bias chain is built from gtsam's own factors: a Python CustomFactor receives a copy of the whole
# Values on every call, which cost 5-6 s per LM iteration on 8448 poses (docs/posegraph.md, sixth pass).
# Variables: per fix an antenna position a (ENU) tied to its pose by a ReferenceFrameFactor (a = T * lever, the
# lever arm a variable held by a tight prior); per bias state the *negated* bias c = -b, so that the fix
# z = a + b + white is BetweenFactorPoint3(c, a, z) (error a - c - z); the Gauss-Markov step c_b - decay c_a
# is a JacobianFactor, exact as a LinearContainerFactor because c lives in a vector space.
_LINK_SIGMA_M = 1e-3  # antenna-to-pose tie (a rigid lever arm)
_LEVER_SIGMA_M = 1e-3
_UNUSED_AXIS_SIGMA_M = 1e6  # horizontal and vertical fixes go in separate factors (each with its own kernel)


def gnss_fix_factors(pose_key: int, bias_key: int, antenna_key: int, lever_key: int, measured_enu_m: np.ndarray,
                     sigma_enu_m: np.ndarray, robust: str, kernel_k: float) -> list:
    """Antenna tie + horizontal and vertical fixes through the bias (see the comment above)."""
    out = [gtsam.ReferenceFrameFactorPoint3Pose3(lever_key, pose_key, antenna_key,
                                                 gtsam.noiseModel.Isotropic.Sigma(3, _LINK_SIGMA_M))]
    for axes in ((0, 1), (2,)):
        sig = np.full(3, _UNUSED_AXIS_SIGMA_M)
        sig[list(axes)] = np.asarray(sigma_enu_m, float)[list(axes)]
        model = _robustify(gtsam.noiseModel.Diagonal.Sigmas(sig), robust, kernel_k)
        out.append(gtsam.BetweenFactorPoint3(bias_key, antenna_key, np.asarray(measured_enu_m, float), model))
    return out


def gauss_markov_factor(key_a: int, key_b: int, decay: float, sigma_m: np.ndarray) -> gtsam.LinearContainerFactor:
    """c_b - decay * c_a ~ N(0, diag(sigma^2)), linear and exact about a zero linearisation point."""
    lin = gtsam.JacobianFactor(key_a, -decay * np.eye(3), key_b, np.eye(3), np.zeros(3),
                               gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigma_m, float)))
    zero = gtsam.Values()
    zero.insert(key_a, np.zeros(3))
    zero.insert(key_b, np.zeros(3))
    return gtsam.LinearContainerFactor(lin, zero)


def _noise(information: np.ndarray, robust: str, k: float):
    base = gtsam.noiseModel.Gaussian.Information(0.5 * (information + information.T))
    return _robustify(base, robust, k)


def _robustify(base, robust: str, k: float):
    if robust == "none":
        return base
    est = {"huber": gtsam.noiseModel.mEstimator.Huber, "cauchy": gtsam.noiseModel.mEstimator.Cauchy}[robust]
    return gtsam.noiseModel.Robust.Create(est.Create(k), base)


def build_graph(problem: Problem, poses: np.ndarray | None = None
                ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, list[tuple[str, int]]]:
    """Factor graph + values at ``poses`` (default ``problem.initial``; biases zero, antennas from the poses);
    ``tags[f] = (list name, index)`` says where factor f came from."""
    poses = problem.initial if poses is None else poses
    graph = gtsam.NonlinearFactorGraph()
    tags: list[tuple[str, int]] = []
    values = gtsam.Values()
    for i in range(problem.n_poses):
        values.insert(_key(i), gtsam.Pose3(poses[i]))
    levers: dict[tuple[float, ...], int] = {}
    for n, b in enumerate(problem.betweens):
        graph.add(gtsam.BetweenFactorPose3(_key(b.i), _key(b.j), gtsam.Pose3(b.T_i_j),
                                           _noise(b.information, b.robust, b.kernel_k)))
        tags.append(("betweens", n))
    for n, g in enumerate(problem.positions):
        if g.bias >= 0:
            lever = tuple(float(v) for v in np.asarray(g.lever_arm_m, float))
            if lever not in levers:
                levers[lever] = _lever_key(len(levers))
                values.insert(levers[lever], np.asarray(lever))
                graph.add(gtsam.PriorFactorPoint3(levers[lever], np.asarray(lever),
                                                  gtsam.noiseModel.Isotropic.Sigma(3, _LEVER_SIGMA_M)))
                tags.append(("lever_arms", len(levers) - 1))
            values.insert(_antenna_key(n), gtsam.Pose3(poses[g.i]).transformFrom(np.asarray(lever)))
            for f in gnss_fix_factors(_key(g.i), _bias_key(g.bias), _antenna_key(n), levers[lever],
                                      g.position_enu_m, g.sigma_enu_m, g.robust, g.kernel_k):
                graph.add(f)
                tags.append(("positions", n))
            continue
        model = _robustify(gtsam.noiseModel.Diagonal.Sigmas(np.asarray(g.sigma_enu_m, float)), g.robust,
                           g.kernel_k)
        if np.any(g.lever_arm_m):
            graph.add(gtsam.GPSFactorArm(_key(g.i), np.asarray(g.position_enu_m, float),
                                         np.asarray(g.lever_arm_m, float), model))
        else:
            graph.add(gtsam.GPSFactor(_key(g.i), np.asarray(g.position_enu_m, float), model))
        tags.append(("positions", n))
    for n, a in enumerate(problem.attitudes):
        if a.with_yaw:
            graph.add(gtsam.PoseRotationPrior3D(_key(a.i), gtsam.Rot3(a.R_map_vehicle),
                                                gtsam.noiseModel.Diagonal.Sigmas(np.asarray(a.sigma_rad, float))))
        else:  # the map's up axis seen in the vehicle frame: invariant to heading
            up_vehicle = np.asarray(a.R_map_vehicle, float).T @ _UP
            graph.add(gtsam.AttitudeFactorPose3(_key(a.i), gtsam.Unit3(_UP),
                                                gtsam.noiseModel.Isotropic.Sigma(2, float(a.sigma_rad[0])),
                                                gtsam.Unit3(up_vehicle)))
        tags.append(("attitudes", n))
    for n, prior in enumerate(problem.pose_priors):
        graph.add(gtsam.PriorFactorPose3(_key(prior.i), gtsam.Pose3(prior.T_map_vehicle),
                                         _noise(prior.information, prior.robust, prior.kernel_k)))
        tags.append(("pose_priors", n))
    _insert_biases(values, problem.n_biases)
    for n, link in enumerate(problem.bias_links):
        graph.add(gauss_markov_factor(_bias_key(link.a), _bias_key(link.b), link.decay, link.sigma_m))
        tags.append(("bias_links", n))
    for n, bp in enumerate(problem.bias_priors):
        graph.add(gtsam.PriorFactorPoint3(_bias_key(bp.index), np.zeros(3),
                                          gtsam.noiseModel.Diagonal.Sigmas(np.asarray(bp.sigma_m, float))))
        tags.append(("bias_priors", n))
    return graph, values, tags


def _insert_biases(values: gtsam.Values, n_biases: int) -> None:
    for j in range(n_biases):
        values.insert(_bias_key(j), np.zeros(3))


def optimize(problem: Problem, *, max_iterations: int = 100, gnc_loops: bool = False,
             initial: np.ndarray | None = None, relative_error_tol: float = 1e-7) -> np.ndarray:
    """Levenberg-Marquardt (or GNC for the loop factors, all others known inliers) -> (N,4,4) poses, from
    ``initial`` when given (else ``problem.initial``); LM stops when an iteration lowers the error by less
    than ``relative_error_tol`` of it. Inside ``regions.partitioned`` a graph larger than its ``max_poses`` is
    solved region by region (``regions.optimize_regions``: the same optimum)."""
    from stages.posegraph import regions  # here: regions builds on this module

    part = regions.active()
    if part is not None and not gnc_loops and 0 < part.max_poses < problem.n_poses:
        return regions.optimize_regions(problem, part, initial=initial, max_iterations=max_iterations,
                                        relative_error_tol=relative_error_tol).poses
    graph, values, tags = build_graph(problem, initial)
    if gnc_loops:
        opts = gtsam.GncLMParams()
        inliers = [f for f, (name, n) in enumerate(tags)
                   if not (name == "betweens" and problem.betweens[n].kind == "loop")]
        opts.setKnownInliers(inliers)
        opts.setAllowNonNoiseModelFactors(True)  # the bias chain's LinearContainerFactors (known inliers)
        opts.setMaxIterations(max_iterations)
        result = gtsam.GncLMOptimizer(graph, values, opts).optimize()
    else:
        opts = gtsam.LevenbergMarquardtParams()
        opts.setMaxIterations(max_iterations)
        opts.setRelativeErrorTol(relative_error_tol)
        opts.setAbsoluteErrorTol(1e-9)
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, opts).optimize()
    return poses_from_values(result, problem.n_poses)


def poses_from_values(values: gtsam.Values, n: int) -> np.ndarray:
    return np.array([values.atPose3(_key(i)).matrix() for i in range(n)])


def _variable_named(err: Exception) -> str:
    """The variable a gtsam elimination error names (``Symbol: x130``), for a one-line message."""
    near = re.search(r"Symbol: (\w+)", str(err))
    return near.group(1) if near else "an unnamed variable"


def pose_marginals(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, n_poses: int) -> list[np.ndarray]:
    """Marginal covariance (6x6, body frame, rotation then translation) of poses 0..n_poses-1.

    gtsam's ``Marginals`` eliminates by Cholesky, which gives up on a graph that is determined but badly
    conditioned: a short straight drive whose heading only the GNSS track fixes, through its bias chain, next to
    ICP edges eight orders of magnitude firmer (the 154 real HDL-64E scans of ``bench_build --preset kitti``:
    eigenvalues 1.7e-4 to 3.4e8). There the covariances come from a QR elimination of the same linearised graph
    (``EliminateQR``: no normal equations, so the condition number is not squared). A graph that QR cannot
    eliminate either is not determined: ``ValueError``."""
    try:
        marginals = gtsam.Marginals(graph, values)
        return [marginals.marginalCovariance(_key(i)) for i in range(n_poses)]
    except RuntimeError as err:
        if "Indeterminate" not in str(err):
            raise
        log.warning("pose graph: gtsam's Cholesky marginals gave up on an ill-conditioned graph (near %s); "
                    "computing them by QR", _variable_named(err))
    try:
        tree = graph.linearize(values).eliminateMultifrontal(gtsam.Ordering.OrderingType.COLAMD, gtsam.EliminateQR)
        out = [tree.marginalCovariance(_key(i)) for i in range(n_poses)]
    except RuntimeError as err:
        raise ValueError(f"the pose graph is not determined near {_variable_named(err)} "
                         "(gtsam's QR elimination failed)") from err
    bad = [i for i, c in enumerate(out) if not np.all(np.isfinite(c))]
    if bad:
        raise ValueError(f"the pose graph is not determined: pose {bad[0]} has a non-finite marginal covariance")
    return out


def marginal_cov_xy_yaw(problem: Problem, poses: np.ndarray) -> np.ndarray:
    """(N,9): marginal covariance of (east m, north m, yaw rad) per pose, rotated into ENU axes."""
    graph, values, _ = build_graph(problem, poses)  # linear in biases and antennas: any point for them will do
    covs = pose_marginals(graph, values, problem.n_poses)
    out = np.empty((problem.n_poses, 9))
    for i in range(problem.n_poses):
        cov = covs[i]  # body frame, (rot, trans)
        R = poses[i, :3, :3]
        B = np.zeros((6, 6))
        B[:3, :3] = R
        B[3:, 3:] = R
        cw = B @ cov @ B.T
        sel = [3, 4, 2]
        out[i] = 0.5 * (cw[np.ix_(sel, sel)] + cw[np.ix_(sel, sel)].T).reshape(9)
    return out


def between_residuals(betweens: list[Between], poses: np.ndarray) -> np.ndarray:
    """Whitened residual norm of each between factor at ``poses`` (no robust kernel: the raw misfit)."""
    out = np.empty(len(betweens))
    for n, b in enumerate(betweens):
        est = gtsam.Pose3(poses[b.i]).between(gtsam.Pose3(poses[b.j]))
        err = gtsam.Pose3.Logmap(gtsam.Pose3(b.T_i_j).between(est))
        L = np.linalg.cholesky(0.5 * (b.information + b.information.T))
        out[n] = float(np.linalg.norm(L.T @ err))
    return out
