"""RTK/INS error model: the gangnam-like statistics of Im et al. and canyon behaviour."""
from __future__ import annotations

import numpy as np
import pytest

from stages.simulate.gnss import simulate_gnss_errors


def test_gangnam_drive0_gnss_error_within_reported_band():
    from stages.simulate.city import generate_city
    from stages.simulate.core import component_rng
    from stages.simulate.drive import DriveSpec, gnss_errors_for
    from stages.simulate.mesh import Scene, build_building_soup
    from stages.simulate.presets import get_preset
    from stages.simulate.trajectory import choose_loop_cells, lane_polyline, loop_nodes, plan_drive

    p = get_preset("gangnam", map_laps=1)  # one lap instead of two: same streets, half the time
    seed = 0
    city = generate_city(p, component_rng(seed, "city"))
    loop = loop_nodes(choose_loop_cells(p.n_rows, p.n_cols, city.nodes_en, p.lap_length_m,
                                        component_rng(seed, "route")))
    spec = DriveSpec.for_index(0, loop, p, city, seed)
    r_route, _, _, r_gnss, _ = component_rng(seed, "drive0").spawn(5)
    traj = plan_drive(*lane_polyline(city, spec.loop, spec.lane), spec.laps, p.cruise_mps, p.stop_share, r_route)
    t, _, canyon, err = gnss_errors_for(traj, Scene(build_building_soup(city)), p, r_gnss)
    h = np.linalg.norm(err.err_enu_m[err.valid, :2], axis=1)
    assert 0.6 <= np.sqrt(np.mean(h ** 2)) <= 1.0
    assert 1.2 <= h.max() <= 2.5
    assert 0.3 < canyon.mean() < 0.8  # a dense grid of 15-60 m buildings
    assert 0.1 < np.degrees(np.sqrt(np.mean(err.err_yaw_rad ** 2))) < 0.6
    # reported std understates the true error where the sky is blocked
    deep = canyon > np.quantile(canyon, 0.75)
    assert np.mean(np.hypot(*err.std_enu_m[deep, :2].T)) < 0.5 * np.sqrt(np.mean(h[deep[err.valid]] ** 2))


def test_error_grows_with_canyon_and_outages_drop_rows():
    n = 20 * 3600
    t = np.arange(n) / 20.0
    canyon = np.where(t < 1800, 0.05, 0.8)
    err = simulate_gnss_errors(t, canyon, t * 8.0, 0.8, 0.25, 1.0, 1.0, 2.0, np.random.default_rng(3))
    h = np.linalg.norm(err.err_enu_m[:, :2], axis=1)
    open_rms = np.sqrt(np.mean(h[t < 1700] ** 2))
    canyon_rms = np.sqrt(np.mean(h[t > 1900] ** 2))
    assert canyon_rms > 2.0 * open_rms
    assert 0 < (~err.valid).sum() < 0.06 * n  # about 2 outages/km of 1.5-5 s at 8 m/s
    assert (~err.valid[t < 1800]).sum() < (~err.valid[t >= 1800]).sum()


@pytest.mark.slow
def test_full_gangnam_drive0_stats(tmp_path):
    from stages.simulate.core import simulate

    s = simulate("gangnam", 0, tmp_path, n_drives=1)
    st = s.gnss_stats["drive_0"]
    assert 0.6 <= st["rms_m"] <= 1.0 and 1.2 <= st["max_m"] <= 2.5
    assert 7000 <= s.n_scans["drive_0"] <= 10000
