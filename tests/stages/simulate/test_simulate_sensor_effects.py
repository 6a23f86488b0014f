"""Sensor effects against their analytic models: angular jitter and beam divergence spread the range on an
oblique wall as predicted, mixed pixels float between a foreground edge and the background, sector dropouts
remove exactly one azimuth sector."""
from __future__ import annotations

import numpy as np
import pytest

from stages.simulate.markings import Raster
from stages.simulate.mesh import WALL, Scene, TriangleSoup, vertical_quads
from stages.simulate.sensor import N_AZIMUTH, RANGE_SIGMA_M, LaserCalibration, build_beam_table, simulate_scan
from stages.simulate.sensor_effects import SensorEffects, dropped_columns, mix_edge_ranges

BEAMS = build_beam_table()


def _walls(p0, p1, height=30.0):
    tris = vertical_quads(np.asarray(p0, float), np.asarray(p1, float), -5.0, height)
    return TriangleSoup(
        tris.astype(np.float32), np.full(len(tris), WALL, np.uint8), np.full(len(tris), 0.5, np.float32)
    )


def _scan(soup: TriangleSoup, effects: SensorEffects | None, seed: int = 0):
    empty = Raster(np.zeros((1, 1), np.uint8), 0.0, 0.0, 1.0)
    albedo = Raster(np.full((1, 1), 0.1, np.float32), -1e4, 1e4, 2e4)
    dynamic = Scene(TriangleSoup(np.zeros((0, 3, 3), np.float32), np.zeros(0, np.uint8), np.zeros(0, np.float32)))
    return simulate_scan(BEAMS, np.zeros((N_AZIMUTH, 5)), Scene(soup), dynamic, empty, albedo,
                         LaserCalibration(np.ones(32), np.zeros(32)), np.random.default_rng(seed), effects,
                         np.random.default_rng(seed + 1000))


def _wall_residuals(pts, wall_x_m: float = 10.0):
    """Range residual along each reported ray to the plane x = wall_x_m, and the azimuth (deg) of the ray."""
    xyz = np.column_stack([pts["x"], pts["y"], pts["z"]]).astype(float)
    r = np.linalg.norm(xyz, axis=1)
    d = xyz / r[:, None]
    return r - wall_x_m / d[:, 0], np.degrees(np.arctan2(d[:, 1], d[:, 0])), r


@pytest.mark.parametrize("what", ["jitter", "divergence"])
def test_oblique_wall_range_spread_follows_the_model(what):
    wall = _walls([[10.0, -60.0]], [[10.0, 60.0]])
    sigma_deg, div_mrad = 0.25, 30.0  # exaggerated so the effect dominates the 2 cm range noise
    fx = SensorEffects(angular_jitter_deg=sigma_deg) if what == "jitter" else SensorEffects(divergence_mrad=div_mrad)
    res, az, r = [], [], []
    for seed in range(3):
        pts = _scan(wall, fx, seed)
        on = (pts["x"] > 5) & (pts["ring"] == 23)  # the horizontal ring: incidence = azimuth on the wall
        a, b, c = _wall_residuals({k: v[on] for k, v in pts.items()})
        res.append(a), az.append(b), r.append(c)
    res, az, r = np.concatenate(res), np.concatenate(az), np.concatenate(r)
    for lo, hi in ((0.0, 10.0), (40.0, 50.0), (55.0, 65.0)):
        band = (np.abs(az) >= lo) & (np.abs(az) < hi)
        tan_i, rr = np.tan(np.radians(np.abs(az[band]))), r[band]
        if what == "jitter":  # d r / d azimuth = r tan(incidence) on a plane; elevation jitter adds ~nothing at el 0
            model = np.sqrt(RANGE_SIGMA_M ** 2 + np.mean((rr * tan_i * np.radians(sigma_deg)) ** 2))
        else:
            model = np.sqrt(RANGE_SIGMA_M ** 2 + np.mean((0.5 * rr * div_mrad * 1e-3 / 2 * tan_i) ** 2))
        assert band.sum() > 100
        assert np.std(res[band]) == pytest.approx(model, rel=0.15), (lo, hi)
    plain = _scan(wall, None)
    on = (plain["x"] > 5) & (plain["ring"] == 23)
    res0, az0, _ = _wall_residuals({k: v[on] for k, v in plain.items()})
    assert np.std(res0[np.abs(az0) > 40]) == pytest.approx(RANGE_SIGMA_M, rel=0.2)  # without effects: 2 cm only


def test_mixed_pixels_float_between_an_edge_and_the_background():
    # a foreground wall at x = 10 m covering y > 0 (its edge at azimuth 0), a background wall at x = 20 m
    soup = TriangleSoup.concat([_walls([[10.0, 0.0]], [[10.0, 30.0]]), _walls([[20.0, -60.0]], [[20.0, 60.0]])])

    def floating(fx, seeds):
        out = []
        for seed in seeds:
            pts = _scan(soup, fx, seed)
            res = (pts["x"] > 10.5) & (pts["x"] < 19.5)
            out.append((res.sum(), np.degrees(np.arctan2(pts["y"][res], pts["x"][res])),
                        len(np.unique(pts["ring"][(pts["x"] > 9.5) & (pts["x"] < 10.5) & (pts["y"] > 0)]))))
        return out

    assert all(n == 0 for n, _, _ in floating(None, range(3)))
    full = floating(SensorEffects(mixed_pixel_share=1.0), range(4))
    for n, az, rings_on_edge in full:
        # one blended return per ring that sees both walls, w ~ U(0, 1): 90 % of them off both walls by > 0.5 m
        assert 0.6 * rings_on_edge <= n <= rings_on_edge
        assert np.all(np.abs(az) < 0.2)  # at the edge (0.16 deg azimuth steps)
    half = sum(n for n, _, _ in floating(SensorEffects(mixed_pixel_share=0.5), range(4)))
    assert 0.3 < half / sum(n for n, _, _ in full) < 0.7


def test_mix_edge_ranges_blends_only_across_jumps():
    grid = np.full((10, 2), 20.0)
    grid[3:6, 0] = 10.0  # an object in ring 0; ring 1 sees only the background
    grid[8, 1] = np.inf  # no return: never blended
    out, mixed = mix_edge_ranges(grid, 1.0, 0.3, np.random.default_rng(0))
    assert mixed[:, 1].sum() == 0 and mixed[:, 0].sum() == 2  # two edges in ring 0, one blended firing each
    assert np.all((out[mixed] >= 10.0) & (out[mixed] <= 20.0))
    assert np.array_equal(out[~mixed], grid[~mixed])


def test_sector_dropout_removes_one_sector():
    box = _walls([[15.0, -15.0], [15.0, 15.0], [-15.0, 15.0], [-15.0, -15.0]],
                 [[15.0, 15.0], [-15.0, 15.0], [-15.0, -15.0], [15.0, -15.0]])
    fx = SensorEffects(sector_dropout_scan_share=1.0, sector_dropout_deg=(20.0, 20.0))
    for seed in range(3):
        pts = _scan(box, fx, seed)
        column = np.floor(pts["time"].astype(float) / (0.1 / N_AZIMUTH) + 1e-3).astype(int)  # firing time -> column
        occupied = np.zeros(N_AZIMUTH, bool)
        occupied[column] = True
        gap_cols = (~occupied).sum()
        assert gap_cols == pytest.approx(20.0 / 360.0 * N_AZIMUTH, abs=2)
        # contiguous: exactly one run of empty columns around the circle
        assert np.sum(np.diff(np.r_[occupied, occupied[0]].astype(int)) == 1) == 1
    rng = np.random.default_rng(5)
    hit = np.mean([dropped_columns(N_AZIMUTH, 0.1, (5.0, 30.0), rng).any() for _ in range(3000)])
    assert hit == pytest.approx(0.1, abs=3 * np.sqrt(0.1 * 0.9 / 3000))
