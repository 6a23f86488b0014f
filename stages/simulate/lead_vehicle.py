"""Vehicles ahead of the ego car in its own lane: a lead vehicle that follows the ego's path for long
stretches, and queues at the stop-and-go stops of the trajectory (``trajectory.plan_drive``).

- **Lead stretches**: the ego's path is cut into alternating stretches with and without a lead vehicle
  (with: U(50, 200) m; without: the length that makes the lead present on ``share`` of the distance, times
  U(0.5, 1.5)), entered at a uniform phase so the expected share holds on short drives too. A lead
  keeps a bumper gap of 2.5 m + headway * ego speed (headway U(1.2, 2.2) s per stretch): about 20 m at
  10 m/s, 2.5 m when the ego stands. It drives on the ego's own path (same lane, same turns), 0.2 m lateral
  offset at most; 85 % cars, 15 % vans/trucks.
- **Queues**: at a stop-and-go stop, ``n`` vehicles stand ahead of the ego (the first as the lead) with 2.5 m
  bumper gaps and creep with it; a vehicle leaves (drives off through the crossing) once its rear moves past
  the place where the first vehicle stood at the line. Queues show from 30 m before the ego's first stop.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

EGO_FRONT_M = 1.9  # ego bumper ahead of the vehicle origin (sensor.EGO_BOXES_M)
STANDSTILL_GAP_M = 2.5
QUEUE_LOOKAHEAD_M = 30.0
QUEUE_EXIT_M = 0.5  # a queued vehicle leaves once its rear moves this far past where it stood at the line
STRETCH_M = (50.0, 200.0)


def _vehicle(rng: np.random.Generator) -> list[float]:
    """length, width, height, reflectance."""
    if rng.random() < 0.15:
        return [rng.uniform(6.0, 9.0), rng.uniform(2.3, 2.5), rng.uniform(2.6, 3.2), rng.uniform(0.2, 0.7)]
    return [rng.uniform(4.2, 5.0), rng.uniform(1.75, 1.95), rng.uniform(1.4, 1.6), rng.uniform(0.1, 0.7)]


@dataclass(frozen=True)
class LeadTraffic:
    t_s: np.ndarray  # the ego trajectory's samples (100 Hz)
    s_m: np.ndarray  # distance driven by the ego at t_s
    path_en_yaw: np.ndarray  # (N, 3) ego east, north, yaw at t_s (the path the lead follows)
    speed_mps: np.ndarray
    stretches: np.ndarray  # (L, 2) start/end distance of lead stretches
    stretch_car: np.ndarray  # (L, 6) length, width, height, reflectance, headway_s, lateral_m
    queues: list  # (s_first_stop_m, s_last_stop_m, (n, 4) length/width/height/reflectance per vehicle ahead)

    def _pose_at_s(self, s: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(s, self.s_m, self.path_en_yaw[:, k]) for k in range(3)])

    def vehicles_at(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(M, 7) boxes (east, north, yaw, length, width, z0, height) of the vehicles ahead in the ego lane,
        (M,) reflectance and (M,) bumper gap to the vehicle behind (m) at time ``t_s``."""
        s_ego = float(np.interp(t_s, self.t_s, self.s_m))
        v = float(np.interp(t_s, self.t_s, self.speed_mps))
        cars, lateral, headway, s_tail = [], 0.0, 0.0, -np.inf
        for s_first, s_last, queue in self.queues:
            if s_first - QUEUE_LOOKAHEAD_M <= s_ego <= s_last + 10.0:
                cars, s_tail = [(row, s_last + EGO_FRONT_M + STANDSTILL_GAP_M + QUEUE_EXIT_M) for row in queue], s_first
                break
        k = int(np.searchsorted(self.stretches[:, 0], s_ego, side="right")) - 1 if len(self.stretches) else -1
        if k >= 0 and s_ego < self.stretches[k, 1]:
            row = self.stretch_car[k]
            lateral, headway = float(row[5]), float(row[4])
            if cars:
                cars[0] = (row[:4], np.inf)  # the lead heads the queue's line and drives on through the crossing
            else:
                cars = [(row[:4], np.inf)]
        if not cars:
            return np.zeros((0, 7)), np.zeros(0), np.zeros(0)
        boxes, refl, gaps = [], [], []
        # each vehicle follows the one behind it (the ego first) or stands where the queue stood when the ego
        # reached its tail, whichever is further ahead
        front_follow, front_stand = s_ego + EGO_FRONT_M, s_tail + EGO_FRONT_M
        for j, (car, s_exit) in enumerate(cars):
            centre_follow = front_follow + STANDSTILL_GAP_M + (headway * v if j == 0 else 0.0) + car[0] / 2
            centre_stand = front_stand + STANDSTILL_GAP_M + car[0] / 2
            centre_s = max(centre_follow, centre_stand)
            gap = centre_s - car[0] / 2 - front_follow
            front_follow = front_stand = centre_s + car[0] / 2
            if centre_s - car[0] / 2 > s_exit or centre_s > self.s_m[-1]:
                continue
            e, n, yaw = self._pose_at_s(np.array([centre_s]))[0]
            off = lateral if j == 0 else 0.0
            boxes.append([e - np.sin(yaw) * off, n + np.cos(yaw) * off, yaw, car[0], car[1], 0.3, car[2]])
            refl.append(car[3])
            gaps.append(gap)
        return np.array(boxes, float).reshape(-1, 7), np.array(refl, float), np.array(gaps, float)


def _stretch_lengths(share: float, rng: np.random.Generator) -> tuple[float, float]:
    on = rng.uniform(STRETCH_M[0], STRETCH_M[1])
    return on, (on * (1.0 - share) / share * rng.uniform(0.5, 1.5) if share < 1 else 0.0)


def plan_lead_traffic(traj, share: float, rng: np.random.Generator) -> LeadTraffic:
    """Lead stretches over ``share`` of the drive's distance and the queues of ``traj.queue_stops``."""
    dt = np.diff(traj.t_s, prepend=traj.t_s[0])
    s = np.cumsum(traj.speed_mps * dt)
    total = float(s[-1])
    stretches, cars = [], []
    if share > 0:  # alternating renewal process entered at a uniform phase: the expected share is exact
        on, off = _stretch_lengths(share, rng)
        pos = -rng.uniform(0.0, on + off)
        while pos < total:
            if pos + on > 0:
                stretches.append([max(pos, 0.0), min(pos + on, total)])
                cars.append(_vehicle(rng) + [rng.uniform(1.2, 2.2), rng.uniform(-0.2, 0.2)])
            pos += on + off
            on, off = _stretch_lengths(share, rng)
    queues = [(float(s_first), float(s_last), np.array([_vehicle(rng) for _ in range(n)], float))
              for s_first, s_last, n in traj.queue_stops]
    return LeadTraffic(traj.t_s, s, np.column_stack([traj.east_m, traj.north_m, traj.yaw_enu_rad]),
                       traj.speed_mps, np.array(stretches, float).reshape(-1, 2), np.array(cars, float).reshape(-1, 6),
                       queues)
