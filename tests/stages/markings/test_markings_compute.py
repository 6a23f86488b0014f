"""The stage adapter on in-memory tables: survey and drive-scan sources, tile planning, tile borders."""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute  # noqa: F401  (pa.compute)
import pytest
from scipy.spatial.transform import Rotation

from fixtures.markings import make_street, truth_raster
from pipeline.declare import PartitionKey
from pipeline.errors import ConfigError
from pipeline.testing import make_context
from schemas import SCHEMAS
from stages.common.geometry import se3_from_xyz_rpy, se3_inverse, transform_points
from stages.markings.compute import compute, plan_tiles
from stages.markings.decl import STAGE
from stages.markings.metrics import match_masks
from stages.markings.params import MarkingParams
from stages.markings.raster_io import read_tile_rasters

OFFSET = (20.0, 40.0)  # the 20 m street scene sits in tile (1, 2) of a 20 m grid


@pytest.fixture(scope="module")
def street():
    s = make_street(np.random.default_rng(11))
    return s.points_enu_m + np.array([*OFFSET, 0.0]), s.intensity


def _survey_table(points, intensity, drive="survey_a"):
    return pa.table({"drive": [drive] * len(points), "east_m": points[:, 0], "north_m": points[:, 1],
                     "up_m": points[:, 2], "intensity": intensity.astype(np.float32)},
                    schema=SCHEMAS["survey_enu"])


def _run(tables, tile, tile_size_m=20.0, params=MarkingParams(), tmp_path=None):
    ctx = make_context("markings", params, tables, partition=PartitionKey(tile_i=tile[0], tile_j=tile[1]),
                       settings={"tile_size_m": tile_size_m}, outputs=("raster", "rasters"), workdir=tmp_path)
    out = compute(ctx)
    return out, read_tile_rasters(ctx.artifact_dirs["rasters"])


def test_survey_tile_end_to_end(street, tmp_path):
    points, intensity = street
    tables = {"survey": _survey_table(points, intensity)}
    plan_ctx = make_context("markings", MarkingParams(), tables, settings={"tile_size_m": 20.0})
    assert plan_tiles(plan_ctx) == [PartitionKey(tile_i=1, tile_j=2)]
    out, rasters = _run(tables, (1, 2), tmp_path=tmp_path)
    row = out["raster"].to_pylist()[0]
    assert out["raster"].schema.equals(SCHEMAS["marking_raster"]) and out["rasters"] is None
    assert row["source"] == "survey" and (row["width_px"], row["height_px"]) == (200, 200)
    assert (row["origin_east_m"], row["origin_north_m"]) == OFFSET
    assert row["n_points"] + rasters.meta["n_above_surface"] == len(points) and rasters.meta["n_above_surface"] > 0
    assert row["n_marking_px"] == rasters.marking_mask.sum()
    truth = truth_raster(200, 200, *OFFSET, 0.1, *OFFSET)
    scores = match_masks(rasters.marking_mask, truth)
    assert scores["precision"] >= 0.97 and scores["recall"] >= 0.97, scores
    assert rasters.meta["tile_i"] == 1 and rasters.meta["params"]["cell_m"] == 0.1


def test_tiles_agree_across_their_borders(street, tmp_path):
    """Four 10 m tiles (with halos) give the same mosaic as one 20 m tile."""
    points, intensity = street
    tables = {"survey": _survey_table(points, intensity)}
    _, whole = _run(tables, (1, 2), tmp_path=tmp_path / "whole")
    plan = plan_tiles(make_context("markings", MarkingParams(), tables, settings={"tile_size_m": 10.0}))
    assert [(k.tile_i, k.tile_j) for k in plan] == [(2, 4), (2, 5), (3, 4), (3, 5)]
    mosaic_mark = np.zeros((200, 200), bool)
    mosaic_trav = np.zeros((200, 200), bool)
    for k in plan:
        _, part = _run(tables, (k.tile_i, k.tile_j), tile_size_m=10.0, tmp_path=tmp_path / k.label)
        r0 = 100 * (5 - k.tile_j)  # row 0 = north: the northern tile row (j = 5) comes first
        c0 = 100 * (k.tile_i - 2)
        mosaic_mark[r0:r0 + 100, c0:c0 + 100] = part.marking_mask
        mosaic_trav[r0:r0 + 100, c0:c0 + 100] = part.traversable_mask
    assert (mosaic_trav == whole.traversable_mask).mean() == 1.0
    assert (mosaic_mark == whole.marking_mask).mean() >= 0.999


def _drive_tables(points, intensity, rng):
    """Split the street cloud into scans of a vehicle driving east along north = 49 m (lidar 1.8 m up)."""
    xs = np.arange(20.0, 40.0, 1.0)
    T_vehicle_lidar = se3_from_xyz_rpy(0.5, 0.0, 1.8, 0.0, 0.02, 0.0)
    T_map_vehicle = [se3_from_xyz_rpy(x, 49.0, 1.0 + 0.05 * (x - 20), 0.01, -0.05, 0.1 * np.sin(x)) for x in xs]
    nearest = np.argmin(np.abs(points[:, :1] - xs[None, :]), axis=1)
    scans = []
    for s, T in enumerate(T_map_vehicle):
        sel = nearest == s
        p_lidar = transform_points(se3_inverse(T @ T_vehicle_lidar), points[sel])
        scans.append({"drive": "d1", "chunk": s // 10, "scan_id": s, "stamp_ns": s * 100_000_000,
                      "x_m": p_lidar[:, 0], "y_m": p_lidar[:, 1], "z_m": p_lidar[:, 2],
                      "intensity": intensity[sel]})
    cols = {k: np.concatenate([np.broadcast_to(np.asarray(sc[k]), (len(sc["x_m"]),)) for sc in scans])
            for k in scans[0]}
    n = len(cols["x_m"])
    scans_tbl = pa.table({**cols, "ring": np.zeros(n, np.int16), "time_offset_s": np.zeros(n, np.float32)},
                         schema=SCHEMAS["scans_raw"])
    T = np.stack(T_map_vehicle)
    q = Rotation.from_matrix(T[:, :3, :3]).as_quat()
    poses = pa.table({"drive": ["d1"] * len(xs), "scan_id": np.arange(len(xs)), "stamp_ns": np.arange(len(xs)),
                      "x_m": T[:, 0, 3], "y_m": T[:, 1, 3], "z_m": T[:, 2, 3], "qx": q[:, 0], "qy": q[:, 1],
                      "qz": q[:, 2], "qw": q[:, 3], "cov_xy_yaw": [[0.0] * 9] * len(xs)},
                     schema=SCHEMAS["poses_optimized"])
    info = pa.table({"drive": ["d1"], "sensor": ["sim"], "T_vehicle_lidar": [T_vehicle_lidar.ravel().tolist()],
                     "origin_lat_deg": [37.5], "origin_lon_deg": [127.0], "origin_h_m": [57.0], "n_scans": [20],
                     "n_quarantined": [0], "drive_file": ["d1/drive.yaml"]}, schema=SCHEMAS["drive_info"])
    return {"scans": scans_tbl, "poses": poses, "drive_info": info}


def test_drive_scans_rebuild_the_same_map(street, tmp_path):
    points, intensity = street
    tables = _drive_tables(points, intensity, np.random.default_rng(2))
    tables["survey"] = _survey_table(points[:0], intensity[:0])  # a survey input without rows
    params = MarkingParams(min_range_m=0.0)
    plan = plan_tiles(make_context("markings", params, tables, settings={"tile_size_m": 20.0}))
    # poses east 20..39 m, north 49 m, buffered by 30 m: east -10..69 (i -1..3), north 19..79 (j 0..3)
    assert plan == [PartitionKey(tile_i=i, tile_j=j) for i in range(-1, 4) for j in range(0, 4)]
    out, rasters = _run(tables, (1, 2), params=params, tmp_path=tmp_path)
    row = out["raster"].to_pylist()[0]
    assert row["source"] == "drives" and row["n_points"] + rasters.meta["n_above_surface"] == len(points)
    truth = truth_raster(200, 200, *OFFSET, 0.1, *OFFSET)
    scores = match_masks(rasters.marking_mask, truth)
    assert scores["precision"] >= 0.97 and scores["recall"] >= 0.97, scores


def test_source_param_picks_the_cloud_and_eval_drives_stay_out(street, tmp_path):
    """source='drives' with a survey present builds from the map drives' scans; an evaluation drive's scans
    (here the same scans placed 3 m north) never enter the map; source='survey' without survey points is named."""
    points, intensity = street
    tables = _drive_tables(points, intensity, np.random.default_rng(2))
    tables["survey"] = _survey_table(points, intensity)

    def as_drive(t: pa.Table, name: str) -> pa.Table:
        return t.set_column(0, "drive", pa.array([name] * t.num_rows)).cast(t.schema)

    ev_poses = as_drive(tables["poses"], "d2")
    ev_poses = ev_poses.set_column(4, "y_m", pa.compute.add(ev_poses["y_m"], 3.0)).cast(ev_poses.schema)
    for name, extra in (("scans", as_drive(tables["scans"], "d2")), ("poses", ev_poses),
                        ("drive_info", as_drive(tables["drive_info"], "d2"))):
        tables[name] = pa.concat_tables([tables[name], extra])
    params = MarkingParams(min_range_m=0.0, source="drives", surface_band_m=0.0)  # every point counts
    ctx = make_context("markings", params, tables, partition=PartitionKey(tile_i=1, tile_j=2),
                       settings={"tile_size_m": 20.0, "map_drives": ["d1"], "eval_drives": ["d2"]},
                       outputs=("raster", "rasters"), workdir=tmp_path)
    row = compute(ctx)["raster"].to_pylist()[0]
    assert row["source"] == "drives" and row["n_points"] == len(points)
    survey_row = _run({**tables, "poses": tables["poses"].slice(0, 0)}, (1, 2), tmp_path=tmp_path / "s")[0]
    assert survey_row["raster"].to_pylist()[0]["source"] == "survey"
    empty = {**tables, "survey": _survey_table(points[:0], intensity[:0])}
    with pytest.raises(ConfigError, match="source 'survey'"):
        plan_tiles(make_context("markings", MarkingParams(source="survey"), empty, settings={"tile_size_m": 20.0}))


def test_no_source_is_a_config_error():
    with pytest.raises(ConfigError, match="neither a survey"):
        plan_tiles(make_context("markings", MarkingParams(), {}, settings={"tile_size_m": 20.0}))


def test_declaration_matches_the_contract():
    assert STAGE.name == "markings" and STAGE.partition.value == "per_tile"
    assert STAGE.outputs == {"raster": "marking_raster", "rasters": "marking_rasters"}
    assert set(STAGE.optional_inputs) == set(STAGE.inputs)
    assert STAGE.load_compute() is compute
