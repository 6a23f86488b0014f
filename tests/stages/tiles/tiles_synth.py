"""A synthetic city with known buildings, a drive along its streets and painted lane lines (not a test module).

Buildings are 30 m x 20 m rectangles on a 50 m block grid over [0, 300) x [0, 300) m ENU; every building
contributes its 4 vertices as corners (theta1/theta2 point along the two walls). The drive runs north-south
along the streets at east = 50, 150, 250 m. A lane line is painted at east = 50.25 m in tiles (0, *).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa

from pipeline.testing import make_context
from schemas import SCHEMAS
from stages.common.geodesy import EnuOrigin

ORIGIN = EnuOrigin(37.4979, 127.0276, 38.0)  # Gangnam station, WGS84
CELL_M = 0.5
TILE_M = 100.0
LINE_EAST_M = 50.25


def buildings(n_blocks: int = 6, pitch_m: float = 50.0) -> np.ndarray:
    """(B, 4) building rectangles e0, n0, e1, n1."""
    c = pitch_m / 2 + pitch_m * np.arange(n_blocks)
    ce, cn = np.meshgrid(c, c, indexing="ij")
    ce, cn = ce.ravel(), cn.ravel()
    return np.column_stack([ce - 15, cn - 10, ce + 15, cn + 10])


def building_corners(rects: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(4B, 2) vertices, (4B, 2) wall directions (rad), (4B,) building index."""
    e0, n0, e1, n1 = rects.T
    xy = np.stack([np.column_stack([e0, n0]), np.column_stack([e1, n0]), np.column_stack([e1, n1]),
                   np.column_stack([e0, n1])], axis=1).reshape(-1, 2)
    dirs = np.tile(np.array([[0.0, np.pi / 2], [np.pi / 2, np.pi], [np.pi, -np.pi / 2], [-np.pi / 2, 0.0]]),
                   (len(rects), 1))
    return xy, dirs, np.repeat(np.arange(len(rects)), 4)


def corner_table(xy: np.ndarray, dirs: np.ndarray, seed: int, noise_m: float = 0.005,
                 first_id: int = 1) -> pa.Table:
    rng = np.random.default_rng(seed)
    n = len(xy)
    pos = xy + rng.normal(0.0, noise_m, size=xy.shape)
    cols = {
        "corner_id": np.arange(first_id, first_id + n, dtype=np.int64), "east_m": pos[:, 0], "north_m": pos[:, 1],
        "theta1_rad": dirs[:, 0], "theta2_rad": dirs[:, 1], "cov_ee_m2": np.full(n, 0.0021),
        "cov_en_m2": np.full(n, 0.0009), "cov_nn_m2": np.full(n, 0.0029), "n_obs": np.full(n, 12, np.int64),
        "n_drives": np.full(n, 1, np.int32), "drives": ["drive_a"] * n, "first_seen_ns": np.zeros(n, np.int64),
        "last_seen_ns": np.full(n, 10**9, np.int64), "interior_angle_rad": np.full(n, np.pi / 2),
        "convex": np.ones(n, bool)}
    return pa.table(cols, schema=SCHEMAS["corner_map"])


def drive_path(step_m: float = 1.0) -> np.ndarray:
    """Serpentine along the north-south streets: (N, 2) ENU."""
    legs = [((50, 2), (50, 298)), ((50, 298), (150, 298)), ((150, 298), (150, 2)), ((150, 2), (250, 2)),
            ((250, 2), (250, 298))]
    pts = []
    for (a, b) in legs:
        a, b = np.asarray(a, float), np.asarray(b, float)
        n = int(np.ceil(np.linalg.norm(b - a) / step_m))
        pts.append(a + (b - a) * (np.arange(n) / n)[:, None])
    pts.append(np.asarray([[250.0, 298.0]]))
    return np.vstack(pts)


def poses_table(xy: np.ndarray, drive: str = "drive_a") -> pa.Table:
    d = np.diff(xy, axis=0, append=xy[-1:] + (xy[-1:] - xy[-2:-1]))
    yaw = np.arctan2(d[:, 1], d[:, 0])
    n = len(xy)
    return pa.table({
        "drive": [drive] * n, "scan_id": np.arange(n, dtype=np.int64),
        "stamp_ns": 1_400_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 100_000_000,
        "x_m": xy[:, 0], "y_m": xy[:, 1], "z_m": np.zeros(n), "qx": np.zeros(n), "qy": np.zeros(n),
        "qz": np.sin(yaw / 2), "qw": np.cos(yaw / 2), "cov_xy_yaw": [[0.01, 0, 0, 0, 0.01, 0, 0, 0, 1e-4]] * n,
    }, schema=SCHEMAS["poses_optimized"])


def drive_info_table(drive: str = "drive_a") -> pa.Table:
    return pa.table({"drive": [drive], "sensor": ["hdl32e"], "T_vehicle_lidar": [list(np.eye(4).ravel())],
                     "origin_lat_deg": [ORIGIN.lat_deg], "origin_lon_deg": [ORIGIN.lon_deg],
                     "origin_h_m": [ORIGIN.h_m], "n_scans": [100], "n_quarantined": [0],
                     "drive_file": [f"{drive}/drive.yaml"]}, schema=SCHEMAS["drive_info"])


def line_mask(cell_m: float = CELL_M, tile_m: float = TILE_M) -> np.ndarray:
    """The painted line in a tile (0, j) raster: column of east = LINE_EAST_M, row 0 = north."""
    import cv2  # noqa: F401  (the caller writes PNGs)

    n = int(round(tile_m / cell_m))
    mask = np.zeros((n, n), np.uint8)
    mask[:, int(LINE_EAST_M // cell_m)] = 255
    return mask


UNSURVEYED_EAST_M = 80.0  # tile (0, 2) saw no ground east of this (its point_count is 0 there)


def _point_count(shape: tuple[int, int], tile_j: int, cell_m: float) -> np.ndarray:
    count = np.full(shape, 3, np.int64)
    if tile_j == 2:
        count[:, int(round(UNSURVEYED_EAST_M / cell_m)):] = 0
    return count


def write_rasters(directory: Path, cell_m: float = CELL_M, tile_m: float = TILE_M, seed: int = 5,
                  flat: bool = False) -> pa.Table:
    """Marking artifacts for tiles (0, 0..2) and their marking_raster rows.

    Default: the markings stage's own writer, one directory per partition label (what the store serves).
    ``flat``: one directory of ``tile_{i}_{j}_marking.png`` / ``tile_{i}_{j}.json`` files (the older convention).
    """
    import json

    import cv2

    from pipeline.declare import PartitionKey
    from stages.markings.raster_io import TileRasters, write_tile_rasters

    directory.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    rows = []
    mask = line_mask(cell_m, tile_m)
    for j in range(3):
        intensity = rng.uniform(0, 100, mask.shape)
        if flat:
            stem = directory / f"tile_0_{j}"
            cv2.imwrite(f"{stem}_marking.png", mask)
            cv2.imwrite(f"{stem}_intensity.png", intensity.astype(np.uint8))
            Path(f"{stem}.json").write_text(json.dumps({"tile_i": 0, "tile_j": j, "cell_m": cell_m}))
        else:
            write_tile_rasters(directory / PartitionKey(tile_i=0, tile_j=j).label, TileRasters(
                marking_mask=mask > 0, traversable_mask=np.ones(mask.shape, bool), intensity=intensity,
                min_up_m=np.zeros(mask.shape), mean_up_m=np.zeros(mask.shape),
                count=_point_count(mask.shape, j, cell_m), origin_east_m=0.0, origin_north_m=j * tile_m,
                cell_m=cell_m, meta={"tile_i": 0, "tile_j": j}))
        rows.append({"tile_i": 0, "tile_j": j, "origin_east_m": 0.0, "origin_north_m": j * tile_m,
                     "cell_m": cell_m, "width_px": mask.shape[1], "height_px": mask.shape[0],
                     "n_marking_px": int((mask > 0).sum()), "n_traversable_px": 0, "n_points": 1000,
                     "source": "drives"})
    return pa.Table.from_pylist(rows, schema=SCHEMAS["marking_raster"])


def city_context(root: Path, corners: pa.Table, *, params=None, fingerprint: str = "fp1", rasters: bool = True,
                 map_name: str = "city", flat_rasters: bool = False, poses_metadata: dict | None = None):
    from stages.tiles.params import TilesParams

    tables = {"corner_map": corners, "poses": poses_table(drive_path()), "drive_info": drive_info_table()}
    artifacts = {}
    base = root / ("raster_flat" if flat_rasters else "raster_artifacts")
    if rasters:
        tables["raster"] = write_rasters(base, flat=flat_rasters)
        artifacts["raster" if flat_rasters else "rasters"] = base
    meta = {arg: {"fingerprint": f"{fingerprint}-{arg}"} for arg in [*tables, *artifacts]}
    meta["drive_info"]["enu_origin"] = ORIGIN.as_dict()
    meta["poses"].update(poses_metadata or {})  # what the pose graph states beside its poses (error correlation)
    ctx = make_context("tiles", params or TilesParams(), tables, metadata=meta, input_artifacts=artifacts,
                        settings={"map_name": map_name, "root": str(root), "tile_size_m": TILE_M,
                                  "enu_origin": ORIGIN.as_dict()},
                        outputs=("published",), workdir=root / "work")
    if rasters and not flat_rasters:  # the store serves one artifact directory per partition
        ctx.inputs.artifact_dir = lambda arg, partition=None: base / partition.label
    return ctx


def publish_two_versions(root: Path) -> Path:
    """Two published versions of the synthetic city map under ``root``: all buildings, then without building 0."""
    from stages.tiles.compute import compute

    xy, dirs, owner = building_corners(buildings())
    compute(city_context(root, corner_table(xy, dirs, seed=3)))
    keep = owner != 0
    compute(city_context(root, corner_table(xy[keep], dirs[keep], seed=4), fingerprint="fp2"))
    return root
