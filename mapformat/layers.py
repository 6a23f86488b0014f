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
import os
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
    "localizability_ekf": ("float32", float("nan"), "localizability_ekf: predicted sigma_2d of the corner EKF, m"),
    "localizability_mcl": ("float32", float("nan"), "localizability_mcl: predicted sigma_2d of the marking MCL, m"),
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


MAX_TILE_PIXELS = 1 << 26  # 64 Mi pixels (128 MiB at 16 bits): a 100 m tile at 0.1 m is 1 Mi; 819 m at 0.1 m fits
MAX_PNG_BYTES = 1 << 28  # a layer file larger than this is refused before it is read
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_header(data: bytes, where: Path) -> tuple[int, int, int, int]:
    """(width, height, bit depth, colour type) from a PNG's IHDR, without decoding; MapFormatError if not a PNG."""
    if len(data) < 26 or data[:8] != _PNG_SIGNATURE or data[12:16] != b"IHDR":
        raise MapFormatError(f"{where}: not a PNG (no PNG signature and IHDR chunk); hint: run `cornermap tiles "
                             "verify`")
    return (int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big"), data[24], data[25])


def expected_shape(marking_meta: dict[str, Any]) -> tuple[int, int] | None:
    """(height, width) in pixels the manifest records for a tile's rasters (``height_px``, ``width_px``), if any."""
    try:
        h, w = int(marking_meta["height_px"]), int(marking_meta["width_px"])
    except (KeyError, TypeError, ValueError):
        return None
    return (h, w) if h > 0 and w > 0 else None


def decode_png(data: bytes, where: Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """PNG bytes -> pixels (``cv2.IMREAD_UNCHANGED``), decoded only after its header passed the bounds: the size the
    manifest records (``shape`` = (height, width)), at most ``MAX_TILE_PIXELS`` pixels, 8 or 16 bits, at most 4
    channels. A header that promises more (a decompression bomb: 30000 x 30000 from a few kB) is a MapFormatError."""
    import cv2

    width, height, depth, colour = png_header(data, where)
    channels = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}.get(colour)
    if shape is not None and (height, width) != tuple(shape):
        raise MapFormatError(f"{where}: PNG of {width} x {height} pixels; the manifest records {shape[1]} x {shape[0]}"
                             " for this tile; hint: run `cornermap tiles verify`")
    if width * height > MAX_TILE_PIXELS or depth not in (1, 2, 4, 8, 16) or channels is None:
        raise MapFormatError(f"{where}: PNG of {width} x {height} pixels, {depth} bits, colour type {colour}: beyond "
                             f"the limits of a tile raster ({MAX_TILE_PIXELS} pixels, 8 or 16 bits, 1-4 channels)")
    pixels = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if pixels is None or pixels.shape[:2] != (height, width):
        raise MapFormatError(f"{where}: not a decodable PNG; hint: run `cornermap tiles verify`")
    return pixels


def read_bounded(path: Path, limit: int = MAX_PNG_BYTES) -> bytes:
    """A file's bytes, refused (MapFormatError) when it is larger than ``limit`` or cannot be read."""
    try:
        with open(path, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            if size > limit:
                raise MapFormatError(f"{path}: {size} bytes, more than the {limit}-byte limit of a tile raster")
            return fh.read()
    except OSError as exc:
        raise MapFormatError(f"{path}: missing or unreadable ({exc.strerror or exc}); hint: run `cornermap tiles "
                             "verify`") from exc


def read_layer(tile_dir: Path, marking_meta: dict[str, Any], layer: str, data: bytes | None = None) -> np.ndarray:
    """Decoded layer ``layer`` of a published tile (row 0 = north edge), from ``data`` (its file's bytes, already
    verified by the caller) or read from the tile folder; bounded by ``decode_png``. MapFormatError when absent."""
    layers = sidecar_layers(tile_dir, marking_meta)
    if layer not in layers:
        raise MapFormatError(f"{tile_dir}: no raster layer {layer!r}; have {', '.join(sorted(layers)) or 'none'}")
    path = Path(tile_dir) / layers[layer]["file"]
    pixels = decode_png(read_bounded(path) if data is None else data, path, expected_shape(marking_meta))
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
