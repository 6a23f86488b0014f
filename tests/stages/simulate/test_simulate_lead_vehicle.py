"""Vehicles ahead in the ego lane: the lead vehicle's share of the drive, its gap and lane, stop-and-go queues,
and the scans show the lead where truth says it is."""
from __future__ import annotations

import csv

import numpy as np
import pytest

from stages.simulate.lead_vehicle import EGO_FRONT_M, STANDSTILL_GAP_M, plan_lead_traffic
from stages.simulate.trajectory import Trajectory, plan_drive


def _straight(length_m: float, speed_mps: float = 10.0) -> Trajectory:
    t = np.arange(0.0, length_m / speed_mps, 0.01)
    z = np.zeros(len(t))
    return Trajectory(t, speed_mps * t, z + 5.0, z, np.full(len(t), speed_mps), z, z, z, float(length_m))


@pytest.mark.parametrize("share", [0.0, 0.3, 0.6, 1.0])
def test_lead_vehicle_share_gap_and_lane(share):
    traj = _straight(30_000.0)
    lead = plan_lead_traffic(traj, share, np.random.default_rng(1))
    times = np.arange(0.0, traj.t_s[-1] - 5.0, 0.5)
    present = []
    for t in times:
        boxes, _, gaps = lead.vehicles_at(float(t))
        present.append(len(boxes) > 0)
        if len(boxes):
            ego_e = 10.0 * t
            assert len(boxes) == 1 and abs(boxes[0, 1] - 5.0) <= 0.2 + 1e-9  # in the ego lane
            rear = boxes[0, 0] - boxes[0, 3] / 2 - (ego_e + EGO_FRONT_M)
            assert rear == pytest.approx(gaps[0], abs=1e-6)
            assert STANDSTILL_GAP_M + 1.2 * 10.0 - 1e-6 <= gaps[0] <= STANDSTILL_GAP_M + 2.2 * 10.0 + 1e-6  # headway
    assert np.mean(present) == pytest.approx(share, abs=0.07)


def test_stop_and_go_queue_creeps_and_stands_ahead():
    side = 150.0
    poly = np.array([[0, 0], [side, 0], [side, side], [0, side], [0, 0]], float)
    turns = [side - 10.0, 2 * side - 10.0, 3 * side - 10.0, 4 * side - 10.0]
    traj = plan_drive(poly, turns, 1, 9.0, 1.0, np.random.default_rng(2), queue_share=1.0)
    assert len(traj.queue_stops) >= 3
    lead = plan_lead_traffic(traj, 0.0, np.random.default_rng(3))  # queues only, no lead stretches
    s = np.concatenate([[0.0], np.cumsum(traj.speed_mps[1:] * np.diff(traj.t_s))])
    standing = traj.speed_mps < 1e-3
    for s_first, s_last, n in traj.queue_stops:
        # the ego stops n + 1 times within the queue (tail ... stop line), creeping 6.5-8 m between stops
        in_q = (s > s_first - 0.5) & (s < s_last + 0.5) & standing
        stops = np.unique(np.round(s[in_q], 0))
        stops = stops[np.r_[True, np.diff(stops) > 1.5]]
        assert len(stops) == n + 1 and np.all((np.diff(stops) > 6.0) & (np.diff(stops) < 8.6))
        # at the first stop n vehicles stand ahead, 2.5 m bumper to bumper; at the line only the first
        t_first = traj.t_s[np.flatnonzero(in_q & (np.abs(s - stops[0]) < 0.5))[0]]
        boxes, _, gaps = lead.vehicles_at(float(t_first))
        assert len(boxes) == n and np.allclose(gaps, STANDSTILL_GAP_M, atol=0.05)
        t_last = traj.t_s[np.flatnonzero(in_q & (np.abs(s - stops[-1]) < 0.5))[-1]]
        assert len(lead.vehicles_at(float(t_last))[0]) == 1
    free = ~np.any([(s > a - 40) & (s < b + 20) for a, b, _ in traj.queue_stops], axis=0)
    assert all(len(lead.vehicles_at(float(t))[0]) == 0 for t in traj.t_s[free][::200])


def test_scans_show_the_lead_vehicle_at_its_truth_gap(tmp_path):
    from stages.simulate.core import simulate
    from stages.simulate.presets import get_preset
    from tests.stages.simulate.test_simulate_outputs import read_pcd

    p = get_preset("tiny", lead_vehicle_share=1.0, sector_dropout_scan_share=0.0)
    simulate(p, 7, tmp_path, n_drives=1, scan_limit=4)
    rows = list(csv.DictReader(open(tmp_path / "truth/drive_0_vehicles_ahead.csv")))
    assert len(rows) == 4 and all(int(r["vehicles_ahead"]) == 1 for r in rows)
    for r in rows:
        pts = read_pcd(tmp_path / f"drive_0/scans/{int(r['scan_id']):06d}.pcd")
        rear_x = EGO_FRONT_M + float(r["gap_m"])  # lidar frame x forward; the lidar is above the vehicle origin
        on_rear = (np.abs(pts["x"] - rear_x) < 0.25) & (np.abs(pts["y"]) < 0.8) & (pts["z"] > -1.5) & (pts["z"] < -0.4)
        assert on_rear.sum() > 30, (r, on_rear.sum())
