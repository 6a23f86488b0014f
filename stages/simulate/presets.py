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
    # issue 62: the lidar, the survey and the GNSS grade (defaults keep the presets as they were; docs/simulator.md)
    sensor: str = "hdl32e"  # lidar model: hdl32e | hdl64e
    lidar_x_m: float = 0.0  # the lidar in the vehicle frame (x forward, y left, z up; origin on the ground)
    lidar_y_m: float = 0.0
    lidar_z_m: float = 1.9
    lidar_yaw_deg: float = 0.0  # mount yaw: the lidar's x axis turned this far left of the vehicle's
    survey: bool = True  # a mobile-mapping survey cloud (LAS) that the drive files reference
    gnss_attitude: bool = True  # an INS gives roll, pitch, heading; False: heading = course over ground, no roll/pitch
    gnss_bias_tau_s: float = 90.0  # correlation time of the slowly varying bias
    gnss_multipath_m: tuple[float, float] = (1.0, 1.8)  # size of a multipath jump
    gnss_outage_s: tuple[float, float] = (1.5, 5.0)  # length of an outage
    gnss_std_share: float = 0.0  # 0: RTK/INS reported std (understated in canyons); > 0: this share of the target
    # bias std per axis (gnss_target_rms_m / sqrt 2), higher in canyons
    # issue 62: facades as real streets have them (stages/simulate/facades.py); 0 = flat walls
    window_share: float = 0.0  # share of opaque walls with rows of windows set into them
    shopfront_share: float = 0.0  # share of opaque walls whose ground floor is a shop front (glass, entrances)
    balcony_share: float = 0.0  # share of buildings with balconies on their walls with windows
    facade_vegetation_share: float = 0.0  # share of walls with a hedge in front
    parked_tall_share: float = 0.0  # share of parked vehicles that are vans or SUVs (1.8-2.6 m instead of 1.5 m)
    # issue 63: drives without GNSS, keyframe drives (defaults keep the presets as they were; docs/simulator.md)
    gnss: bool = True  # False: no GNSS/INS file; the drive file states its start pose (start:) instead
    prior: str = "none"  # a prior trajectory file (prior.txt, TUM) beside the scans: none | local | enu
    prior_std_m: float = 0.2  # the prior's horizontal error (Gauss-Markov, prior_tau_s), stated as its std
    prior_std_deg: float = 0.1  # the prior's heading error, stated as its std
    prior_tau_s: float = 30.0  # correlation time of the prior's errors (a SLAM trajectory drifts slowly)
    start_heading_std_deg: float = 0.3  # no GNSS: the start heading's error (drawn) and stated std
    start_position_std_m: float = 0.05  # no GNSS: the start position's horizontal error (drawn) and stated std
    keyframe_spacing_m: float = 0.0  # > 0: only keyframes, each 0.5-1.5 x this much travel after the previous
    # issue 63: an out-and-back street whose two passes a drifting estimate puts tens of metres apart
    route: str = "loop"  # loop: around blocks; out_and_back: along one street to its end and back (U-turns);
    # districts: drive k around its own window of 1 x 2 blocks (trajectory.district_loop; issue 59, preset growing)
    prior_heading_walk_deg: float = 0.0  # > 0: the prior's heading also random-walks, this std per sqrt(km) of
    # travel, its positions integrate it (a SLAM without loop closures drifts); the stated std adds the walk's spread
    # at the drive's end


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

# Issue 62: drives as most users bring them. A consumer GNSS receiver (no RTK, no INS): metres of bias varying over
# ten minutes, 2-5 m multipath jumps, outages of 5-20 s, the heading from the course over ground, a reported std of
# the order of the bias; no survey cloud; the lidar on a roof mount ahead of the reference point, turned a quarter
# turn like nuScenes' LIDAR_TOP; facades with windows, shop fronts, balconies and hedges.
CONSUMER = dict(survey=False, gnss_attitude=False, gnss_target_rms_m=3.0, gnss_bias_tau_s=600.0,
                gnss_multipath_m=(2.0, 5.0), multipath_per_km=1.0, outage_per_km=2.0, gnss_outage_s=(5.0, 20.0),
                gnss_std_share=0.7, lidar_x_m=0.95, lidar_y_m=-0.25, lidar_z_m=1.85, lidar_yaw_deg=-90.0,
                window_share=0.8, shopfront_share=0.5, balcony_share=0.3, facade_vegetation_share=0.2)
PRESETS["tiny_consumer"] = replace(PRESETS["tiny"], name="tiny_consumer", **CONSUMER)
PRESETS["demo_consumer"] = replace(PRESETS["demo"], name="demo_consumer", **CONSUMER)
# The held-out real drive of issue 62 as a city: a KITTI-like street (Karlsruhe: one lane each way, cars, vans and
# SUVs parked on both sides, 2.5 m sidewalks, 16 m between the facades, 4-6 storeys with shops below, street trees
# and hedges), the HDL-64E of the KITTI samples at KITTI's mount (0.81 m ahead of and 0.32 m right of the GNSS/INS
# reference, 1.73 m up), OXTS-grade GNSS/INS, no survey, 154 scans per drive (80-100 m from a standing start).
PRESETS["kitti_city"] = Preset(
    name="kitti_city", n_cols=3, n_rows=2, block_w_m=80.0, block_h_m=68.0, jitter_share=0.3, jitter_m=5.0,
    lanes_row=1, lanes_col=1, sidewalk_m=2.5, height_range_m=(12.0, 22.0), glass_building_share=0.1,
    tree_side_share=0.5, parked_side_share=0.9, traffic_per_km=6.0, congested_street_share=0.0,
    lap_length_m=0.0, map_laps=1, eval_laps=1, default_drives=2, cruise_mps=8.5, stop_share=0.0,
    gnss_target_rms_m=0.8, gnss_bias_open_m=0.3, gnss_bias_canyon_m=1.0, multipath_per_km=1.0,
    outage_per_km=0.0, max_scans_per_drive=154, origin_lat_deg=49.0111, origin_lon_deg=8.4164, origin_h_m=160.0,
    gps_week=1655, survey=False, sensor="hdl64e", lidar_x_m=0.81, lidar_y_m=-0.32, lidar_z_m=1.73,
    window_share=0.9, shopfront_share=0.8, balcony_share=0.3, facade_vegetation_share=0.4, parked_tall_share=0.25)

# Issue 59: a city that grows. A grid of 5 x 3 tiny blocks; drive k loops around its own window of one block row and
# two block columns (``route: districts``, trajectory.district_loop): the first 12 drives sweep the grid west to east,
# each sharing streets with earlier ones, later drives revisit them; the survey covers every drive's route. With
# ``--changes --changes-from-drive K`` the city changes along drive K's window (bench/bench_growing.py).
PRESETS["growing"] = replace(PRESETS["tiny"], name="growing", n_cols=5, n_rows=3, route="districts",
                             default_drives=20, max_scans_per_drive=300)

SHARES = ("lead_vehicle_share", "queue_stop_share", "rounded_corner_share", "chamfered_corner_share",
          "mixed_pixel_share", "sector_dropout_scan_share", "window_share", "shopfront_share", "balcony_share",
          "facade_vegetation_share", "parked_tall_share")
SENSOR_NAMES = ("hdl32e", "hdl64e", "os1-64")  # stages/simulate/sensor.py LIDARS
PRIOR_KINDS = ("none", "local", "enu")
ROUTES = ("loop", "out_and_back", "districts")


def get_preset(name: str, **overrides) -> Preset:
    """The preset record, with optional field overrides (tests shorten runs; ``--set`` changes a feature)."""
    if name not in PRESETS:
        raise ConfigError("simulate --preset", [f"unknown preset {name!r}; expected one of {sorted(PRESETS)}"])
    overrides = dict(overrides)
    known = {f.name for f in fields(Preset)} - {"name"}
    bad = [f"unknown preset field {k!r}; expected one of {sorted(known)}" for k in overrides if k not in known]
    bad += [f"{k} must be within 0..1; got {v}" for k, v in overrides.items() if k in SHARES and not 0 <= v <= 1]
    base = PRESETS[name]
    for k, v in overrides.items():  # integer / boolean fields given as numbers (from --set) keep their type
        current = getattr(base, k, None)
        if isinstance(current, bool):
            if v in (0, 1) and not isinstance(v, str):
                overrides[k] = bool(v)
            else:
                bad.append(f"{k} must be 0 or 1 (false or true); got {v!r}")
        elif isinstance(current, int) and isinstance(v, float):
            if v.is_integer():
                overrides[k] = int(v)
            else:
                bad.append(f"{k} must be an integer; got {v}")
        elif isinstance(current, str) and not isinstance(v, str):
            bad.append(f"{k} must be a name; got {v!r}")
        elif not isinstance(current, str) and isinstance(v, str) and k in known:
            bad.append(f"{k} must be a number; got {v!r}")
    if "sensor" in overrides and overrides["sensor"] not in SENSOR_NAMES:
        bad.append(f"sensor must be one of {list(SENSOR_NAMES)}; got {overrides['sensor']!r}")
    if "prior" in overrides and overrides["prior"] not in PRIOR_KINDS:
        bad.append(f"prior must be one of {list(PRIOR_KINDS)}; got {overrides['prior']!r}")
    if "route" in overrides and overrides["route"] not in ROUTES:
        bad.append(f"route must be one of {list(ROUTES)}; got {overrides['route']!r}")
    if bad:
        raise ConfigError(f"simulate preset {name!r} overrides", bad)
    return replace(base, **overrides) if overrides else base


def preset_overrides(p: Preset) -> dict:
    """The fields of ``p`` that differ from its named preset (written to simulation.json)."""
    base = PRESETS[p.name]
    return {f.name: getattr(p, f.name) for f in fields(Preset) if getattr(p, f.name) != getattr(base, f.name)}
