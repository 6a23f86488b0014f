"""``tiles export --format geotiff``: every raster layer of every tile as a Cloud-Optimized GeoTIFF, and one GDAL
VRT per layer mosaicking its tiles.

    OUT/{layer}/{i}_{j}.tif    one COG per tile and layer (mapformat.layers.write_cog)
    OUT/{layer}.vrt            the layer's tiles as one raster (GDAL VRT XML, sources relative to the VRT)

CRS: a transverse Mercator centred on the map's ENU origin on the WGS 84 datum (EPSG:4326's), written as WKT2 with
the base CRS "WGS 84" by name, so GDAL names the datum ("World Geodetic System 1984"), not "unknown based on the
WGS 84 ellipsoid"; easting / northing in metres; false easting and northing 0; scale factor (R + h0) / R with R
the Gaussian radius of curvature at the origin and h0 its height, so that near the origin the projection has the
ENU plane's scale. Its axes are east and north at the origin, so the ENU raster lattice is written as it is
(north-up affine transform, no resampling, pixel edges on the tile bounds); TM and ENU part by 0.02 mm at 1 km
from the origin, 0.4 mm at 3 km, 16 mm at 10 km (pyproj). A UTM zone would fit the GeoTIFF contract as well, but
there the ENU grid is rotated by the meridian convergence (about 1 deg at 127.03 E, 37.50 N in zone 52) and
scaled by 0.9996-1.0004, so every raster would have to be resampled.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING, Callable
from xml.sax.saxutils import escape, quoteattr

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from mapformat.loader import MapReader

log = logging.getLogger(__name__)
GDAL_TYPES = {"uint8": "Byte", "uint16": "UInt16", "float32": "Float32", "float64": "Float64"}


def local_tm_scale(origin: dict[str, float]) -> float:
    """(R + h) / R, R = sqrt(M N) the Gaussian radius of curvature at the origin's latitude (WGS 84)."""
    a, f = 6378137.0, 1.0 / 298.257223563
    e2 = f * (2.0 - f)
    s2 = np.sin(np.radians(float(origin["lat_deg"]))) ** 2
    return 1.0 + float(origin.get("h_m", 0.0)) / (a * np.sqrt(1.0 - e2) / (1.0 - e2 * s2))


def local_tm_crs(origin: dict[str, float]):
    """pyproj ``ProjectedCRS``: the map's local transverse Mercator on EPSG:4326's datum (module docstring)."""
    from pyproj import CRS
    from pyproj.crs import ProjectedCRS
    from pyproj.crs.coordinate_operation import TransverseMercatorConversion

    lat, lon, h = float(origin["lat_deg"]), float(origin["lon_deg"]), float(origin.get("h_m", 0.0))
    conv = TransverseMercatorConversion(latitude_natural_origin=lat, longitude_natural_origin=lon, false_easting=0.0,
                                        false_northing=0.0, scale_factor_natural_origin=local_tm_scale(origin))
    return ProjectedCRS(conversion=conv, geodetic_crs=CRS.from_epsg(4326),
                        name=f"cornermap local TM at {lat:.9f} N {lon:.9f} E h {h:.3f} m (map ENU origin)")


def local_tm_wkt(origin: dict[str, float]) -> str:
    """WKT2 (2019) of ``local_tm_crs``."""
    return local_tm_crs(origin).to_wkt()


def layer_vrt(layer: str, tiles: list[tuple[str, int, int, float, float]], cell_m: float, wkt: str, dtype: str,
              nodata: float | None, description: str, tags: dict[str, str]) -> str:
    """GDAL VRT XML mosaicking a layer's tiles: (relative file, width_px, height_px, west_m, north_m) each, north-up,
    all with the same ``cell_m``."""
    west = min(t[3] for t in tiles)
    north = max(t[4] for t in tiles)
    east = max(t[3] + t[1] * cell_m for t in tiles)
    south = min(t[4] - t[2] * cell_m for t in tiles)
    width, height = int(round((east - west) / cell_m)), int(round((north - south) / cell_m))
    gdal_type = GDAL_TYPES[dtype]
    sources = []
    for rel, w, h, tw, tn in tiles:
        x_off, y_off = int(round((tw - west) / cell_m)), int(round((north - tn) / cell_m))
        sources.append(
            f"    <SimpleSource>\n      <SourceFilename relativeToVRT=\"1\">{escape(rel)}</SourceFilename>\n"
            f"      <SourceBand>1</SourceBand>\n"
            f"      <SourceProperties RasterXSize=\"{w}\" RasterYSize=\"{h}\" DataType=\"{gdal_type}\"/>\n"
            f"      <SrcRect xOff=\"0\" yOff=\"0\" xSize=\"{w}\" ySize=\"{h}\"/>\n"
            f"      <DstRect xOff=\"{x_off}\" yOff=\"{y_off}\" xSize=\"{w}\" ySize=\"{h}\"/>\n    </SimpleSource>")
    nd = "" if nodata is None else "nan" if np.isnan(nodata) else repr(float(nodata))
    nd = f"    <NoDataValue>{nd}</NoDataValue>\n" if nd else ""
    meta = "".join(f"    <MDI key={quoteattr(k)}>{escape(v)}</MDI>\n" for k, v in sorted(tags.items()))
    return (f"<VRTDataset rasterXSize=\"{width}\" rasterYSize=\"{height}\">\n"
            f"  <SRS dataAxisToSRSAxisMapping=\"1,2\">{escape(wkt)}</SRS>\n"
            f"  <GeoTransform>{west!r}, {cell_m!r}, 0.0, {north!r}, 0.0, {-cell_m!r}</GeoTransform>\n"
            f"  <Metadata>\n{meta}  </Metadata>\n"
            f"  <VRTRasterBand dataType=\"{gdal_type}\" band=\"1\">\n{nd}"
            f"    <Description>{escape(description)}</Description>\n"
            + "\n".join(sources) + "\n  </VRTRasterBand>\n</VRTDataset>\n")


def export_geotiffs(reader: "MapReader", out: Path, write: Callable[[Path, bytes], None]) -> list[Path]:
    """Every raster layer of every tile as a COG ``out/{layer}/{i}_{j}.tif``, and ``out/{layer}.vrt`` per layer."""
    from mapformat.layers import LAYER_BANDS, sidecar_layers, write_cog
    from pipeline.progress import report

    wkt = local_tm_wkt(reader.manifest["enu_origin"])
    tags = {"cornermap_map": str(reader.manifest.get("map_name")), "cornermap_version": str(reader.version),
            "cornermap_enu_origin": json.dumps(reader.manifest["enu_origin"])}
    files: list[Path] = []
    by_layer: dict[str, list[tuple[str, int, int, float, float, float]]] = {}
    keys = reader.tile_keys()
    for n, (i, j) in enumerate(keys):
        report("geotiff", n, len(keys), step="tiles")
        meta = reader.tile_entry(i, j).get("marking")
        if not meta:
            continue
        cell = float(meta["cell_m"])
        for layer in sorted(sidecar_layers(reader.path / reader.tile_entry(i, j)["dir"], meta)):
            values = reader.tile_layer(i, j, layer)
            west, north = float(meta["origin_east_m"]), float(meta["origin_north_m"]) + values.shape[0] * cell
            files.append(write_cog(Path(out) / layer / f"{i}_{j}.tif", values, west, north, cell, wkt, layer, tags))
            by_layer.setdefault(layer, []).append((f"{layer}/{i}_{j}.tif", values.shape[1], values.shape[0], west,
                                                   north, cell))
    _localizability_layers(reader, out, wkt, tags, files, by_layer)
    for layer, tiles in sorted(by_layer.items()):
        cells = {t[5] for t in tiles}
        if len(cells) != 1:
            log.warning("geotiff: layer %s has tiles of %d cell sizes (%s m); no VRT written", layer, len(cells),
                        sorted(cells))
            continue
        dtype, nodata, description = LAYER_BANDS.get(layer, ("float32", float("nan"), layer))
        path = Path(out) / f"{layer}.vrt"
        write(path, layer_vrt(layer, [t[:5] for t in tiles], cells.pop(), wkt, dtype, nodata, description,
                              tags).encode("utf-8"))
        files.append(path)
    return files


def _localizability_layers(reader: "MapReader", out: Path, wkt: str, tags: dict[str, str], files: list[Path],
                           by_layer: dict[str, list]) -> None:
    """The localizability layer's sigma_2d per method as ``OUT/localizability_{method}/{i}_{j}.tif`` (one pixel per
    cell, NaN where the drives did not pass), with the raster layers' CRS and a VRT each."""
    from mapformat.layers import write_cog
    from mapformat.localizability import rasterize

    cell = (reader.manifest.get("localizability") or {}).get("cell_m")
    for i, j in reader.tile_keys():
        table = reader.tile_localizability(i, j)
        if table is None or not cell:
            continue
        bounds = tuple(float(b) for b in reader.tile_entry(i, j)["bounds_m"])
        for method in ("ekf", "mcl"):
            layer = f"localizability_{method}"
            values = rasterize(table, method, bounds, float(cell))
            files.append(write_cog(Path(out) / layer / f"{i}_{j}.tif", values, bounds[0], bounds[3], float(cell), wkt,
                                   layer, tags))
            by_layer.setdefault(layer, []).append((f"{layer}/{i}_{j}.tif", values.shape[1], values.shape[0],
                                                   bounds[0], bounds[3], float(cell)))
