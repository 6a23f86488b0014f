"""Moving vehicles: boxes following lanes along street segments (right-hand traffic), with queues on
congested streets. Each drive has its own traffic; the lanes the ego vehicle uses are kept free.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.simulate.city import LANE_W_M, City, street_edges


@dataclass(frozen=True)
class Traffic:
    start_en: np.ndarray  # (K, 2) lane start point
    dir_en: np.ndarray  # (K, 2) unit direction of travel
    span_m: np.ndarray  # (K,) usable lane length (intersections excluded)
    s0_m: np.ndarray  # (K,) position along the lane at t = 0
    speed_mps: np.ndarray  # (K,)
    size_m: np.ndarray  # (K, 3) length, width, height
    refl: np.ndarray  # (K,) paint reflectance

    def boxes_at(self, t_s: float, near_en: np.ndarray, radius_m: float = 110.0) -> tuple[np.ndarray, np.ndarray]:
        """(M, 7) boxes (east, north, yaw, length, width, z0, height) within ``radius_m`` of ``near_en``,
        and their (M,) reflectance."""
        s = np.mod(self.s0_m + self.speed_mps * t_s, self.span_m)
        pos = self.start_en + self.dir_en * s[:, None]
        ok = np.linalg.norm(pos - near_en, axis=1) < radius_m
        yaw = np.arctan2(self.dir_en[:, 1], self.dir_en[:, 0])
        return np.column_stack([pos[ok], yaw[ok], self.size_m[ok, :2], np.full(ok.sum(), 0.3),
                                self.size_m[ok, 2]]), self.refl[ok]


def ego_lanes(city: City, loop: list[tuple[int, int]], lane: int) -> set[tuple]:
    """(node_a, node_b, travel_sign, lane) keys of the lanes an ego loop drives (a < b as in street_edges)."""
    keys = set()
    for k in range(len(loop)):
        a, b = loop[k], loop[(k + 1) % len(loop)]
        lanes = city.lanes_row if a[0] == b[0] else city.lanes_col
        keys.add((min(a, b), max(a, b), 1 if a < b else -1, min(lane, lanes - 1)))
    return keys


def generate_traffic(city: City, per_km: float, avoid: set[tuple], rng: np.random.Generator) -> Traffic:
    rows: list[list[float]] = []
    for a, b, hw, lanes in street_edges(city):
        pa, pb = city.nodes_en[a], city.nodes_en[b]
        length = float(np.linalg.norm(pb - pa))
        t = (pb - pa) / length
        left = np.array([-t[1], t[0]])
        clear = 1.25 * (city.hw_col_m if a[0] == b[0] else city.hw_row_m) + 6.0
        span = length - 2 * clear
        if span < 10:
            continue
        congested = (a, b) in city.congested
        for sign in (1, -1):
            jam = congested and sign == 1
            for lane in range(lanes):
                if (a, b, sign, lane) in avoid:
                    continue
                d = (lane + 0.5) * LANE_W_M
                start = (pa + t * clear if sign == 1 else pb - t * clear) - sign * left * d
                if jam:
                    s0 = np.arange(rng.uniform(0, 4), span, rng.uniform(7.5, 9.0))
                    speed = np.full(len(s0), rng.uniform(0.3, 1.5))
                else:
                    n = rng.poisson(per_km * span / 1000.0)
                    s0 = np.sort(rng.uniform(0, span, n))
                    speed = rng.uniform(5.0, 11.0, n)
                for s_i, v_i in zip(s0, speed):
                    truck = rng.random() < 0.1
                    size = [rng.uniform(7.0, 10.0), 2.5, rng.uniform(2.8, 3.4)] if truck else \
                        [rng.uniform(4.2, 5.0), rng.uniform(1.75, 1.95), rng.uniform(1.2, 1.6)]
                    rows.append([*start, *(sign * t), span, s_i, v_i, *size, rng.uniform(0.1, 0.7)])
    arr = np.array(rows, float).reshape(-1, 11)
    return Traffic(arr[:, 0:2], arr[:, 2:4], arr[:, 4], arr[:, 5], arr[:, 6], arr[:, 7:10], arr[:, 10])
