"""Monte Carlo localisation on a road-marking raster (Kim, Liu & Myung s.2.3; Thrun et al. ch. 8).

Particles are (N,3) arrays of (x_m, y_m, yaw_rad) in ENU. Prediction samples the wheel-speed + gyro motion
model; the weight of a particle is the correlation of the scan's feature points, placed by that particle,
with a smoothed marking raster (vectorised over particles x points); resampling is low-variance (systematic).
All randomness comes from a ``np.random.Generator`` passed in.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.common.geometry import wrap_angle_rad


@dataclass(frozen=True)
class Raster:
    """A marking likelihood window: ``values[row, col]``, row 0 at ``origin_en_m[1]`` (south), float32."""

    values: np.ndarray
    origin_en_m: tuple[float, float]
    cell_m: float

    def contains(self, e0: float, n0: float, e1: float, n1: float) -> bool:
        h, w = self.values.shape
        oe, on = self.origin_en_m
        return oe <= e0 and on <= n0 and e1 <= oe + w * self.cell_m and n1 <= on + h * self.cell_m


def smooth_marking_mask(mask: np.ndarray, cell_m: float, blur_m: float) -> np.ndarray:
    """0/1 marking mask -> likelihood field in [0, 1]: Gaussian blur, rescaled so a marking cell scores 1."""
    from scipy.ndimage import gaussian_filter

    field = np.asarray(mask > 0, dtype=np.float32)
    if blur_m > 0:
        field = gaussian_filter(field, sigma=blur_m / cell_m, mode="constant")
        peak = float(gaussian_filter(np.pad(np.ones((1, 1), np.float32), 8), sigma=blur_m / cell_m).max())
        field = np.minimum(field / max(peak, 1e-6), 1.0)  # an isolated marking cell scores 1 at its centre
        field = np.maximum(field, np.asarray(mask > 0, dtype=np.float32))
    return field


def init_particles(q0: np.ndarray, sigma_xy_m: float, sigma_yaw_rad: float, n: int,
                   rng: np.random.Generator) -> np.ndarray:
    noise = rng.standard_normal((n, 3)) * np.array([sigma_xy_m, sigma_xy_m, sigma_yaw_rad])
    particles = np.asarray(q0, dtype=float)[None, :] + noise
    particles[:, 2] = wrap_angle_rad(particles[:, 2])
    return particles


def predict_particles(particles: np.ndarray, increment: np.ndarray, sigma_frac: float, sigma_xy_m: float,
                      sigma_yaw_rad: float, rng: np.random.Generator) -> np.ndarray:
    """Apply an odometry increment (dx, dy, dyaw in the previous vehicle frame) with per-particle noise.

    Translation noise is ``sigma_frac * |t| + sigma_xy_m`` on each axis, heading noise ``sigma_yaw_rad``.
    """
    n = len(particles)
    dist = float(np.hypot(increment[0], increment[1]))
    eps = rng.standard_normal((n, 3))
    s_xy = sigma_frac * dist + sigma_xy_m
    dx = increment[0] + s_xy * eps[:, 0]
    dy = increment[1] + s_xy * eps[:, 1]
    c, s = np.cos(particles[:, 2]), np.sin(particles[:, 2])
    out = np.empty_like(particles)
    out[:, 0] = particles[:, 0] + c * dx - s * dy
    out[:, 1] = particles[:, 1] + s * dx + c * dy
    out[:, 2] = wrap_angle_rad(particles[:, 2] + increment[2] + sigma_yaw_rad * eps[:, 2])
    return out


def correlation_scores(particles: np.ndarray, features_vehicle_m: np.ndarray, raster: Raster) -> np.ndarray:
    """(N,) mean raster value under the feature points (F,2) placed by each particle; 0 outside the window."""
    if len(features_vehicle_m) == 0:
        return np.zeros(len(particles))
    px = features_vehicle_m[:, 0].astype(np.float32)[None, :]
    py = features_vehicle_m[:, 1].astype(np.float32)[None, :]
    c = np.cos(particles[:, 2]).astype(np.float32)[:, None]
    s = np.sin(particles[:, 2]).astype(np.float32)[:, None]
    inv = np.float32(1.0 / raster.cell_m)
    ox = ((particles[:, 0] - raster.origin_en_m[0]) * inv).astype(np.float32)[:, None]
    oy = ((particles[:, 1] - raster.origin_en_m[1]) * inv).astype(np.float32)[:, None]
    col = np.floor(ox + (c * px - s * py) * inv).astype(np.int32)
    row = np.floor(oy + (s * px + c * py) * inv).astype(np.int32)
    h, w = raster.values.shape
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    flat = np.where(inside, row * w + col, 0)
    vals = np.where(inside, raster.values.ravel()[flat], 0.0)
    return vals.mean(axis=1, dtype=np.float64)


def log_likelihood(scores: np.ndarray, n_features: int, sharpness: float, effective_points: float) -> np.ndarray:
    """Tempered log-likelihood from correlation scores: the F points count as ``min(F, effective_points)``
    independent ones (neighbouring feature points are far from independent)."""
    return sharpness * min(float(n_features), effective_points) * scores


def low_variance_resample(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Systematic resampling (Thrun et al. Table 4.4): indices of the particles to keep."""
    n = len(weights)
    positions = (rng.random() + np.arange(n)) / n
    cumulative = np.cumsum(weights)
    cumulative[-1] = 1.0
    return np.searchsorted(cumulative, positions, side="left")


def effective_sample_size(weights: np.ndarray) -> float:
    return float(1.0 / np.sum(weights**2))


def estimate(particles: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean (circular for yaw) and covariance (3x3)."""
    w = weights / weights.sum()
    yaw = float(np.arctan2(np.sum(w * np.sin(particles[:, 2])), np.sum(w * np.cos(particles[:, 2]))))
    q = np.array([np.sum(w * particles[:, 0]), np.sum(w * particles[:, 1]), yaw])
    d = particles - q
    d[:, 2] = wrap_angle_rad(d[:, 2])
    cov = (d * w[:, None]).T @ d
    return q, cov
