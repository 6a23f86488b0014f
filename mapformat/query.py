"""Where the vehicle is: everything a localizer needs around a place, asked by latitude / longitude or by a pose with
a field of view (``MapReader.query_latlon`` / ``query_pose``; ``cornermap tiles query``).

A query returns the corners in the area (every corner_map column plus ``lat_deg`` / ``lon_deg`` on WGS84, the corner
at the map's ENU height 0), the marking window over the area's bounding box (``MapReader.marking_window``: row 0 north,
0 where no raster) and the localizability cells whose road point lies in the area. Latitude / longitude go to the
map's ENU frame with pymap3d at the origin's height (a query 1 km from the origin that is 50 m off in height moves
by 8 mm horizontally).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from pipeline.errors import LimitError

if TYPE_CHECKING:  # pragma: no cover
    from mapformat.loader import MapReader

MAX_RADIUS_M = 10_000.0


@dataclass(frozen=True)
class MapQuery:
    """One query's answer. ``marking``: (mask uint8 row 0 north, (east_m, north_m) of its south-west corner, cell_m),
    None when the map has no rasters or it was not asked for."""

    east_m: float
    north_m: float
    radius_m: float
    corners: pa.Table
    marking: tuple[np.ndarray, tuple[float, float], float] | None
    localizability: pa.Table
    heading_rad: float | None = None
    fov_rad: float | None = None


def check_area(radius_m: float, fov_deg: float | None = None) -> None:
    if not (np.isfinite(radius_m) and 0.0 < radius_m <= MAX_RADIUS_M):
        raise LimitError(f"radius {radius_m} m: expected more than 0 and at most {MAX_RADIUS_M:g} m")
    if fov_deg is not None and not (np.isfinite(fov_deg) and 0.0 < fov_deg <= 360.0):
        raise LimitError(f"field of view {fov_deg} deg: expected more than 0 and at most 360 deg")


def to_enu(reader: "MapReader", lat_deg: float, lon_deg: float) -> tuple[float, float]:
    """(east_m, north_m) of a WGS84 latitude / longitude in the map's frame (at the origin's height)."""
    from stages.common.geodesy import geodetic_to_enu

    if not (np.isfinite(lat_deg) and np.isfinite(lon_deg) and -90 <= lat_deg <= 90 and -180 <= lon_deg <= 180):
        raise LimitError(f"latitude {lat_deg}, longitude {lon_deg}: expected degrees in [-90, 90] and [-180, 180]")
    e, n, _ = geodetic_to_enu([lat_deg], [lon_deg], [reader.origin.h_m], reader.origin)[0]
    return float(e), float(n)


def with_latlon(reader: "MapReader", corners: pa.Table) -> pa.Table:
    """``corners`` with ``lat_deg`` / ``lon_deg`` (WGS84) appended."""
    from stages.common.geodesy import enu_to_geodetic

    if corners.num_rows == 0:
        ll = np.zeros((0, 3))
    else:
        enu = np.column_stack([corners["east_m"].to_numpy(), corners["north_m"].to_numpy(), np.zeros(corners.num_rows)])
        ll = enu_to_geodetic(enu, reader.origin)
    return corners.append_column(pa.field("lat_deg", pa.float64(), metadata={"unit": "deg", "datum": "WGS84"}),
                                 pa.array(ll[:, 0])).append_column(
        pa.field("lon_deg", pa.float64(), metadata={"unit": "deg", "datum": "WGS84"}), pa.array(ll[:, 1]))


def _in_view(east: np.ndarray, north: np.ndarray, e0: float, n0: float, radius_m: float, heading_rad: float | None,
             fov_rad: float | None) -> np.ndarray:
    d_e, d_n = east - e0, north - n0
    keep = d_e * d_e + d_n * d_n <= radius_m * radius_m
    if heading_rad is not None and fov_rad is not None and fov_rad < 2 * np.pi:
        off = np.abs((np.arctan2(d_n, d_e) - heading_rad + np.pi) % (2 * np.pi) - np.pi)
        keep &= (off <= fov_rad / 2) | (d_e * d_e + d_n * d_n < 1e-12)
    return keep


def query(reader: "MapReader", east_m: float, north_m: float, radius_m: float, *, heading_rad: float | None = None,
          fov_rad: float | None = None, markings: bool = True) -> MapQuery:
    """The area within ``radius_m`` of (east_m, north_m) (map ENU), within ``fov_rad`` about ``heading_rad`` (ENU,
    counter-clockwise from east) when both are given."""
    check_area(radius_m, None if fov_rad is None else float(np.degrees(fov_rad)))
    corners = reader.corners_within(east_m, north_m, radius_m)
    if heading_rad is not None and fov_rad is not None and corners.num_rows:
        keep = _in_view(corners["east_m"].to_numpy(), corners["north_m"].to_numpy(), east_m, north_m, radius_m,
                        heading_rad, fov_rad)
        corners = corners.take(np.flatnonzero(keep))
    box = (east_m - radius_m, north_m - radius_m, east_m + radius_m, north_m + radius_m)
    cells = reader.localizability_in_bbox(*box, keep=lambda e, n: _in_view(e, n, east_m, north_m, radius_m,
                                                                           heading_rad, fov_rad))
    marking = reader.marking_window(*box) if markings and reader.cell_m is not None else None
    return MapQuery(east_m, north_m, radius_m, with_latlon(reader, corners), marking, cells, heading_rad, fov_rad)


def query_latlon(reader: "MapReader", lat_deg: float, lon_deg: float, radius_m: float, *,
                 heading_deg: float | None = None, fov_deg: float | None = None, markings: bool = True) -> MapQuery:
    """``query`` about a WGS84 latitude / longitude; a heading in degrees from east, counter-clockwise (ENU)."""
    e, n = to_enu(reader, lat_deg, lon_deg)
    heading = None if heading_deg is None else float(np.radians(heading_deg))
    fov = None if fov_deg is None else float(np.radians(fov_deg))
    return query(reader, e, n, radius_m, heading_rad=heading, fov_rad=fov, markings=markings)


CORNER_KEYS = ("corner_id", "east_m", "north_m", "lat_deg", "lon_deg", "theta1_rad", "theta2_rad", "cov_ee_m2",
               "cov_en_m2", "cov_nn_m2", "n_obs", "n_drives", "convex")


def as_json(reader: "MapReader", q: MapQuery) -> dict[str, Any]:
    """The answer as JSON-able data: the corners (``CORNER_KEYS``), the marking window's georeference and counts,
    the localizability cells."""
    corners = q.corners.select([k for k in CORNER_KEYS if k in q.corners.column_names]).to_pylist()
    for c in corners:
        c["theta1_deg"], c["theta2_deg"] = round(np.degrees(c["theta1_rad"]), 3), round(np.degrees(c["theta2_rad"]), 3)
    marking = None
    if q.marking is not None:
        mask, (e_sw, n_sw), cell = q.marking
        marking = {"origin_east_m": e_sw, "origin_north_m": n_sw, "cell_m": cell, "width_px": int(mask.shape[1]),
                   "height_px": int(mask.shape[0]), "painted_px": int(np.count_nonzero(mask))}
    lat, lon = reader_latlon(reader, q.east_m, q.north_m)
    return {"map": reader.manifest.get("map_name"), "version": reader.version,
            "at": {"lat_deg": lat, "lon_deg": lon, "east_m": round(q.east_m, 4), "north_m": round(q.north_m, 4)},
            "radius_m": q.radius_m,
            "heading_deg": None if q.heading_rad is None else round(float(np.degrees(q.heading_rad)), 6),
            "fov_deg": None if q.fov_rad is None else round(float(np.degrees(q.fov_rad)), 6),
            "corners": corners, "marking_window": marking,
            "localizability": q.localizability.to_pylist()}


def reader_latlon(reader: "MapReader", east_m: float, north_m: float) -> tuple[float, float]:
    from stages.common.geodesy import enu_to_geodetic

    ll = enu_to_geodetic(np.array([[east_m, north_m, 0.0]]), reader.origin)[0]
    return float(ll[0]), float(ll[1])


def cells_of(table: pa.Table, method: str) -> pa.Table:
    return table.filter(pc.equal(table["method"], method)) if table.num_rows else table
