"""Raster layers of a published tile, decoded, and their Cloud-Optimized GeoTIFF export.

A tile's ``raster.json`` sidecar (written by the markings stage) lists every layer with its PNG file and coding:
8-bit masks (255 = yes), 16-bit values ``offset + (pixel - 1) * scale`` with 0 = no data, 16-bit point counts.
``decode_layer`` turns the PNG pixels into the layer's values (float64 with NaN = no data for coded layers).

GeoTIFF CRS: a transverse Mercator centred on the map's ENU origin (no false easting/northing, WGS84, scale
factor putting it at the origin's height). At the origin its x/y axes are east/north with the ENU plane's scale,
so the ENU raster lattice is written as-is (an affine north-up transform, no resampling); TM and the ENU tangent
plane part by 0.02 mm at 1 km from the origin, 0.4 mm at 3 km, 16 mm at 10 km (pyproj; tested at 1 km).
In a UTM zone the ENU grid would be rotated by the meridian convergence
(~1 deg at 127 E 37.5 N, 0.1 deg from the central meridian) and scaled by 0.9996..1.0004, so the raster would
have to be resampled.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import MapFormatError

MASK_LAYERS = ("marking_mask", "traversable_mask")
#: layer -> (GeoTIFF dtype, nodata, band description)
LAYER_BANDS: dict[str, tuple[str, float | None, str]] = {
    "marking_mask": ("uint8", None, "marking_mask: 255 = road marking, 0 = not"),
    "traversable_mask": ("uint8", None, "traversable_mask: 255 = traversable, 0 = not"),
    "intensity": ("float32", float("nan"), "intensity: mean LiDAR intensity, raw sensor units"),
    "elevation_min": ("float32", float("nan"), "elevation_min: lowest point up, m (map ENU)"),
    "elevation_mean": ("float32", float("nan"), "elevation_mean: mean point up, m (map ENU)"),
    "point_count": ("uint16", 0, "point_count: points per cell (saturates at 65535), 0 = no data"),
}


def local_tm_proj4(origin: dict[str, float]) -> str:
    """PROJ string of the transverse Mercator centred on ``origin`` (lat_deg, lon_deg, h_m), metres, WGS84.

    The scale factor is (R + h) / R with R the Gaussian radius of curvature at the origin, so that the projection
    is at the origin's height like the ENU plane (k = 1 would shrink ENU distances by h / R: 6 mm per km at 38 m).
    """
    a, f = 6378137.0, 1.0 / 298.257223563
    e2 = f * (2.0 - f)
    s2 = np.sin(np.radians(float(origin["lat_deg"]))) ** 2
    radius_m = a * np.sqrt(1.0 - e2) / (1.0 - e2 * s2)  # sqrt(M N)
    k = 1.0 + float(origin.get("h_m", 0.0)) / radius_m
    return (f"+proj=tmerc +lat_0={float(origin['lat_deg']):.10f} +lon_0={float(origin['lon_deg']):.10f} "
            f"+k_0={k:.12f} +x_0=0 +y_0=0 +ellps=WGS84 +units=m +no_defs +type=crs")


def sidecar_layers(tile_dir: Path, marking_meta: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """layer name -> its sidecar entry ({file, dtype, scale, offset, ...}); only the mask without a full sidecar."""
    path = Path(tile_dir) / "raster.json"
    layers: dict[str, dict[str, Any]] = {}
    if path.is_file():
        try:
            doc = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise MapFormatError(
                f"{path}: unreadable raster sidecar ({exc}); hint: run `cornermap tiles verify`"
            ) from exc
        layers = {k: v for k, v in (doc.get("layers") or {}).items() if (Path(tile_dir) / v.get("file", "")).is_file()}
    mask_file = marking_meta.get("mask_file")
    if mask_file:
        layers["marking_mask"] = {**layers.get("marking_mask", {}), "file": mask_file, "dtype": "uint8"}
    return layers


def decode_layer(pixels: np.ndarray, entry: dict[str, Any]) -> np.ndarray:
    """PNG pixels -> values: masks and counts unchanged, coded 16-bit layers float64 with NaN = no data."""
    if pixels.ndim == 3:
        pixels = pixels[..., 0]
    if "scale" in entry and "offset" in entry:
        return np.where(pixels > 0, float(entry["offset"]) + (pixels.astype(np.float64) - 1.0) * float(entry["scale"]),
                        np.nan)
    return pixels


def read_layer(tile_dir: Path, marking_meta: dict[str, Any], layer: str) -> np.ndarray:
    """Decoded layer ``layer`` of a published tile (row 0 = north edge). Raises MapFormatError when absent."""
    import cv2

    layers = sidecar_layers(tile_dir, marking_meta)
    if layer not in layers:
        raise MapFormatError(f"{tile_dir}: no raster layer {layer!r}; have {', '.join(sorted(layers)) or 'none'}")
    path = Path(tile_dir) / layers[layer]["file"]
    pixels = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if pixels is None:
        raise MapFormatError(f"{path}: missing or not a PNG; hint: run `cornermap tiles verify`")
    return decode_layer(pixels, layers[layer])


def write_cog(path: Path, values: np.ndarray, west_m: float, north_m: float, cell_m: float, crs: str,
              layer: str, tags: dict[str, str] | None = None) -> Path:
    """One band Cloud-Optimized GeoTIFF (deflate, internal tiles, overviews) of ``values`` (row 0 = north)."""
    import rasterio
    from affine import Affine
    from rasterio.io import MemoryFile
    from rasterio.shutil import copy as rio_copy

    dtype, nodata, description = LAYER_BANDS.get(layer, (str(values.dtype), None, layer))
    data = np.asarray(values).astype(dtype)
    profile = {
        "driver": "GTiff",
        "width": data.shape[1],
        "height": data.shape[0],
        "count": 1,
        "dtype": dtype,
        "crs": rasterio.crs.CRS.from_string(crs),
        "transform": Affine(cell_m, 0.0, west_m, 0.0, -cell_m, north_m),
        "nodata": nodata,
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    with MemoryFile() as mem:
        with mem.open(**profile) as ds:
            ds.write(data, 1)
            ds.set_band_description(1, description)
            ds.update_tags(**(tags or {}))
            ds.update_tags(1, layer=layer)
        with mem.open() as src:
            rio_copy(src, str(tmp), driver="COG", compress="DEFLATE", overview_resampling="nearest")
    tmp.replace(path)
    return path
