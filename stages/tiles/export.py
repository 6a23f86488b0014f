"""Exports of a published map: Im 2016 Table 1 text, GeoJSON (WGS84), Autoware (projector info + PCD).

``*_document`` / ``*_bytes`` functions are pure (arrays in, text/bytes out); ``export_map`` writes files.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pyarrow as pa

from pipeline.errors import DatasetIOError, LimitError, PublishConflictError
from stages.common.geodesy import EnuOrigin, enu_to_geodetic
from stages.common.im2016_text import format_im2016_text

if TYPE_CHECKING:  # pragma: no cover
    from stages.tiles.loader import MapReader

FORMATS = ("im2016-text", "geojson", "autoware")
MAX_COLUMN_HEIGHT_M = 1000.0  # autoware columns: a corner is a building edge, not a space elevator
MAX_EXPORT_POINTS = 200_000_000  # 3.2 GB of float32 x y z intensity


def corners_geojson(corners: pa.Table, origin: EnuOrigin, properties: dict[str, Any] | None = None) -> dict:
    """RFC 7946 FeatureCollection: one Point [lon, lat, h] (WGS84 degrees, ellipsoidal m) per corner.

    Coordinates keep 1e-9 degree (~0.1 mm) so that a round trip to ENU stays within 1 mm.
    """
    n = corners.num_rows
    col = {c: corners[c].to_numpy(zero_copy_only=False) for c in corners.column_names}
    enu = np.column_stack([col["east_m"], col["north_m"], np.zeros(n)]) if n else np.zeros((0, 3))
    llh = enu_to_geodetic(enu, origin) if n else np.zeros((0, 3))
    lon = np.round(llh[:, 1], 9).tolist()
    lat = np.round(llh[:, 0], 9).tolist()
    h = np.round(llh[:, 2], 4).tolist()
    a1, a2 = np.round(np.degrees(col["theta1_rad"]), 3).tolist(), np.round(np.degrees(col["theta2_rad"]), 3).tolist()
    feats = []
    for k in range(n):
        feats.append({"type": "Feature", "id": int(col["corner_id"][k]),
                      "geometry": {"type": "Point", "coordinates": [lon[k], lat[k], h[k]]},
                      "properties": {"corner_id": int(col["corner_id"][k]), "east_m": float(col["east_m"][k]),
                                     "north_m": float(col["north_m"][k]), "angle1_deg": a1[k], "angle2_deg": a2[k],
                                     "cov_m2": [float(col["cov_ee_m2"][k]), float(col["cov_en_m2"][k]),
                                                float(col["cov_nn_m2"][k])],
                                     "n_obs": int(col["n_obs"][k]), "n_drives": int(col["n_drives"][k])}})
    doc: dict[str, Any] = {"type": "FeatureCollection", "features": feats}
    if properties:
        doc["cornermap"] = properties  # a foreign member (RFC 7946 s.6.1): map name, version, ENU origin
    return doc


def autoware_projector_yaml(origin: EnuOrigin) -> str:
    """Autoware ``map_projector_info.yaml`` for a local ENU (LocalCartesian) frame about ``origin``."""
    return ("# written by cornermap: the map frame is ENU about this WGS84 origin\n"
            "projector_type: LocalCartesian\n"
            "vertical_datum: WGS84\n"
            "map_origin:\n"
            f"  latitude: {origin.lat_deg:.10f}\n"
            f"  longitude: {origin.lon_deg:.10f}\n"
            f"  altitude: {origin.h_m:.4f}\n")


def corner_columns_xyz(east_m: np.ndarray, north_m: np.ndarray, height_m: float, step_m: float) -> np.ndarray:
    """Each corner as a vertical column of points from 0 to ``height_m`` (it is a vertical edge), (N*K, 3)."""
    z = np.arange(0.0, height_m + 1e-9, step_m) if height_m > 0 else np.zeros(1)
    k = len(z)
    return np.column_stack([np.repeat(east_m, k), np.repeat(north_m, k), np.tile(z, len(east_m))])


def pcd_bytes(xyz_m: np.ndarray, intensity: np.ndarray) -> bytes:
    """Binary PCD v0.7 with float32 x y z intensity (what Autoware's map loader reads)."""
    n = len(xyz_m)
    header = ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\n"
              f"TYPE F F F F\nCOUNT 1 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n")
    data = np.column_stack([np.asarray(xyz_m, np.float32), np.asarray(intensity, np.float32)]).astype("<f4")
    return header.encode("ascii") + data.tobytes()


def _atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to a temporary sibling and rename it over ``path``; nothing is left behind on failure."""
    if path.is_dir():
        raise DatasetIOError(f"{path}: is a directory; expected a file name for this export format")
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_bytes(data)
        os.replace(tmp, path)
    except OSError as exc:
        if tmp.parent.is_dir():
            tmp.unlink(missing_ok=True)
        raise DatasetIOError(f"{path}: cannot write the export ({exc.strerror or exc})") from exc


def check_export_target(out: Path, map_dir: Path) -> None:
    """Refuse an ``--out`` inside a published map collection (it could overwrite LATEST or a published file)."""
    target, collection = Path(out).resolve(), Path(map_dir).resolve()
    if target == collection or collection in target.parents:
        raise PublishConflictError(f"{out}: inside the published map {collection}; an export never writes there "
                                   "(it could replace LATEST or a published file). hint: choose another --out")


def check_column_limits(n_corners: int, height_m: float, step_m: float) -> None:
    """Named LimitError before allocating: height in [0, MAX_COLUMN_HEIGHT_M], step > 0, bounded points."""
    if not (math.isfinite(height_m) and 0.0 <= height_m <= MAX_COLUMN_HEIGHT_M):
        raise LimitError(f"--column-height-m {height_m}: expected 0 to {MAX_COLUMN_HEIGHT_M} m")
    if not (math.isfinite(step_m) and step_m > 0.0):
        raise LimitError(f"column step {step_m} m: expected a positive number")
    points = n_corners * (int(height_m / step_m) + 1)
    if points > MAX_EXPORT_POINTS:
        raise LimitError(f"autoware export of {n_corners} corners as {height_m} m columns every {step_m} m = "
                         f"{points} points, more than the limit of {MAX_EXPORT_POINTS}; hint: lower "
                         "--column-height-m")


def export_map(reader: "MapReader", fmt: str, out: Path, column_height_m: float = 10.0,
               column_step_m: float = 0.5) -> list[Path]:
    """Write ``reader``'s map in ``fmt`` to ``out`` (a file for text/geojson, a directory for autoware)."""
    if fmt not in FORMATS:
        raise ValueError(f"unknown export format {fmt!r}; expected one of {', '.join(FORMATS)}")
    out = Path(out)
    check_export_target(out, reader.path.parent)
    if fmt == "autoware":
        check_column_limits(0, column_height_m, column_step_m)
        if out.exists() and not out.is_dir():
            raise DatasetIOError(f"{out}: not a directory; the autoware export writes a directory")
    corners = reader.all_corners()
    if fmt == "im2016-text":
        text = format_im2016_text(*(corners[c].to_numpy() for c in (
            "corner_id", "east_m", "north_m", "theta1_rad", "theta2_rad", "cov_ee_m2", "cov_en_m2", "cov_nn_m2")))
        _atomic_write(out, text.encode("utf-8"))
        return [out]
    if fmt == "geojson":
        props = {"map_name": reader.manifest.get("map_name"), "version": reader.version,
                 "enu_origin": reader.manifest["enu_origin"], "manifest_sha256": reader.manifest_sha256}
        doc = corners_geojson(corners, reader.origin, props)
        _atomic_write(out, json.dumps(doc, separators=(",", ":")).encode("utf-8"))
        return [out]
    east, north = corners["east_m"].to_numpy(), corners["north_m"].to_numpy()
    check_column_limits(len(east), column_height_m, column_step_m)
    xyz = corner_columns_xyz(east, north, column_height_m, column_step_m)
    per = len(xyz) // max(1, len(east))
    intensity = np.repeat(corners["n_obs"].to_numpy().astype(float), per)
    files = [out / "map_projector_info.yaml", out / "pointcloud_map.pcd"]
    _atomic_write(files[0], autoware_projector_yaml(reader.origin).encode("utf-8"))
    _atomic_write(files[1], pcd_bytes(xyz, intensity))
    return files
