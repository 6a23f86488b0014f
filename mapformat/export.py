"""Exports of a published map: Im 2016 Table 1 text, GeoJSON (WGS84; corners and markings), GeoTIFF + VRT, Autoware,
and the version's trajectories (TUM, KITTI).

``*_document`` / ``*_bytes`` functions are pure (arrays in, text/bytes out); ``export_map`` writes files.
"""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np
import pyarrow as pa

from pipeline.errors import DatasetIOError, PublishConflictError
from stages.common.geodesy import EnuOrigin, enu_to_geodetic
from stages.common.im2016_text import format_im2016_text

if TYPE_CHECKING:  # pragma: no cover
    from mapformat.loader import MapReader

FORMATS = ("im2016-text", "geojson", "markings-geojson", "autoware", "geotiff", "tum", "kitti")
DIRECTORY_FORMATS = ("autoware", "geotiff", "tum", "kitti")  # --out is a directory
GEOJSON_CRS = "urn:ogc:def:crs:OGC:1.3:CRS84"


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
    # RFC 7946 coordinates are always WGS84 lon/lat; the 2008 "crs" member says so for readers that look for it
    # (GDAL/OGR, QGIS): OGC CRS84 = WGS84 with longitude first.
    doc: dict[str, Any] = {"type": "FeatureCollection", "crs": {"type": "name", "properties": {"name": GEOJSON_CRS}},
                           "features": feats}
    if properties:
        doc["cornermap"] = properties  # a foreign member (RFC 7946 s.6.1): map name, version, ENU origin
    return doc


def markings_geojson(features: list, origin: EnuOrigin, properties: dict[str, Any] | None = None) -> dict:
    """RFC 7946 FeatureCollection of typed road markings: LineString / Polygon [lon, lat] (WGS84, 1e-9 deg)."""
    feats = []
    for k, f in enumerate(features):
        xy = np.asarray(f.xy_m, float)
        ring = np.vstack([xy, xy[:1]]) if f.is_polygon else xy
        llh = enu_to_geodetic(np.column_stack([ring, np.zeros(len(ring))]), origin)
        coords = np.round(llh[:, [1, 0]], 9).tolist()
        geom = {"type": "Polygon", "coordinates": [coords]} if f.is_polygon else {"type": "LineString",
                                                                                   "coordinates": coords}
        feats.append({"type": "Feature", "id": k, "geometry": geom,
                      "properties": {"type": f.type, "width_m": round(float(f.width_m), 3),
                                     "length_m": round(float(f.length_m), 3)}})
    doc: dict[str, Any] = {"type": "FeatureCollection", "crs": {"type": "name", "properties": {"name": GEOJSON_CRS}},
                           "features": feats}
    if properties:
        doc["cornermap"] = properties
    return doc


def autoware_projector_yaml(origin: EnuOrigin) -> str:
    """Autoware ``map_projector_info.yaml``: LocalCartesian (ENU) about ``origin``'s latitude and longitude at 0 m.

    Autoware's map_projection_loader sets a LocalCartesian origin's altitude to 0 whatever the file says, so the
    folder's frame is ENU about (lat0, lon0, 0 m): z = ellipsoidal height near the origin. The export writes its
    point cloud in that frame (the map frame raised by h0) and the Lanelet2 nodes' ``ele`` as WGS84 ellipsoidal
    heights, which every LocalCartesian projector about this origin (Autoware's, lanelet2's) maps there too."""
    return (f"# written by cornermap: ENU about this WGS84 origin at 0 m; the cornermap map frame is ENU about "
            f"h_m = {origin.h_m:.4f} (z here = z there + {origin.h_m:.4f})\n"
            "projector_type: LocalCartesian\n"
            "vertical_datum: WGS84\n"
            "map_origin:\n"
            f"  latitude: {origin.lat_deg:.10f}\n"
            f"  longitude: {origin.lon_deg:.10f}\n"
            "  altitude: 0.0\n")


class ExportTargetError(DatasetIOError, FileExistsError):
    """A folder export's ``--out`` already holds files (another export's would mix with this one's)."""


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


def export_map(reader: "MapReader", fmt: str, out: Path, root: Path | None = None, *,
               overwrite: bool = False) -> list[Path]:
    """Write ``reader``'s map in ``fmt`` to ``out`` (a file for text/geojson, a directory for the others).

    Each export reads the version directory only, except ``autoware``, which reads the scans, poses and extrinsics
    the version was built from under ``root`` through the fingerprints its manifest records
    (``mapformat.lineage``; default root: the one holding the map's ROOT/maps/NAME/vNNNN directory).

    A folder export (``DIRECTORY_FORMATS``) is written into a hidden sibling and renamed into place when complete;
    an existing non-empty ``out`` is refused (``ExportTargetError``) unless ``overwrite``, which replaces it whole."""
    if fmt not in FORMATS:
        raise ValueError(f"unknown export format {fmt!r}; expected one of {', '.join(FORMATS)}")
    out = Path(out)
    check_export_target(out, reader.path.parent)
    if fmt in DIRECTORY_FORMATS:
        if out.exists() and not out.is_dir():
            raise DatasetIOError(f"{out}: not a directory; the {fmt} export writes a directory")
        held = sum(1 for _ in out.iterdir()) if out.is_dir() else 0
        if held and not overwrite:
            entries = f"{held} entr{'y' if held == 1 else 'ies'}"
            raise ExportTargetError(
                f"{out}: a folder holding {entries}; a {fmt} export writes a folder of its own (another export's "
                "files would mix with this one's). hint: choose a new --out, or pass --overwrite to replace the "
                "folder as a whole")
        return _staged_folder(out, lambda stage: _export_files(reader, fmt, stage, root))
    return _export_files(reader, fmt, out, root)


def _staged_folder(out: Path, write_into: Callable[[Path], list[Path]]) -> list[Path]:
    """Run ``write_into`` on a hidden sibling of ``out`` and put it in place of ``out`` when it is complete: a
    reader of ``out`` sees the old folder or the new one, never a half-written or mixed one (a folder rename;
    between the two renames ``out`` is briefly absent). Returns the written files under ``out``."""
    stage = out.with_name(f".{out.name}.export-{os.getpid()}")
    old = out.with_name(f".{out.name}.replaced-{os.getpid()}")
    shutil.rmtree(stage, ignore_errors=True)
    try:
        stage.mkdir(parents=True)
        files = write_into(stage)
        if out.exists():
            os.replace(out, old)
        os.replace(stage, out)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        if old.exists() and not out.exists():
            os.replace(old, out)  # the earlier folder stays as it was
        raise
    shutil.rmtree(old, ignore_errors=True)
    return [out / Path(f).relative_to(stage) for f in files]


def _export_files(reader: "MapReader", fmt: str, out: Path, root: Path | None) -> list[Path]:
    """Write the files of one export format under (or at) ``out``."""
    corners = reader.all_corners()
    if fmt == "im2016-text":
        text = format_im2016_text(
            *(
                corners[c].to_numpy()
                for c in (
                    "corner_id",
                    "east_m",
                    "north_m",
                    "theta1_rad",
                    "theta2_rad",
                    "cov_ee_m2",
                    "cov_en_m2",
                    "cov_nn_m2",
                )
            ),
            origin=reader.manifest["enu_origin"],
        )
        _atomic_write(out, text.encode("utf-8"))
        return [out]
    props = {"map_name": reader.manifest.get("map_name"), "version": reader.version,
             "enu_origin": reader.manifest["enu_origin"], "manifest_sha256": reader.manifest_sha256}
    if fmt == "markings-geojson":
        from mapformat.vectors import read_map_features

        doc = markings_geojson(read_map_features(reader.path, [reader.tile_entry(*k) for k in reader.tile_keys()]),
                               reader.origin, props)
        _atomic_write(out, json.dumps(doc, separators=(",", ":")).encode("utf-8"))
        return [out]
    if fmt == "geojson":
        doc = corners_geojson(corners, reader.origin, props)
        _atomic_write(out, json.dumps(doc, separators=(",", ":")).encode("utf-8"))
        return [out]
    if fmt == "geotiff":
        from mapformat.geotiff import export_geotiffs

        return export_geotiffs(reader, out, write=_atomic_write)
    if fmt in ("tum", "kitti"):
        from mapformat.trajectories import export_trajectories

        return export_trajectories(reader, fmt, out, write=_atomic_write)
    from mapformat.autoware import export_autoware

    return export_autoware(reader, out, root if root is not None else reader.path.parents[2],
                           write=_atomic_write)
