"""``simulate``: city -> drives -> files. Deterministic from (preset, seed): every random component draws
from its own generator derived from the seed and the component's name.

Layout of ``out_dir``: ``drive_K/`` (drive.yaml, scans/NNNNNN.pcd, scans/stamps.csv, gnss_inspva.csv,
wheel_gyro.csv), ``survey/survey.las``, ``truth/`` (drive_K_poses_tum.txt, drive_K_gnss_stats.json,
corners.csv, markings.png/json, city.json) and ``simulation.json``.
"""
from __future__ import annotations

import logging
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from pipeline.errors import ConfigError
from stages.simulate import changes as dated
from stages.simulate import writers
from stages.simulate.city import City, generate_city
from stages.simulate.corner_shapes import SHAPE_NAMES, shape_corners
from stages.simulate.drive import DriveSpec, simulate_drive
from stages.simulate.facades import facade_corner_rows, generate_facades
from stages.simulate.furniture import furniture_corners, generate_furniture
from stages.simulate.markings import asphalt_albedo, generate_markings, rasterize_markings
from stages.simulate.mesh import Scene, build_building_soup, build_static_soup
from stages.simulate.presets import Preset, get_preset, preset_overrides
from stages.simulate.sensor import LIDARS, LaserCalibration, build_beam_table, mount_matrix
from stages.simulate.survey import generate_survey
from stages.simulate.trajectory import choose_loop_cells, district_loop, loop_nodes, out_and_back_nodes
from stages.simulate.truth import building_corners, city_description, count_visible_scans

log = logging.getLogger(__name__)
CODE_VERSION = "2"
FURNITURE_COLUMNS = ["id", "kind", "east_m", "north_m", "theta1_deg", "theta2_deg", "interior_angle_deg", "height_m"]


@dataclass(frozen=True)
class SimulationSummary:
    preset: str
    seed: int
    out_dir: Path
    drives: list[str]
    n_scans: dict[str, int]
    enu_origin: dict
    utm_epsg: int
    gnss_stats: dict[str, dict] = field(default_factory=dict)


def component_rng(seed: int, name: str) -> np.random.Generator:
    """An independent generator per (seed, component name); stable across runs and platforms."""
    return np.random.default_rng(np.random.SeedSequence(entropy=seed, spawn_key=(zlib.crc32(name.encode()),)))


VEHICLE_FRAME = ("x forward, y left, z up; origin on the ground at the vehicle's reference point, which the "
                 "trajectory, the GNSS solution and the truth poses refer to (under the lidar when the preset's "
                 "lidar_x_m and lidar_y_m are 0); the lidar at T_vehicle_lidar")


def preset_mount(p: Preset) -> np.ndarray:
    """The preset's T_vehicle_lidar (lidar_x_m, lidar_y_m, lidar_z_m, lidar_yaw_deg)."""
    return mount_matrix(p.lidar_x_m, p.lidar_y_m, p.lidar_z_m, p.lidar_yaw_deg)


def build_city(p: Preset, seed: int) -> City:
    """The city of (preset, seed): street grid and buildings, then rounded/chamfered corners, street furniture
    and facade detail, each from its own generator (so the grid and footprints do not depend on those
    features)."""
    city = generate_city(p, component_rng(seed, "city"))
    city.buildings = shape_corners(city.buildings, p.rounded_corner_share, p.chamfered_corner_share,
                                   p.corner_radius_m, p.chamfer_m, component_rng(seed, "corner_shapes"))
    city.furniture = generate_furniture(city.curbs_en, p.sidewalk_m, p.furniture_per_km, city.trees, city.poles,
                                       component_rng(seed, "furniture"))
    if p.window_share or p.shopfront_share or p.balcony_share or p.facade_vegetation_share:
        details = generate_facades(city.buildings, p.window_share, p.shopfront_share, p.balcony_share,
                                   p.facade_vegetation_share, component_rng(seed, "facades"))
        city.buildings = [replace(b, facade=d) for b, d in zip(city.buildings, details)]
    if p.parked_tall_share:
        rng = component_rng(seed, "parked_heights")
        tall = rng.random(len(city.parked)) < p.parked_tall_share
        city.parked_top_m = np.where(tall, rng.uniform(1.8, 2.6, len(city.parked)), 1.5)
    return city


def simulate(preset: str | Preset, seed: int, out_dir: Path, n_drives: int | None = None,
             motion_distortion: bool = True, scan_limit: int | None = None,
             progress: Callable[[str, int, int], None] | None = None, changes: bool = False,
             changes_from_drive: int | None = None) -> SimulationSummary:
    """Generate a city, ``n_drives`` drives over it (drive 0 maps, later drives evaluate), a survey cloud
    and ground truth into ``out_dir``. ``scan_limit`` caps the scans written per drive (tests). With
    ``changes``, drives from ``changes_from_drive`` (default: the last) see a changed city (changes.py)."""
    from stages.common.geodesy import EnuOrigin, utm_epsg_for

    p = get_preset(preset) if isinstance(preset, str) else preset
    n_drives = p.default_drives if n_drives is None else int(n_drives)
    if n_drives < 1:
        raise ConfigError("simulate", [f"drives must be >= 1; got {n_drives}"])
    if p.max_scans_per_drive is not None:
        scan_limit = p.max_scans_per_drive if scan_limit is None else min(scan_limit, p.max_scans_per_drive)
    out_dir = Path(out_dir)
    for sub in ("survey", "truth") if p.survey else ("truth",):
        (out_dir / sub).mkdir(parents=True, exist_ok=True)
    origin = EnuOrigin(p.origin_lat_deg, p.origin_lon_deg, p.origin_h_m)
    epsg = utm_epsg_for(origin.lat_deg, origin.lon_deg)

    city = build_city(p, seed)
    marks = rasterize_markings(generate_markings(city), city.bounds_en)
    albedo = asphalt_albedo(city.bounds_en, component_rng(seed, "albedo"))
    static = Scene(build_static_soup(city, component_rng(seed, "mesh")))
    buildings = Scene(build_building_soup(city))
    cells = choose_loop_cells(p.n_rows, p.n_cols, city.nodes_en, p.lap_length_m, component_rng(seed, "route"))
    loop = loop_nodes(cells) if p.route == "loop" else out_and_back_nodes(p.n_rows, p.n_cols)
    T_vehicle_lidar = preset_mount(p)
    lidar = LIDARS[p.sensor]
    beams = build_beam_table(lidar, T_vehicle_lidar)
    calib = LaserCalibration.draw(component_rng(seed, "laser_calibration"), lidar.n_rings)
    corners = building_corners(city)
    worlds = {False: (city, static, buildings, marks)}  # dated variants: False = as generated
    plan = None
    # route districts: every drive its own loop (trajectory.district_loop); the changes along the first changed drive's
    loops = [district_loop(p.n_rows, p.n_cols, k) for k in range(n_drives)] if p.route == "districts" else None
    if changes:
        if loops is not None:
            first = n_drives - 1 if changes_from_drive is None else int(changes_from_drive)
            loop = loops[min(max(first, 0), n_drives - 1)]  # out of range: changed_world names the problem
        plan, *worlds[True] = dated.changed_world(city, loop, p.sidewalk_m, marks, n_drives, changes_from_drive,
                                                  component_rng(seed, "changes"), component_rng(seed, "mesh"))

    names, n_scans, stats, visible, ahead = [], {}, {}, {}, {}
    route0 = None
    for k in range(n_drives):
        spec = DriveSpec.for_index(k, loop if loops is None else loops[k], p, city, seed)
        name = f"drive_{k}"
        drive_dir = out_dir / name
        changed = plan is not None and k >= plan.from_drive  # the drive sees the city as of its date
        w_city, w_static, w_buildings, w_marks = worlds[changed]
        result = simulate_drive(spec, p, w_city, w_static, w_buildings, w_marks, albedo, beams, calib, origin,
                                drive_dir, out_dir / "truth", motion_distortion, scan_limit,
                                component_rng(seed, f"drive{k}"),
                                (lambda i, n, _name=name: progress(_name, i, n)) if progress else None)
        writers.write_drive_yaml(drive_dir / "drive.yaml", name, T_vehicle_lidar, f"EPSG:{epsg}" if p.survey else None,
                                 dated.SURVEY_DIR if changed else "survey", sensor=p.sensor,
                                 gnss_attitude=p.gnss_attitude, gnss=p.gnss, start=result.start,
                                 prior=prior_section(p, origin, _travel_km(result.scan_positions_en)))
        names.append(name)
        n_scans[name] = result.n_scans
        stats[name] = result.gnss_stats
        visible[name] = count_visible_scans(corners, w_static, result.scan_positions_en, p.lidar_z_m)
        if k == 0:
            route0 = result.route_en
        if loops is not None:  # the survey covers every drive's route
            route0 = [*(route0 if isinstance(route0, list) else []), result.route_en]
        ahead[name] = result.lead_scan_share
        log.info("%s: %d scans, GNSS horizontal RMS %.2f m, a vehicle ahead in %.0f%% of the scans", name,
                 result.n_scans, result.gnss_stats["rms_m"], 100 * result.lead_scan_share)

    if p.survey:
        _write_survey(city, route0, p, marks, albedo, origin, epsg, out_dir, component_rng(seed, "survey"))
    _write_truth(out_dir / "truth", city, corners, visible, marks, origin, epsg)
    if plan is not None and p.survey:  # the survey of the changed city, which later drives reference
        (out_dir / dated.SURVEY_DIR).mkdir(exist_ok=True)
        _write_survey(worlds[True][0], route0, p, worlds[True][3], albedo, origin, epsg, out_dir,
                      component_rng(seed, "survey"), dated.SURVEY_DIR)
        dated.write_changes_truth(out_dir / "truth", plan, city, worlds[True][0], marks, worlds[True][3])
    summary = SimulationSummary(p.name, seed, out_dir, names, n_scans, origin.as_dict(), epsg, stats)
    writers.write_json(out_dir / "simulation.json", {
        "preset": p.name, "seed": seed, "code_version": CODE_VERSION, "motion_distortion": motion_distortion,
        "preset_overrides": preset_overrides(p),
        "scan_limit": scan_limit, "drives": names, "n_scans": n_scans, "enu_origin": origin.as_dict(),
        "utm_epsg": epsg, "gnss_error_stats": stats,
        "vehicles_ahead_scan_share": ahead, "T_vehicle_lidar": T_vehicle_lidar.tolist(),
        **({"changes": {"from_drive": plan.from_drive, "truth": "truth/changes.json"}} if plan is not None else {}),
        "vehicle_frame": VEHICLE_FRAME, "sensor": p.sensor, "survey": p.survey,
        "laser_calibration": {"gain": np.round(calib.gain, 6).tolist(), "offset": np.round(calib.offset, 6).tolist()},
    })
    return summary


def _travel_km(positions_en: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(positions_en, axis=0), axis=1).sum()) / 1000.0


def prior_section(p, origin, travel_km: float = 0.0) -> dict | None:
    """The drive file's ``prior:`` of a simulated prior trajectory (``drive.write_prior``), its stated std the
    simulated errors' (horizontal per axis, heading; height, roll and pitch carry none: 0.1 m / 0.1 deg stated). With
    ``prior_heading_walk_deg`` the walk's spread at the drive's end (``travel_km``) is added in quadrature: heading
    walk x sqrt(km), position travel x that heading std / sqrt(3) per axis (a random walk's integral)."""
    if p.prior == "none":
        return None
    std_m, std_deg = p.prior_std_m / np.sqrt(2), p.prior_std_deg
    if p.prior_heading_walk_deg > 0:
        walk_deg = p.prior_heading_walk_deg * np.sqrt(travel_km)
        std_deg = float(np.hypot(std_deg, walk_deg))
        std_m = float(np.hypot(std_m, 1000.0 * travel_km * np.radians(walk_deg) / np.sqrt(3)))
    doc = {"file": "prior.txt", "format": "tum", "frame": p.prior, "time": "stamps", "body": "vehicle",
           "std_m": [round(float(std_m), 4)] * 2 + [0.1],
           "std_deg": [0.1, 0.1, round(float(std_deg), 4)]}
    if p.prior == "enu":
        doc["origin"] = {"lat_deg": origin.lat_deg, "lon_deg": origin.lon_deg, "h_m": origin.h_m}
    return doc


def _write_survey(city, route_en, p: Preset, marks, albedo, origin, epsg, out_dir: Path, rng,
                  sub: str = "survey") -> None:
    from stages.common.geodesy import enu_to_geodetic, geodetic_to_projected

    corridor = max(city.hw_row_m, city.hw_col_m) + p.sidewalk_m
    xyz_enu, refl = generate_survey(city, route_en, corridor, marks, albedo, rng)
    llh = enu_to_geodetic(xyz_enu, origin)
    xyz_utm = geodetic_to_projected(llh[:, 0], llh[:, 1], llh[:, 2], f"EPSG:{epsg}")
    writers.write_las(out_dir / sub / "survey.las", xyz_utm, np.round(refl * 65535.0), epsg)


def _write_truth(truth_dir: Path, city, corners, visible, marks, origin, epsg) -> None:
    header = ["id", "east_m", "north_m", "theta1_deg", "theta2_deg", "interior_angle_deg", "glass_walls"]
    cols = [corners[h] for h in header]
    fmts = ["%d", "%.4f", "%.4f", "%.4f", "%.4f", "%.4f", "%d"]
    for name, counts in visible.items():
        header.append(f"scans_visible_{name.split('_')[-1]}")
        cols.append(counts)
        fmts.append("%d")
    header += ["height_m", "corner_shape", "shape_size_m"]
    cols += [corners["height_m"], np.array([SHAPE_NAMES[k] for k in corners["corner_shape"]], dtype=object),
             corners["shape_size_m"]]
    fmts += ["%.3f", "%s", "%.3f"]
    writers.write_csv(truth_dir / "corners.csv", header, cols, fmts)
    if any(b.facade is not None for b in city.buildings):
        rows = facade_corner_rows([b.facade for b in city.buildings])
        writers.write_csv(truth_dir / "facade_corners.csv", list(rows), list(rows.values()),
                          ["%d", "%s", "%.4f", "%.4f", "%.4f", "%.4f", "%.1f", "%.3f", "%.3f"])
    fc = furniture_corners(city.furniture)
    writers.write_csv(truth_dir / "furniture_corners.csv",
                      FURNITURE_COLUMNS, [fc[k] for k in FURNITURE_COLUMNS],
                      ["%d", "%s", "%.4f", "%.4f", "%.4f", "%.4f", "%.4f", "%.3f"])
    writers.write_png(truth_dir / "markings.png", np.where(marks.data > 0, 255, 0).astype(np.uint8))
    writers.write_json(truth_dir / "markings.json", {
        "frame": "ENU", "origin": origin.as_dict(), "resolution_m": marks.res_m,
        "west_m": marks.west_m, "north_m": marks.north_m, "width_px": int(marks.data.shape[1]),
        "height_px": int(marks.data.shape[0]),
        "pixel_centre": "east = west_m + (col + 0.5) * res, north = north_m - (row + 0.5) * res",
        "values": {"0": "unpainted", "255": "painted (white or yellow)"}})
    writers.write_json(truth_dir / "city.json", city_description(city, origin.as_dict(), epsg))
