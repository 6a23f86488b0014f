"""Small synthetic worlds for tests and benchmarks of the localizers (known truth, fixed seeds).

Nothing here reads files: a road-marking mask (lane lines, dashes, a crosswalk), ground rings of a
multi-layer LiDAR with uncalibrated per-ring intensity, and corner observations seen from a trajectory.
"""
from __future__ import annotations

import numpy as np

from stages.common.geometry import wrap_angle_rad


def paint_markings(width_m: float, height_m: float, cell_m: float, road_y_m: float, crosswalks_x_m=(),
                   dash_m: tuple[float, float] = (3.0, 5.0)) -> tuple[np.ndarray, tuple[float, float]]:
    """A uint8 mask (rows north, cols east) with an east-west road centred at ``road_y_m``: solid edge
    lines, a dashed centre line, solid lane lines and crosswalk stripes. Origin (0, 0) at the lower-left."""
    h, w = int(round(height_m / cell_m)), int(round(width_m / cell_m))
    e = (np.arange(w) + 0.5) * cell_m
    n = (np.arange(h) + 0.5) * cell_m
    E, N = np.meshgrid(e, n)
    dy = N - road_y_m
    line = lambda y0: np.abs(dy - y0) <= 0.075  # noqa: E731 - 15 cm paint
    dashed = line(0.0) & ((E % (dash_m[0] + dash_m[1])) < dash_m[0])
    mask = line(-7.0) | line(7.0) | line(-3.5) | line(3.5) | dashed
    for x0 in crosswalks_x_m:
        stripes = (np.abs(E - x0) <= 2.0) & (np.abs(dy) <= 6.5) & ((np.floor((dy + 6.5) / 0.5) % 2) == 0)
        mask |= stripes
    return mask.astype(np.uint8), (0.0, 0.0)


def ground_ring_scan(q_vehicle: np.ndarray, mask: np.ndarray, origin_en_m: tuple[float, float], cell_m: float,
                     rng: np.random.Generator, *, lidar_height_m: float = 1.8, n_rings: int = 16,
                     lowest_deg: float = -15.0, highest_deg: float = -3.0, azimuth_step_deg: float = 0.2,
                     max_range_m: float = 30.0, noise: float = 2.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground returns of the downward rings: (P,3) xyz in a lidar frame at ``lidar_height_m`` above the
    vehicle origin (same axes), (P,) raw intensity with a different gain and offset per ring, (P,) ring."""
    elev = np.deg2rad(np.linspace(lowest_deg, highest_deg, n_rings))
    az = np.deg2rad(np.arange(-180.0, 180.0, azimuth_step_deg))
    r_ground = lidar_height_m / np.tan(-elev)
    rr, aa = np.meshgrid(r_ground, az, indexing="ij")
    ring = np.repeat(np.arange(n_rings), len(az))
    x, y = (rr * np.cos(aa)).ravel(), (rr * np.sin(aa)).ravel()
    keep = rr.ravel() <= max_range_m
    x, y, ring = x[keep], y[keep], ring[keep]
    c, s = np.cos(q_vehicle[2]), np.sin(q_vehicle[2])
    east, north = q_vehicle[0] + c * x - s * y, q_vehicle[1] + s * x + c * y
    col = np.floor((east - origin_en_m[0]) / cell_m).astype(int)
    row = np.floor((north - origin_en_m[1]) / cell_m).astype(int)
    inside = (col >= 0) & (col < mask.shape[1]) & (row >= 0) & (row < mask.shape[0])
    paint = np.zeros(len(x))
    paint[inside] = mask[row[inside], col[inside]]
    gain = np.linspace(25.0, 60.0, n_rings)[ring]  # uncalibrated: each laser sees paint differently
    base = np.linspace(5.0, 20.0, n_rings)[ring][::-1]
    intensity = base + gain * paint + noise * rng.standard_normal(len(x))
    z = np.full(len(x), -lidar_height_m) + 0.01 * rng.standard_normal(len(x))
    return np.column_stack([x, y, z]), intensity.astype(np.float32), ring.astype(np.int16)


def observe_corners(truth: np.ndarray, corners_en_m: np.ndarray, dirs_enu_rad: np.ndarray, rng: np.random.Generator,
                    *, range_m: float = 40.0, sigma0_m: float = 0.02, sigma_per_m: float = 0.002,
                    dir_sigma_rad: float = np.deg2rad(0.5), p_detect: float = 0.8):
    """Vehicle-frame corner observations along ``truth`` (E,3): (epoch, xy, cov, dirs) flat arrays."""
    d = corners_en_m[None, :, :] - truth[:, None, :2]  # (E,K,2)
    c, s = np.cos(truth[:, 2])[:, None], np.sin(truth[:, 2])[:, None]
    vx, vy = c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]
    r = np.hypot(vx, vy)
    seen = (r <= range_m) & (rng.random(r.shape) < p_detect)
    epoch, k = np.nonzero(seen)
    sig = sigma0_m + sigma_per_m * r[epoch, k]
    xy = np.column_stack([vx[epoch, k], vy[epoch, k]]) + sig[:, None] * rng.standard_normal((len(epoch), 2))
    cov = np.eye(2)[None] * (sig**2)[:, None, None]
    dirs = wrap_angle_rad(dirs_enu_rad[k] - truth[epoch, 2:3] + dir_sigma_rad * rng.standard_normal((len(k), 2)))
    return epoch, xy, cov, dirs


def relative_increments(q: np.ndarray) -> np.ndarray:
    """(E,3) poses -> (E,3) increments from k-1 to k in the frame of k-1 (row 0 zero)."""
    inc = np.zeros_like(q)
    d = np.diff(q[:, :2], axis=0)
    c, s = np.cos(q[:-1, 2]), np.sin(q[:-1, 2])
    inc[1:, 0] = c * d[:, 0] + s * d[:, 1]
    inc[1:, 1] = -s * d[:, 0] + c * d[:, 1]
    inc[1:, 2] = wrap_angle_rad(np.diff(q[:, 2]))
    return inc


def road_trajectory(n: int, speed_mps: float = 8.0, rate_hz: float = 10.0, road_y_m: float = 20.0,
                    x0_m: float = 20.0) -> np.ndarray:
    """(n,3) truth along the synthetic east-west road, weaving gently between the two eastbound lanes."""
    s = x0_m + np.arange(n) * speed_mps / rate_hz
    y = road_y_m - 1.75 - 1.2 * np.sin(s / 60.0)
    yaw = np.arctan2(np.gradient(y), np.gradient(s))
    return np.column_stack([s, y, yaw])


def roadside_corners(length_m: float, road_y_m: float, rng: np.random.Generator, spacing_m: float = 18.0
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Building corners on both sides of the road (10-14 m off its centre) with wall directions in ENU."""
    xs = np.arange(10.0, length_m - 10.0, spacing_m)
    xs = xs + rng.uniform(-4.0, 4.0, len(xs))
    side = np.where(np.arange(len(xs)) % 2 == 0, 1.0, -1.0)
    ys = road_y_m + side * rng.uniform(10.0, 14.0, len(xs))
    away = np.where(side > 0, np.pi / 2, -np.pi / 2)  # one wall leaves the road, the other runs along it
    along = np.where(rng.random(len(xs)) < 0.5, 0.0, np.pi)
    dirs = np.column_stack([away + rng.normal(0, np.deg2rad(10), len(xs)), along])
    return np.column_stack([xs, ys]), wrap_angle_rad(dirs)


def direct_features(truth: np.ndarray, mask: np.ndarray, origin_en_m: tuple[float, float], cell_m: float,
                    rng: np.random.Generator, range_m: float = 25.0, n_max: int = 300, sigma_m: float = 0.05,
                    outlier_share: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Cheap stand-in for ring features: painted cells near each pose, in the vehicle frame, with noise and
    outliers. Returns flat (epoch, (F,2) xy)."""
    rows, cols = np.nonzero(mask)
    east = origin_en_m[0] + (cols + 0.5) * cell_m
    north = origin_en_m[1] + (rows + 0.5) * cell_m
    ep, pts = [], []
    for k, (x, y, yaw) in enumerate(truth):
        near = np.flatnonzero((np.abs(east - x) < range_m) & (np.abs(north - y) < range_m))
        pick = near[rng.choice(len(near), min(n_max, len(near)), replace=False)] if len(near) else near
        d = np.column_stack([east[pick] - x, north[pick] - y])
        c, s = np.cos(yaw), np.sin(yaw)
        v = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
        v += sigma_m * rng.standard_normal(v.shape)
        n_out = int(outlier_share * len(v))
        if n_out:
            v[:n_out] = rng.uniform(-range_m, range_m, (n_out, 2))
        ep.append(np.full(len(v), k)), pts.append(v)
    return np.concatenate(ep), np.concatenate(pts)


def synthetic_drive(n: int, rng: np.random.Generator, *, outage_s: tuple[float, float] | None = None,
                    features: str = "direct", rate_hz: float = 10.0, cell_m: float = 0.1):
    """A whole evaluation drive along the synthetic road: (DriveArrays, CornerMap, fetch, truth (n,3), stamps).

    ICP increments carry 1 % + 1 cm noise, wheel odometry 2 % and a gyro bias, GNSS/INS a 0.5 m bias plus
    noise and ``outage_s = (start, duration)`` seconds without a valid fix.
    """
    from stages.evaluate import mcl
    from stages.evaluate.localize_ekf import CornerMap, CornerObservations
    from stages.evaluate.run import DriveArrays

    truth = road_trajectory(n, rate_hz=rate_hz)
    length = float(truth[-1, 0] + 60.0)
    mask, origin = paint_markings(length, 40.0, cell_m, road_y_m=20.0,
                                  crosswalks_x_m=tuple(np.arange(150.0, length, 250.0)))
    corners, dirs = roadside_corners(length, 20.0, rng)
    stamps = 1_000_000_000_000 + np.round(np.arange(n) * 1e9 / rate_hz).astype(np.int64)
    inc = relative_increments(truth)
    dist = np.hypot(inc[:, 0], inc[:, 1])
    icp = inc + np.column_stack([(0.01 * dist + 0.01) * rng.standard_normal(n),
                                 (0.01 * dist + 0.01) * rng.standard_normal(n),
                                 np.deg2rad(0.03) * rng.standard_normal(n)])
    odo = inc * np.array([1.02, 1.0, 1.0]) + np.column_stack([0.02 * rng.standard_normal(n), np.zeros(n),
                                                              np.full(n, np.deg2rad(0.02))])
    odo[0] = 0.0
    t_s = np.arange(n) / rate_hz
    gnss_q = truth + np.array([0.5, -0.3, np.deg2rad(0.3)]) + rng.standard_normal((n, 3)) * [0.1, 0.1, 0.002]
    valid = np.ones(n, dtype=bool)
    if outage_s is not None:
        valid &= ~((t_s >= outage_s[0]) & (t_s < outage_s[0] + outage_s[1]))
    std = np.tile([0.6, 0.6, np.deg2rad(0.5)], (n, 1))
    ep, xy, cov, cdirs = observe_corners(truth, corners, dirs, rng)
    if features == "rings":
        f_ep, f_xy = [], []
        from stages.common.road_features import extract_road_features
        T = np.eye(4)
        T[2, 3] = 1.8
        for k in range(n):
            xyz, inten, ring = ground_ring_scan(truth[k], mask, origin, cell_m, rng)
            f = extract_road_features(xyz, inten, ring, T)
            f_ep.append(np.full(len(f), k)), f_xy.append(f)
        f_ep, f_xy = np.concatenate(f_ep), np.concatenate(f_xy)
    else:
        f_ep, f_xy = direct_features(truth, mask, origin, cell_m, rng)
    d = DriveArrays(stamps, icp, odo, gnss_q, std, valid, CornerObservations(ep, xy, cov, cdirs), f_ep, f_xy)
    map_noise = 0.03 * rng.standard_normal(corners.shape)
    cmap = CornerMap(corners + map_noise, np.tile(np.eye(2) * 0.03**2, (len(corners), 1, 1)), dirs)
    field = mcl.distance_likelihood_field(mask, cell_m, 0.2)

    def fetch(e0: float, n0: float, e1: float, n1: float) -> mcl.Raster:
        return mcl.Raster(field, origin, cell_m)
    return d, cmap, fetch, truth, stamps
