"""Simulation presets: one frozen record per preset (city size, traffic, route, GNSS error level).

``tiny`` is a single block loop for tests, ``demo`` about 1 km per drive for the README job, ``gangnam`` the
experiment of Im et al. (2016, sec. 5): a dense urban grid, 4.5 km in two laps, about 8000 scans, RTK/INS with
0.6-1.0 m horizontal RMS and 1.2-2.5 m maximum error.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

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


def get_preset(name: str, **overrides) -> Preset:
    """The preset record, with optional field overrides (used by tests to shorten runs)."""
    if name not in PRESETS:
        raise ConfigError("simulate --preset", [f"unknown preset {name!r}; expected one of {sorted(PRESETS)}"])
    return replace(PRESETS[name], **overrides) if overrides else PRESETS[name]
