"""Per-tile marking rasters on disk: lossless PNGs plus one JSON sidecar, readable without this package.

Layout of one tile directory (see docs/markings.md for the full format):
    raster.json            sidecar: format, georeference (south-west origin, cell, size, frame), layers
    marking_mask.png       8-bit, 255 = road marking, 0 = not
    traversable_mask.png   8-bit, 255 = traversable
    intensity.png          16-bit, raw intensity = offset + (pixel - 1) * scale, 0 = no data
    elevation_min.png      16-bit, minimum up (m) = offset + (pixel - 1) * scale, 0 = no data
    elevation_mean.png     16-bit, mean up (m), same coding
    point_count.png        16-bit, points per cell (saturates at 65535)
Row 0 is the NORTH edge, column 0 the WEST edge. Every file is written to a temporary name then renamed;
the sidecar is written last.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from pipeline.errors import DatasetIOError, FormatError, MapFormatError

FORMAT = "cornermap.marking_raster"
FORMAT_VERSION = 1
SIDECAR = "raster.json"
_U16_LEVELS = 65534  # pixel values 1..65535 carry data; 0 is no data
_MIN_HEIGHT_SCALE_M = 0.001


@dataclass
class TileRasters:
    """Decoded rasters of one tile, all (height_px, width_px), row 0 = north."""

    marking_mask: np.ndarray  # bool
    traversable_mask: np.ndarray  # bool
    intensity: np.ndarray  # float64 raw units, NaN = no data
    min_up_m: np.ndarray  # float64, NaN = no data
    mean_up_m: np.ndarray  # float64, NaN = no data
    count: np.ndarray  # int64
    origin_east_m: float  # south-west corner, ENU
    origin_north_m: float
    cell_m: float
    meta: dict[str, Any] = field(default_factory=dict)  # tile_i, tile_j, source, enu_origin, params, ...


def _encode_u16(values: np.ndarray, min_scale: float) -> tuple[np.ndarray, float, float]:
    """float array (NaN = no data) -> uint16 with 0 = no data; returns (pixels, scale, offset)."""
    finite = np.isfinite(values)
    if not finite.any():
        return np.zeros(values.shape, np.uint16), 1.0, 0.0
    lo, hi = float(values[finite].min()), float(values[finite].max())
    scale = max(min_scale, (hi - lo) / _U16_LEVELS) if hi > lo else max(min_scale, 1e-12)
    pixels = np.zeros(values.shape, np.uint16)
    pixels[finite] = (np.round((values[finite] - lo) / scale) + 1).clip(1, 65535).astype(np.uint16)
    return pixels, scale, lo


def _decode_u16(pixels: np.ndarray, scale: float, offset: float) -> np.ndarray:
    return np.where(pixels > 0, offset + (pixels.astype(np.float64) - 1.0) * scale, np.nan)


def _write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    except OSError as exc:
        raise DatasetIOError(f"could not write {path}: {exc}; hint: check free space and permissions") from exc


def _write_png(path: Path, pixels: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", pixels)
    if not ok:
        raise DatasetIOError(f"OpenCV could not encode {path.name} ({pixels.dtype}, {pixels.shape})")
    _write_atomic(path, buf.tobytes())


def write_tile_rasters(directory: Path, rasters: TileRasters) -> Path:
    """Write the PNGs and the sidecar of one tile into ``directory``; returns the sidecar path."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    height, width = rasters.marking_mask.shape
    layers: dict[str, dict[str, Any]] = {}
    for name, mask, meaning in (("marking_mask", rasters.marking_mask, "255 = road marking, 0 = not"),
                                ("traversable_mask", rasters.traversable_mask, "255 = traversable, 0 = not")):
        _write_png(directory / f"{name}.png", np.where(mask, 255, 0).astype(np.uint8))
        layers[name] = {"file": f"{name}.png", "dtype": "uint8", "meaning": meaning, "nodata": None}
    for name, values, units, min_scale in (("intensity", rasters.intensity, "raw", 1e-9),
                                           ("elevation_min", rasters.min_up_m, "m", _MIN_HEIGHT_SCALE_M),
                                           ("elevation_mean", rasters.mean_up_m, "m", _MIN_HEIGHT_SCALE_M)):
        pixels, scale, offset = _encode_u16(np.asarray(values, float), min_scale)
        _write_png(directory / f"{name}.png", pixels)
        layers[name] = {"file": f"{name}.png", "dtype": "uint16", "units": units, "nodata": 0,
                        "scale": scale, "offset": offset,
                        "decode": "value = offset + (pixel - 1) * scale where pixel != 0"}
    _write_png(directory / "point_count.png", np.clip(rasters.count, 0, 65535).astype(np.uint16))
    layers["point_count"] = {"file": "point_count.png", "dtype": "uint16", "units": "points", "nodata": None,
                             "meaning": "points per cell, saturating at 65535"}
    sidecar = {
        "format": FORMAT, "format_version": FORMAT_VERSION, "frame": "enu",
        "origin_east_m": rasters.origin_east_m, "origin_north_m": rasters.origin_north_m,
        "origin_corner": "south_west", "cell_m": rasters.cell_m, "width_px": width, "height_px": height,
        "row_order": "row 0 = north edge", "col_order": "col 0 = west edge",
        "pixel_center": "east = origin_east_m + (col + 0.5) * cell_m; "
                        "north = origin_north_m + (height_px - row - 0.5) * cell_m",
        "layers": layers, **rasters.meta,
    }
    path = directory / SIDECAR
    _write_atomic(path, json.dumps(sidecar, indent=1, sort_keys=True).encode())
    return path


def _read_png(path: Path, dtype: str, shape: tuple[int, int]) -> np.ndarray:
    if not path.is_file():
        raise DatasetIOError(f"marking raster {path} is missing; hint: the tile directory is incomplete, "
                             "rebuild the markings stage")
    pixels = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if pixels is None:
        raise FormatError(f"{path} is not a readable PNG")
    if pixels.dtype != np.dtype(dtype) or pixels.shape != shape:
        raise FormatError(f"{path}: expected {dtype} {shape}, got {pixels.dtype} {pixels.shape}")
    return pixels


def read_tile_rasters(directory: Path) -> TileRasters:
    """Read and decode one tile written by ``write_tile_rasters``."""
    directory = Path(directory)
    path = directory / SIDECAR
    try:
        sidecar = json.loads(path.read_text())
    except FileNotFoundError as exc:
        raise DatasetIOError(f"no {SIDECAR} in {directory}; hint: not a marking-raster tile directory") from exc
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise FormatError(f"{path} is not valid JSON: {exc}") from exc
    if not isinstance(sidecar, dict) or sidecar.get("format") != FORMAT:
        got = sidecar.get("format") if isinstance(sidecar, dict) else type(sidecar).__name__
        raise FormatError(f"{path}: expected format {FORMAT!r}, got {got!r}")
    if sidecar.get("format_version") != FORMAT_VERSION:
        raise MapFormatError(f"{path}: format_version {sidecar.get('format_version')!r} is not understood "
                             f"(this code reads {FORMAT_VERSION}); hint: upgrade cornermap")
    try:
        shape = (int(sidecar["height_px"]), int(sidecar["width_px"]))
        layers = sidecar["layers"]
        cell_m = float(sidecar["cell_m"])
        origin = float(sidecar["origin_east_m"]), float(sidecar["origin_north_m"])
        lay = {name: _read_png(directory / layers[name]["file"], layers[name]["dtype"], shape)
               for name in ("marking_mask", "traversable_mask", "intensity", "elevation_min", "elevation_mean",
                            "point_count")}
        decoded = {name: _decode_u16(lay[name], float(layers[name]["scale"]), float(layers[name]["offset"]))
                   for name in ("intensity", "elevation_min", "elevation_mean")}
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, FormatError):
            raise
        raise FormatError(f"{path}: missing or malformed entry {exc}; expected the keys written by "
                          "write_tile_rasters (height_px, width_px, cell_m, origin_*, layers)") from exc
    known = {"format", "format_version", "frame", "origin_east_m", "origin_north_m", "origin_corner", "cell_m",
             "width_px", "height_px", "row_order", "col_order", "pixel_center", "layers"}
    return TileRasters(
        marking_mask=lay["marking_mask"] > 0, traversable_mask=lay["traversable_mask"] > 0,
        intensity=decoded["intensity"], min_up_m=decoded["elevation_min"], mean_up_m=decoded["elevation_mean"],
        count=lay["point_count"].astype(np.int64), origin_east_m=origin[0], origin_north_m=origin[1],
        cell_m=cell_m, meta={k: v for k, v in sidecar.items() if k not in known})
