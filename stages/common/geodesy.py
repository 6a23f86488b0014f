"""Geodetic <-> local ENU (pymap3d, WGS84, float64) and projected CRS -> geodetic (pyproj).

The map's ENU origin is an ``EnuOrigin`` (lat_deg, lon_deg, h_m on WGS84) written in every manifest.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

# The one "same frame" rule: two origins within these are one local ENU frame (1e-9 deg is ~0.1 mm on the ground).
# A map's pinned origin against --origin, a trajectory's header against its sidecar, a version against its parent.
ORIGIN_TOL_DEG = 1e-9
ORIGIN_TOL_M = 1e-3
LAT_RANGE_DEG = (-90.0, 90.0)
LON_RANGE_DEG = (-180.0, 180.0)
H_RANGE_M = (-1000.0, 10000.0)  # metres above the WGS84 ellipsoid


class OriginError(ValueError):
    """An ENU origin that does not parse or lies outside the ranges; ``problems``: one line each."""

    def __init__(self, problems: list[str]):
        self.problems = list(problems)
        super().__init__("; ".join(self.problems))


@dataclass(frozen=True)
class EnuOrigin:
    """The map's local ENU frame: its origin on the WGS84 ellipsoid (degrees, degrees, metres). Parsed from
    ``LAT,LON,H`` (``parse``) or a mapping (``validate``, ``from_dict``), written with ``as_dict`` (manifests) or
    ``plain`` (a map's identity, a workflow); ``same_frame`` is the one tolerance every comparison uses."""

    lat_deg: float
    lon_deg: float
    h_m: float

    def as_dict(self) -> dict[str, float]:
        return {"lat_deg": self.lat_deg, "lon_deg": self.lon_deg, "h_m": self.h_m, "ellipsoid": "WGS84"}

    def plain(self) -> dict[str, float]:
        """``{lat_deg, lon_deg, h_m}`` (a map's identity, a workflow's ``enu_origin``: WGS84 implied)."""
        return {"lat_deg": self.lat_deg, "lon_deg": self.lon_deg, "h_m": self.h_m}

    @classmethod
    def from_dict(cls, d: dict) -> "EnuOrigin":
        """A manifest's or a trusted document's ``enu_origin`` (no range check: ``validate`` checks input)."""
        return cls(float(d["lat_deg"]), float(d["lon_deg"]), float(d["h_m"]))

    @staticmethod
    def problems(lat_deg: float, lon_deg: float, h_m: float) -> list[str]:
        """What is wrong with these numbers as an origin (empty when nothing is)."""
        out = []
        if not (math.isfinite(lat_deg) and LAT_RANGE_DEG[0] <= lat_deg <= LAT_RANGE_DEG[1]):
            out.append(f"latitude {lat_deg} is outside -90..90 degrees")
        if not (math.isfinite(lon_deg) and LON_RANGE_DEG[0] <= lon_deg <= LON_RANGE_DEG[1]):
            out.append(f"longitude {lon_deg} is outside -180..180 degrees")
        if not (math.isfinite(h_m) and H_RANGE_M[0] <= h_m <= H_RANGE_M[1]):
            out.append(f"height {h_m} m is outside -1000..10000 m")
        return out

    @classmethod
    def parse(cls, text: str) -> "EnuOrigin":
        """``LAT,LON,H`` (degrees, degrees, metres above the WGS84 ellipsoid); OriginError naming every problem."""
        try:
            lat, lon, h = (float(p.strip()) for p in str(text).split(","))
        except ValueError:
            raise OriginError([f"expected LAT,LON,H (three numbers: degrees, degrees, metres), got {text!r}"]) from None
        return cls._checked(lat, lon, h)

    @classmethod
    def validate(cls, doc: object) -> "EnuOrigin":
        """A mapping ``{lat_deg, lon_deg, h_m (default 0), ellipsoid (WGS84 only, optional)}`` from input (a
        workflow, a map's identity); OriginError naming every problem (a missing or unknown key, a non-number, a
        value out of range)."""
        if isinstance(doc, EnuOrigin):
            return cls._checked(doc.lat_deg, doc.lon_deg, doc.h_m)
        if not isinstance(doc, dict):
            raise OriginError([f"expected a mapping {{lat_deg, lon_deg, h_m}}, got {type(doc).__name__}"])
        problems = [f"unknown key {k!r} (expected lat_deg, lon_deg, h_m)" for k in doc
                    if k not in ("lat_deg", "lon_deg", "h_m", "ellipsoid")]
        if doc.get("ellipsoid", "WGS84") != "WGS84":
            problems.append(f"ellipsoid {doc['ellipsoid']!r}; only WGS84 is supported")
        values = {}
        for key in ("lat_deg", "lon_deg", "h_m"):
            if key not in doc and key != "h_m":
                problems.append(f"{key}: missing")
                continue
            value = doc.get(key, 0.0)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                problems.append(f"{key}: expected a number, got {value!r}")
                continue
            values[key] = float(value)
        if len(values) == 3:
            problems += cls.problems(values["lat_deg"], values["lon_deg"], values["h_m"])
        if problems:
            raise OriginError(problems)
        return cls(values["lat_deg"], values["lon_deg"], values["h_m"])

    @classmethod
    def _checked(cls, lat_deg: float, lon_deg: float, h_m: float) -> "EnuOrigin":
        problems = cls.problems(lat_deg, lon_deg, h_m)
        if problems:
            raise OriginError(problems)
        return cls(float(lat_deg), float(lon_deg), float(h_m))

    def same_frame(self, other: "EnuOrigin") -> bool:
        """The same local ENU frame: latitudes and longitudes within ``ORIGIN_TOL_DEG``, heights within
        ``ORIGIN_TOL_M``."""
        return (abs(self.lat_deg - other.lat_deg) <= ORIGIN_TOL_DEG
                and abs(self.lon_deg - other.lon_deg) <= ORIGIN_TOL_DEG and abs(self.h_m - other.h_m) <= ORIGIN_TOL_M)

    def text(self) -> str:
        """``LAT,LON,H`` with 9, 9 and 3 decimals (what ``parse`` reads back)."""
        return f"{self.lat_deg:.9f},{self.lon_deg:.9f},{self.h_m:.3f}"


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
