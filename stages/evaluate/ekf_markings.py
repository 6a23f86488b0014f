"""Road-marking measurement of the corner EKF: the scan's marking features against the map's marking raster.

Between corners (a street of glass and trees, the corner-poor stretches of issue 28) the corner EKF has only its
motion model; the same map's marking raster still constrains the lateral position and the heading. This module
turns one scan's road features into a Gaussian measurement of the pose, with the MCL's likelihood (Kim et al.
s.2.3; ``mcl.log_likelihood``: ``alpha * sharpness * min(F, effective_points) * correlation`` on the distance
likelihood field), so the two localizers share one measurement model.

The likelihood is not Gaussian (paint is sparse; a dashed line repeats along the road), so it is not linearised.
The posterior of the pose under the EKF's Gaussian prior is evaluated on a grid in the prior's whitened
coordinates ``u = L^-1 (pose - mean)`` (``P = L L^T``), moment-matched, and evaluated again on grids spanning that
posterior (three passes; point-mass filter steps, Bucy & Senne 1971, each projected on a Gaussian). The update the
posterior implies is then written as a linear measurement of the pose, so the EKF applies it to its whole state
(gyro bias, consider states) with the usual Joseph form: in whitened coordinates the measurement's information is
``G = Sigma_u^-1 - I``; along each eigenvector ``e`` of ``G`` with eigenvalue ``g`` above ``min_info`` it is a
measurement ``e^T u`` with variance ``1 / g`` and innovation ``e^T Sigma_u^-1 mu_u / g``. Directions the markings do
not inform (along a road of unbroken lines, ``g`` ~ 0) are not measured: their posterior is the prior, not a grid
artefact. Pure numpy, arrays in, arrays out.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.evaluate import mcl


@dataclass(frozen=True)
class MarkingMeasurement:
    H: np.ndarray  # (r, 3) rows on (x_m, y_m, yaw_rad)
    innovation: np.ndarray  # (r,)
    variance: np.ndarray  # (r,)
    score: float  # posterior-weighted correlation of the scan with the raster


def unit_grid(n: int, half_width: float) -> np.ndarray:
    """(n^3, 3) points of a regular grid on ``[-half_width, half_width]^3``."""
    a = np.linspace(-half_width, half_width, n)
    return np.stack(np.meshgrid(a, a, a, indexing="ij"), axis=-1).reshape(-1, 3)


def _moments(u: np.ndarray, log_w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    w = np.exp(log_w - log_w.max())
    w /= w.sum()
    mu = w @ u
    d = u - mu
    return mu, (d * w[:, None]).T @ d, w


def grid_posterior(q: np.ndarray, P: np.ndarray, features_vehicle_m: np.ndarray, raster: mcl.Raster, gain: float,
                   n: int = 7, half_width: float = 3.0, passes: int = 3
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Posterior of the pose (prior ``N(q, P)``, 3x3) given the features' marking log-likelihood ``gain *
    correlation``, moment-matched in whitened coordinates.

    Returns ``(mu_u, Sigma_u, L, score)``: the posterior mean and covariance of ``u = L^-1 (pose - q)``, the prior's
    Cholesky factor, and the posterior-weighted correlation score. Each pass evaluates ``n^3`` poses spanning
    ``half_width`` std of the previous pass's Gaussian (the first: the prior); a pass's Gaussian is widened by its
    grid spacing so a likelihood narrower than one cell cannot collapse the next grid.
    """
    q = np.asarray(q, dtype=float)[:3]
    L = np.linalg.cholesky(0.5 * (P + P.T) + 1e-12 * np.eye(3))
    base = unit_grid(n, half_width)
    mu, C = np.zeros(3), np.eye(3)
    score = float("nan")
    h = 2.0 * half_width / (n - 1)  # the grid's spacing along each axis of the Gaussian it spans
    for _ in range(passes):
        Lc = np.linalg.cholesky(C)
        u = mu + base @ Lc.T
        poses = q + u @ L.T
        s = mcl.correlation_scores(poses, features_vehicle_m, raster)
        log_w = -0.5 * np.einsum("ij,ij->i", u, u) + gain * s
        mu, C, w = _moments(u, log_w)
        score = float(w @ s)
        C = 0.5 * (C + C.T) + (h * h / 12.0) * (Lc @ Lc.T)
    return mu, C, L, score


def equivalent_measurement(mu_u: np.ndarray, Sigma_u: np.ndarray, L: np.ndarray, min_info: float
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The linear measurement of the pose whose Kalman update turns the prior ``N(0, I)`` (whitened) into
    ``N(mu_u, Sigma_u)``, in the directions where its information exceeds ``min_info`` (in units of the prior's).
    Returns ``(H (r,3), innovation (r,), variance (r,))`` on the unwhitened pose (its gate is the filter's:
    ``consider.update_linear``)."""
    Lam = np.linalg.inv(0.5 * (Sigma_u + Sigma_u.T))
    g, E = np.linalg.eigh(Lam - np.eye(3))
    keep = g > min_info
    g, E = g[keep], E[:, keep]
    if len(g) == 0:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0)
    nu = (E.T @ (Lam @ mu_u)) / g
    return E.T @ np.linalg.inv(L), nu, 1.0 / g


def marking_measurement(q: np.ndarray, P: np.ndarray, features_vehicle_m: np.ndarray, raster: mcl.Raster,
                        gain: float, min_info: float, n: int = 7, half_width: float = 3.0
                        ) -> MarkingMeasurement:
    """One scan's marking measurement of the pose at prior ``N(q, P)`` (see the module doc)."""
    mu, C, L, score = grid_posterior(q, P, features_vehicle_m, raster, gain, n, half_width)
    H, nu, var = equivalent_measurement(mu, C, L, min_info)
    return MarkingMeasurement(H, nu, var, score)
