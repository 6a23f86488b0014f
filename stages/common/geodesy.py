"""Geodetic <-> local ENU (pymap3d, WGS84, float64) and projected CRS -> geodetic (pyproj).

The map's ENU origin is an ``EnuOrigin`` (lat_deg, lon_deg, h_m on WGS84) written in every manifest.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np


@dataclass(frozen=True)
class EnuOrigin:
    lat_deg: float
    lon_deg: float
    h_m: float

    def as_dict(self) -> dict[str, float]:
        return {"lat_deg": self.lat_deg, "lon_deg": self.lon_deg, "h_m": self.h_m, "ellipsoid": "WGS84"}

    @classmethod
    def from_dict(cls, d: dict) -> "EnuOrigin":
        return cls(float(d["lat_deg"]), float(d["lon_deg"]), float(d["h_m"]))


def geodetic_to_enu(lat_deg, lon_deg, h_m, origin: EnuOrigin) -> np.ndarray:
    """(N,) arrays -> (N,3) east/north/up metres about ``origin``."""
    import pymap3d

    e, n, u = pymap3d.geodetic2enu(np.asarray(lat_deg, float), np.asarray(lon_deg, float), np.asarray(h_m, float),
                                   origin.lat_deg, origin.lon_deg, origin.h_m, deg=True)
    return np.column_stack([np.atleast_1d(e), np.atleast_1d(n), np.atleast_1d(u)])


def enu_to_geodetic(enu_m: np.ndarray, origin: EnuOrigin) -> np.ndarray:
    """(N,3) east/north/up -> (N,3) lat_deg, lon_deg, h_m."""
    import pymap3d

    enu_m = np.atleast_2d(np.asarray(enu_m, float))
    lat, lon, h = pymap3d.enu2geodetic(enu_m[:, 0], enu_m[:, 1], enu_m[:, 2],
                                       origin.lat_deg, origin.lon_deg, origin.h_m, deg=True)
    return np.column_stack([np.atleast_1d(lat), np.atleast_1d(lon), np.atleast_1d(h)])


def utm_epsg_for(lat_deg: float, lon_deg: float) -> int:
    """EPSG code of the WGS84 UTM zone holding a point (326xx north, 327xx south)."""
    zone = int((lon_deg + 180.0) // 6.0) % 60 + 1
    return (32600 if lat_deg >= 0 else 32700) + zone


@lru_cache(maxsize=32)
def _transformer(src: str, dst: str):
    from pyproj import Transformer

    return Transformer.from_crs(src, dst, always_xy=True)


def projected_to_geodetic(x: np.ndarray, y: np.ndarray, z: np.ndarray, crs: str) -> np.ndarray:
    """Points in a projected CRS (e.g. 'EPSG:32652', 'EPSG:28992') -> (N,3) lat_deg, lon_deg, h_m.

    Heights are passed through unchanged (a vertical datum shift such as NAP -> ellipsoid is not applied
    unless the CRS is a 3D/compound one that pyproj can transform).
    """
    lon, lat, h = _transformer(crs, "EPSG:4979").transform(np.asarray(x, float), np.asarray(y, float),
                                                          np.asarray(z, float))
    return np.column_stack([lat, lon, h])


def geodetic_to_projected(lat_deg, lon_deg, h_m, crs: str) -> np.ndarray:
    x, y, z = _transformer("EPSG:4979", crs).transform(np.asarray(lon_deg, float), np.asarray(lat_deg, float),
                                                      np.asarray(h_m, float))
    return np.column_stack([x, y, z])
