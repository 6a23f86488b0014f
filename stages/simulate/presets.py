"""Simulation presets: one frozen record per preset (city size, traffic, route, GNSS error level).

``tiny`` is a single block loop for tests, ``demo`` about 1 km per drive for the README job, ``gangnam`` the
experiment of Im et al. (2016, sec. 5): a dense urban grid, 4.5 km in two laps, about 8000 scans, RTK/INS with
0.6-1.0 m horizontal RMS and 1.2-2.5 m maximum error.
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace

from pipeline.errors import ConfigError


@dataclass(frozen=True)
class Preset:
    name: str
    # city grid
    n_cols: int  # number of blocks east-west
    n_rows: int  # number of blocks north-south
    block_w_m: float
    block_h_m: float
    jitter_share: float  # share of streets whose nodes are shifted (non-orthogonal streets)
    jitter_m: float  # max node shift
    lanes_row: int  # lanes per direction on east-west streets
    lanes_col: int  # lanes per direction on north-south streets
    sidewalk_m: float
    height_range_m: tuple[float, float]
    glass_building_share: float  # share of buildings with glass facades
    tree_side_share: float  # share of street sides lined with trees
    parked_side_share: float
    traffic_per_km: float  # moving vehicles per km of lane
    congested_street_share: float
    # route
    lap_length_m: float  # the driven loop encloses blocks until its perimeter reaches this length
    map_laps: int
    eval_laps: int
    default_drives: int
    cruise_mps: float
    stop_share: float  # share of crossings where the vehicle stops
    # GNSS/INS error level
    gnss_target_rms_m: float  # RMS of the slowly varying bias over a drive (calibrated, see gnss.py)
    gnss_bias_open_m: float  # bias std under open sky (relative weight)
    gnss_bias_canyon_m: float  # additional bias std at full canyon (relative weight)
    multipath_per_km: float
    outage_per_km: float
    max_scans_per_drive: int | None = None  # tiny keeps its promise of at most 500 scans in all
    origin_lat_deg: float = 37.4979  # Gangnam station, Seoul
    origin_lon_deg: float = 127.0276
    origin_h_m: float = 57.0  # WGS84 ellipsoidal (about 30 m orthometric + 27 m geoid)
    gps_week: int = 1890  # March 2016
    # issue 25: what real streets showed (defaults apply to every preset; docs/simulator.md)
    lead_vehicle_share: float = 0.3  # share of the drive's distance with a vehicle ahead in the ego lane
    queue_stop_share: float = 0.5  # share of the stops that are stop-and-go queues (1-3 vehicles ahead)
    rounded_corner_share: float = 0.15  # share of convex building corners rounded (radius corner_radius_m)
    chamfered_corner_share: float = 0.10  # share of convex building corners cut (chamfer_m along each wall)
    corner_radius_m: tuple[float, float] = (1.0, 5.0)
    chamfer_m: tuple[float, float] = (1.0, 3.0)
    furniture_per_km: float = 10.0  # bus shelters, kiosks, L-fences per km of kerb
    angular_jitter_deg: float = 0.03  # std of each firing's azimuth and elevation
    beam_divergence_mrad: float = 3.0  # full angle; range spread over the footprint on oblique surfaces
    mixed_pixel_share: float = 0.5  # share of depth discontinuities (> 0.3 m) giving a mixed return
    sector_dropout_scan_share: float = 0.02  # share of scans losing one azimuth sector
    sector_dropout_deg: tuple[float, float] = (5.0, 30.0)


PRESETS: dict[str, Preset] = {
    "tiny": Preset(
        name="tiny", n_cols=2, n_rows=2, block_w_m=40.0, block_h_m=33.0, jitter_share=0.5, jitter_m=7.0,
        lanes_row=1, lanes_col=1, sidewalk_m=3.0, height_range_m=(10.0, 35.0), glass_building_share=0.3,
        tree_side_share=0.7, parked_side_share=0.4, traffic_per_km=6.0, congested_street_share=0.0,
        lap_length_m=0.0, map_laps=1, eval_laps=1, default_drives=2, cruise_mps=10.0, stop_share=0.0,
        gnss_target_rms_m=0.5, gnss_bias_open_m=0.3, gnss_bias_canyon_m=1.0, multipath_per_km=2.0,
        outage_per_km=0.0, max_scans_per_drive=250),
    "demo": Preset(
        name="demo", n_cols=4, n_rows=3, block_w_m=110.0, block_h_m=85.0, jitter_share=0.4, jitter_m=14.0,
        lanes_row=2, lanes_col=2, sidewalk_m=4.0, height_range_m=(10.0, 45.0), glass_building_share=0.3,
        tree_side_share=0.7, parked_side_share=0.4, traffic_per_km=10.0, congested_street_share=0.0,
        lap_length_m=950.0, map_laps=1, eval_laps=1, default_drives=2, cruise_mps=9.5, stop_share=0.3,
        gnss_target_rms_m=0.7, gnss_bias_open_m=0.3, gnss_bias_canyon_m=1.0, multipath_per_km=2.0,
        outage_per_km=1.0),
    "gangnam": Preset(
        name="gangnam", n_cols=7, n_rows=6, block_w_m=115.0, block_h_m=88.0, jitter_share=0.35, jitter_m=16.0,
        lanes_row=3, lanes_col=2, sidewalk_m=5.0, height_range_m=(15.0, 60.0), glass_building_share=0.35,
        tree_side_share=0.8, parked_side_share=0.3, traffic_per_km=18.0, congested_street_share=0.3,
        lap_length_m=2250.0, map_laps=2, eval_laps=1, default_drives=2, cruise_mps=9.5, stop_share=0.3,
        gnss_target_rms_m=0.72, gnss_bias_open_m=0.25, gnss_bias_canyon_m=1.0, multipath_per_km=0.6,
        outage_per_km=1.0),
}


SHARES = ("lead_vehicle_share", "queue_stop_share", "rounded_corner_share", "chamfered_corner_share",
          "mixed_pixel_share", "sector_dropout_scan_share")


def get_preset(name: str, **overrides) -> Preset:
    """The preset record, with optional field overrides (tests shorten runs; ``--set`` changes a feature)."""
    if name not in PRESETS:
        raise ConfigError("simulate --preset", [f"unknown preset {name!r}; expected one of {sorted(PRESETS)}"])
    overrides = dict(overrides)
    known = {f.name for f in fields(Preset)} - {"name"}
    bad = [f"unknown preset field {k!r}; expected one of {sorted(known)}" for k in overrides if k not in known]
    bad += [f"{k} must be within 0..1; got {v}" for k, v in overrides.items() if k in SHARES and not 0 <= v <= 1]
    base = PRESETS[name]
    for k, v in overrides.items():  # integer fields given as integral floats (from --set) stay integers
        if isinstance(getattr(base, k, None), int) and isinstance(v, float):
            if v.is_integer():
                overrides[k] = int(v)
            else:
                bad.append(f"{k} must be an integer; got {v}")
    if bad:
        raise ConfigError(f"simulate preset {name!r} overrides", bad)
    return replace(base, **overrides) if overrides else base


def preset_overrides(p: Preset) -> dict:
    """The fields of ``p`` that differ from its named preset (written to simulation.json)."""
    base = PRESETS[p.name]
    return {f.name: getattr(p, f.name) for f in fields(Preset) if getattr(p, f.name) != getattr(base, f.name)}
