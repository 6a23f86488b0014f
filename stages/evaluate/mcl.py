"""Monte Carlo localisation on a road-marking raster (Kim, Liu & Myung s.2.3; Thrun et al. ch. 4, 6.4, 8).

Particles are (N,3) arrays of (x_m, y_m, yaw_rad) in ENU, plus an (N,2) array of odometry calibration states
per particle: the wheel-speed scale factor and the gyro bias [rad/s] (the along-track and heading errors of
wheel + gyro dead reckoning are a scale and a bias, not white noise). Prediction samples the wheel-speed + gyro
motion model through each particle's calibration; the weight of a particle is the correlation of the scan's
feature points, placed by that particle, with a marking likelihood field (vectorised over particles x points);
resampling is low-variance (systematic), followed by a small roughening. All randomness comes from a
``np.random.Generator`` passed in.
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
    observed: np.ndarray | None = None  # bool, same lattice: where the map saw the ground (None: everywhere)

    def contains(self, e0: float, n0: float, e1: float, n1: float) -> bool:
        h, w = self.values.shape
        oe, on = self.origin_en_m
        return oe <= e0 and on <= n0 and e1 <= oe + w * self.cell_m and n1 <= on + h * self.cell_m


def observed_features(features_vehicle_m: np.ndarray, q: np.ndarray, raster: Raster) -> np.ndarray:
    """Boolean mask of the features that, placed by the pose ``q`` (x, y, yaw), fall where the map saw the ground
    (``raster.observed``; all of them when the raster carries no coverage). Beyond the surveyed area the raster's 0
    means "not known", not "no paint": a feature there would pull every pose towards the mapped half of a crosswalk
    the survey cut. One pose decides for every particle, so their scores stay comparable."""
    f = np.asarray(features_vehicle_m, dtype=np.float64).reshape(-1, 2)
    if raster.observed is None or len(f) == 0:
        return np.ones(len(f), dtype=bool)
    c, s = np.cos(q[2]), np.sin(q[2])
    col = np.floor((q[0] + c * f[:, 0] - s * f[:, 1] - raster.origin_en_m[0]) / raster.cell_m).astype(np.int64)
    row = np.floor((q[1] + s * f[:, 0] + c * f[:, 1] - raster.origin_en_m[1]) / raster.cell_m).astype(np.int64)
    h, w = raster.observed.shape
    inside = (row >= 0) & (row < h) & (col >= 0) & (col < w)
    out = np.zeros(len(f), dtype=bool)
    out[inside] = raster.observed[row[inside], col[inside]]
    return out


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


def distance_likelihood_field(mask: np.ndarray, cell_m: float, sigma_m: float) -> np.ndarray:
    """0/1 marking mask -> likelihood field ``exp(-d^2 / (2 sigma^2))`` in [0, 1] with d the Euclidean distance
    from the cell centre to the nearest marking cell (Thrun et al. s.6.4). Unlike a blurred mask, a point next to
    a thin line scores as high as one next to a wide crosswalk stripe, and the score keeps falling with distance
    (a blur of a 15 cm line is already flat at 0.3 m)."""
    import cv2

    paint = np.asarray(mask) > 0
    if not paint.any():
        return np.zeros(paint.shape, np.float32)
    d = cv2.distanceTransform((~paint).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)  # exact, in cells
    d *= np.float32(cell_m / sigma_m)
    np.square(d, out=d)
    d *= np.float32(-0.5)
    return np.exp(d, out=d)


def init_particles(q0: np.ndarray, sigma_xy_m: float, sigma_yaw_rad: float, n: int,
                   rng: np.random.Generator) -> np.ndarray:
    noise = rng.standard_normal((n, 3)) * np.array([sigma_xy_m, sigma_xy_m, sigma_yaw_rad])
    particles = np.asarray(q0, dtype=float)[None, :] + noise
    particles[:, 2] = wrap_angle_rad(particles[:, 2])
    return particles


def init_calibration(n: int, sigma_scale: float, sigma_gyro_bias_radps: float, rng: np.random.Generator,
                     sigma_gyro_gain: float = 0.0) -> np.ndarray:
    """(N,2) per-particle odometry calibration: wheel-speed scale factor about 1, gyro bias [rad/s] about 0; with
    ``sigma_gyro_gain`` > 0 a third column, the gyro's gain about 1 (true turn = gain * (gyro turn - bias dt): a
    gyro's scale error is one number for a drive, so a turn's heading error is systematic, not white)."""
    cols = [1.0 + sigma_scale * rng.standard_normal(n), sigma_gyro_bias_radps * rng.standard_normal(n)]
    if sigma_gyro_gain > 0:
        cols.append(1.0 + sigma_gyro_gain * rng.standard_normal(n))
    return np.column_stack(cols)


def predict_particles(particles: np.ndarray, increment: np.ndarray, sigma_frac: float, sigma_xy_m: float,
                      sigma_yaw_rad: float, rng: np.random.Generator, calibration: np.ndarray | None = None,
                      dt_s: float = 0.1, sigma_lateral_frac: float | None = None,
                      sigma_yaw_frac: float = 0.0) -> np.ndarray:
    """Apply an odometry increment (dx, dy, dyaw in the previous vehicle frame) with per-particle noise.

    With ``calibration`` (N,2) each particle scales the translation by its wheel scale and removes its gyro bias
    times ``dt_s`` from the heading change; a third column, when present, multiplies that heading change (the
    gyro's gain). Noise: along track ``sigma_frac * |t| + sigma_xy_m``, across track
    ``sigma_lateral_frac * |t| + sigma_xy_m`` (default: as along track), heading
    ``sigma_yaw_rad + sigma_yaw_frac * |dyaw|``.
    """
    n = len(particles)
    dist = float(np.hypot(increment[0], increment[1]))
    eps = rng.standard_normal((n, 3))
    lat_frac = sigma_frac if sigma_lateral_frac is None else sigma_lateral_frac
    scale = 1.0 if calibration is None else calibration[:, 0]
    bias = 0.0 if calibration is None else calibration[:, 1] * dt_s
    gain = 1.0 if calibration is None or calibration.shape[1] < 3 else calibration[:, 2]
    ux, uy = (increment[0] / dist, increment[1] / dist) if dist > 0 else (1.0, 0.0)
    along = dist * scale + (sigma_frac * dist + sigma_xy_m) * eps[:, 0]
    across = (lat_frac * dist + sigma_xy_m) * eps[:, 1]
    dx, dy = ux * along - uy * across, uy * along + ux * across
    c, s = np.cos(particles[:, 2]), np.sin(particles[:, 2])
    out = np.empty_like(particles)
    out[:, 0] = particles[:, 0] + c * dx - s * dy
    out[:, 1] = particles[:, 1] + s * dx + c * dy
    dyaw = gain * (increment[2] - bias) + (sigma_yaw_rad + sigma_yaw_frac * abs(increment[2])) * eps[:, 2]
    out[:, 2] = wrap_angle_rad(particles[:, 2] + dyaw)
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


def roughen(particles: np.ndarray, sigma_xy_m: float, sigma_yaw_rad: float, rng: np.random.Generator) -> np.ndarray:
    """Roughening after resampling (Gordon et al. 1993): a small fixed jitter so duplicated particles spread
    again (``regularize`` with no spread-scaled part)."""
    return regularize(particles, rng, bandwidth=0.0, floor=(sigma_xy_m, sigma_xy_m, sigma_yaw_rad))


def effective_sample_size(weights: np.ndarray) -> float:
    return float(1.0 / np.sum(weights**2))


def normalized_weights(log_weights: np.ndarray) -> np.ndarray:
    w = np.exp(log_weights - log_weights.max())
    return w / w.sum()


def tempering_step(log_weights: np.ndarray, loglik: np.ndarray, remaining: float, min_ess: float,
                   iterations: int = 12) -> float:
    """Largest fraction ``beta <= remaining`` of ``loglik`` whose update keeps the effective sample size at or
    above ``min_ess`` (bisection; the ESS falls monotonically with beta). A step of progressive correction
    (Oudjane & Musso 2000): a likelihood far narrower than the particle cloud is applied in pieces, with a
    resample-and-move in between, instead of collapsing the cloud onto its luckiest particle."""
    if effective_sample_size(normalized_weights(log_weights + remaining * loglik)) >= min_ess:
        return remaining
    lo, hi = 0.0, remaining
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        if effective_sample_size(normalized_weights(log_weights + mid * loglik)) >= min_ess:
            lo = mid
        else:
            hi = mid
    return max(lo, 1e-3 * remaining)


def regularize(particles: np.ndarray, rng: np.random.Generator, bandwidth: float | None = None,
               floor: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Move equally weighted particles by a Gaussian kernel scaled to the cloud's own spread, per axis and never
    below ``floor`` (regularised particle filter, Musso et al. 2001). The default bandwidth is the optimal one for
    a Gaussian density in d = 3 dimensions: (4 / (N (d + 2)))^(1 / (d + 4)), 0.36 at N = 1000."""
    n = len(particles)
    h = (4.0 / (n * 5.0)) ** (1.0 / 7.0) if bandwidth is None else bandwidth
    d = particles - particles.mean(axis=0)
    mean_yaw = np.arctan2(np.sin(particles[:, 2]).mean(), np.cos(particles[:, 2]).mean())
    d[:, 2] = wrap_angle_rad(particles[:, 2] - mean_yaw)
    sigma = np.maximum(h * d.std(axis=0), np.asarray(floor))
    out = particles + rng.standard_normal(particles.shape) * sigma
    out[:, 2] = wrap_angle_rad(out[:, 2])
    return out


def estimate(particles: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean (circular for yaw) and covariance (3x3)."""
    w = weights / weights.sum()
    yaw = float(np.arctan2(np.sum(w * np.sin(particles[:, 2])), np.sum(w * np.cos(particles[:, 2]))))
    q = np.array([np.sum(w * particles[:, 0]), np.sum(w * particles[:, 1]), yaw])
    d = particles - q
    d[:, 2] = wrap_angle_rad(d[:, 2])
    cov = (d * w[:, None]).T @ d
    return q, cov
