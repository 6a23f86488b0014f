"""Loader API for localizers: open a published map version and query corners and marking rasters.

    reader = open_map("ROOT/maps/city", version="LATEST")   # or "v0003", 3, or a version directory
    near = reader.corners_within(east_m, north_m, 100.0)       # pa.Table with corner_map columns
    mask, (e0_m, n0_m), cell_m = reader.marking_window(e0, n0, e1, n1)   # row 0 = north edge

The version is pinned when the reader opens (LATEST is read once), so a publish running meanwhile never
mixes two versions under one reader. Tiles load lazily and stay in an LRU cache (``cache_tiles`` each for
corners and for marking rasters). Query boxes are half-open like tiles: [e0, e1) x [n0, n1).

Verified reads: every file is read once into memory, its sha256 compared with the manifest's file table
(``IntegrityError`` otherwise) and only then decoded; a file verified once is not hashed again by this
process while its size, mtime and inode are unchanged. Every path in the manifest is resolved inside the
version directory (``PathEscapeError`` otherwise). Opening ``ROOT/maps/NAME`` also checks the manifest
against the digest recorded outside it (LATEST, then each child's ``parent_manifest_sha256``).
``trust_files=True`` skips the file hashing for trusted local use (paths are still confined).
``marking_window`` refuses windows over MAX_WINDOW_CELLS cells (``LimitError``).
Over 300 lines on purpose: the one reader of published maps keeps its verified reads, caches and size
bounds in one place (docs/security.md), so no path around a check can appear in a second module.
"""
from __future__ import annotations

import hashlib
import os
import threading
from collections import OrderedDict
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from mapformat import layout
from pipeline.errors import IntegrityError, LimitError, MapFormatError, PathEscapeError, UnknownNameError
from pipeline.names import inside
from pipeline.versioned import MANIFEST_NAME, read_manifest, resolve_version, trusted_manifest_digests
from stages.common.geodesy import EnuOrigin
from stages.common.tiling import tile_key_of

MAX_WINDOW_CELLS = 1 << 28  # 256 Mi cells = 256 MiB of uint8: e.g. 16 km x 16 km at 1 m cells
MAX_TILE_CORNERS = 1_000_000  # rows of one tile's corners.parquet (a dense 100 m tile holds a few hundred)
MAX_TILE_TABLE_BYTES = 256 << 20  # one tile's corners once decompressed (footer's row-group sizes)
_VERIFIED: dict[tuple[str, int, int, int], str] = {}  # (path, size, mtime_ns, inode) -> sha256, this process
_VERIFIED_LOCK = threading.Lock()


def read_verified(version_dir: Path, rel: str, files: dict[str, Any], trust: bool = False) -> bytes:
    """Bytes of ``version_dir/rel`` after checking its sha256 against the manifest's file table ``files``."""
    path = inside(version_dir, rel)
    entry = files.get(rel) if isinstance(files, dict) else None
    if not isinstance(entry, dict) or not isinstance(entry.get("sha256"), str):
        raise IntegrityError(f"{path}: not in the manifest's file table; refusing to read an unverified file")
    try:
        with open(path, "rb") as fh:
            st = os.fstat(fh.fileno())
            if isinstance(entry.get("bytes"), int) and st.st_size != entry["bytes"]:
                raise IntegrityError(f"{path}: {st.st_size} bytes, the manifest records {entry['bytes']}; "
                                     "hint: run `cornermap tiles verify`")
            data = fh.read()
    except OSError as exc:
        raise MapFormatError(
            f"{path}: cannot read ({exc.strerror or exc}); hint: run `cornermap tiles verify`"
        ) from exc
    key = (str(path), st.st_size, st.st_mtime_ns, st.st_ino)
    if trust or _VERIFIED.get(key) == entry["sha256"]:
        return data
    got = hashlib.sha256(data).hexdigest()
    if got != entry["sha256"]:
        raise IntegrityError(f"{path}: sha256 {got[:16]}... differs from the manifest's {entry['sha256'][:16]}...; "
                             "the file is corrupt or was altered. hint: run `cornermap tiles verify`")
    with _VERIFIED_LOCK:
        _VERIFIED[key] = got
    return data


def decode_table(data: bytes, path: Path, expected_rows: int | None = None) -> pa.Table:
    """A Parquet file's bytes -> table, decoded only after its footer passed the bounds: ``expected_rows`` when the
    manifest records them, at most MAX_TILE_CORNERS rows and MAX_TILE_TABLE_BYTES decompressed (MapFormatError)."""
    try:
        pfile = pq.ParquetFile(pa.BufferReader(data))
        meta = pfile.metadata
        rows = meta.num_rows
        inflated = sum(meta.row_group(g).total_byte_size for g in range(meta.num_row_groups))
        if (expected_rows is not None and rows != expected_rows) or rows > MAX_TILE_CORNERS \
                or inflated > MAX_TILE_TABLE_BYTES:
            raise MapFormatError(f"{path}: {rows} rows, {inflated} bytes decompressed; the manifest records "
                                 f"{expected_rows} rows for it (limits {MAX_TILE_CORNERS} rows, {MAX_TILE_TABLE_BYTES} "
                                 "bytes); hint: run `cornermap tiles verify`")
        table = pfile.read(use_threads=False)
    except MapFormatError:
        raise
    except (OSError, pa.ArrowInvalid, ValueError) as exc:
        raise MapFormatError(f"{path}: cannot read the table ({exc}); hint: run `cornermap tiles verify`") from exc
    if table.num_rows != rows:
        raise MapFormatError(f"{path}: {table.num_rows} rows read, its footer says {rows}")
    return table


class _Lru:
    def __init__(self, capacity: int, load: Callable[[tuple[int, int]], Any]):
        self._capacity, self._load = max(1, capacity), load
        self._items: OrderedDict[tuple[int, int], Any] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: tuple[int, int]) -> Any:
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
        value = self._load(key)
        with self._lock:
            self._items[key] = value
            while len(self._items) > self._capacity:
                self._items.popitem(last=False)
        return value

    def clear(self) -> None:
        with self._lock:
            self._items.clear()


def check_manifest_format(manifest: dict[str, Any], where: Path) -> None:
    fmt, ver = manifest.get("format"), manifest.get("format_version")
    if fmt != layout.FORMAT_NAME or not isinstance(ver, int) or ver not in layout.SUPPORTED_FORMAT_VERSIONS:
        raise MapFormatError(
            f"{where}: map format {fmt!r} version {ver!r} is not readable by this code (reads {layout.FORMAT_NAME!r} "
            f"versions {sorted(layout.SUPPORTED_FORMAT_VERSIONS)}); hint: upgrade cornermap or open an older version")


def _error_correlation(doc: Any, where: Path) -> tuple[float, float] | None:
    """The map's ``corner_error_correlation`` entry as ``(share, length_m)``: two corners' errors correlate
    ``share * exp(-d^2 / (2 length_m^2))`` at distance d (the pose graph's own figure; docs/map-format.md). None
    when the map states none (maps published before it, or a pose graph that could not compute it)."""
    if doc is None:
        return None
    try:
        share, length = float(doc["share"]), float(doc["length_m"])
    except (KeyError, TypeError, ValueError) as exc:
        raise MapFormatError(f"{where}: corner_error_correlation is malformed ({type(exc).__name__}: {exc}); "
                             "expected share and length_m numbers") from exc
    if not (0.0 <= share < 1.0 and length > 0.0 and np.isfinite(length)):
        raise MapFormatError(f"{where}: corner_error_correlation share {share} / length_m {length}: expected a "
                             "share in [0, 1) and a positive length")
    return share, length


def _map_frame(doc: Any, where: Path) -> dict[str, Any] | None:
    """The map's ``map_frame`` entry: how far the map frame may sit from the true ENU frame (a shift at
    ``reference_en_m`` and a rotation, covariance ``cov_shift_rotation`` 3x3 in m^2, m rad, rad^2), stated once per
    version; the corners' covariances are then relative to the frame (docs/map-format.md). None for maps published
    before it: their corner covariances hold the frame's error too."""
    if doc is None:
        return None
    try:
        ref = np.asarray(doc["reference_en_m"], dtype=float)
        cov = np.asarray(doc["cov_shift_rotation"], dtype=float)
    except (KeyError, TypeError, ValueError) as exc:
        raise MapFormatError(f"{where}: map_frame is malformed ({type(exc).__name__}: {exc}); expected "
                             "reference_en_m [e, n] and cov_shift_rotation 3x3") from exc
    ok = ref.shape == (2,) and cov.shape == (3, 3) and np.all(np.isfinite(ref)) and np.all(np.isfinite(cov))
    if not ok or not np.allclose(cov, cov.T, atol=1e-12) or np.linalg.eigvalsh(cov).min() < -1e-12:
        raise MapFormatError(f"{where}: map_frame reference_en_m {ref.tolist()} / cov_shift_rotation "
                             f"{cov.tolist()}: expected 2 finite numbers and a symmetric positive semi-definite 3x3")
    return {**doc, "reference_en_m": ref, "cov_shift_rotation": cov}


class MapReader:
    """A pinned, read-only view of one map version."""

    def __init__(self, version_dir: Path, cache_tiles: int = 64, *, manifest_sha256: str | None = None,
                 trust_files: bool = False):
        self.path = Path(version_dir)
        self.trust_files = trust_files
        self.manifest, self.manifest_sha256 = read_manifest(self.path)
        if manifest_sha256 is not None and manifest_sha256 != self.manifest_sha256:
            raise IntegrityError(f"{self.path / MANIFEST_NAME}: sha256 {self.manifest_sha256[:16]}... differs from "
                                 f"the digest recorded outside it ({manifest_sha256[:16]}...); the manifest was edited "
                                 "or replaced. hint: run `cornermap tiles verify`")
        check_manifest_format(self.manifest, self.path / MANIFEST_NAME)
        try:
            self.version: int = int(self.manifest["version"])
            self.tile_size_m: float = float(self.manifest["tile_size_m"])
            self.origin = EnuOrigin.from_dict(self.manifest["enu_origin"])
            self._tiles = {(int(t["i"]), int(t["j"])): t for t in self.manifest["tiles"]}
            for t in self._tiles.values():
                inside(self.path, t["dir"])
            cells = {float(t["marking"]["cell_m"]) for t in self._tiles.values() if t.get("marking")}
        except PathEscapeError:
            raise
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise MapFormatError(
                f"{self.path / MANIFEST_NAME}: malformed manifest ({type(exc).__name__}: {exc}); "
                "hint: run `cornermap tiles verify`"
            ) from exc
        if not (self.tile_size_m > 0 and np.isfinite(self.tile_size_m)):
            raise MapFormatError(
                f"{self.path / MANIFEST_NAME}: tile_size_m {self.tile_size_m} is not a positive number"
            )
        if len(cells) > 1:
            raise MapFormatError(f"{self.path}: marking rasters use several cell sizes {sorted(cells)} m")
        self.cell_m: float | None = cells.pop() if cells else None
        self.corner_error_correlation = _error_correlation(self.manifest.get("corner_error_correlation"),
                                                           self.path / MANIFEST_NAME)
        self.map_frame = _map_frame(self.manifest.get("map_frame"), self.path / MANIFEST_NAME)
        self._schema = _corner_schema()
        self._empty = self._schema.empty_table()
        self._corners = _Lru(cache_tiles, self._load_corners)
        self._markings = _Lru(cache_tiles, self._load_marking)
        self._observed = _Lru(cache_tiles, self._load_observed)
        self._localizability = _Lru(cache_tiles, self._load_localizability)

    # -- tiles -------------------------------------------------------------------------------------------
    def tile_keys(self) -> list[tuple[int, int]]:
        return sorted(self._tiles)

    def tile_entry(self, i: int, j: int) -> dict[str, Any]:
        try:
            return self._tiles[(int(i), int(j))]
        except KeyError as exc:
            raise UnknownNameError(f"{self.path}: no tile ({i},{j}); the map has {len(self._tiles)} tiles") from exc

    def tile_corners(self, i: int, j: int) -> pa.Table:
        """All corners of tile (i, j) (an empty table for a tile the map does not have)."""
        if (i, j) not in self._tiles:
            return self._empty
        return self._corners.get((int(i), int(j)))[0]

    def tile_marking(self, i: int, j: int) -> np.ndarray | None:
        """Tile (i, j)'s marking raster (uint8, row 0 = north edge) or None when it has none."""
        if (i, j) not in self._tiles or not (self._tiles[(i, j)].get("marking") or {}).get("mask_file"):
            return None
        return self._markings.get((int(i), int(j)))

    def _read(self, key: tuple[int, int], name: str) -> tuple[Path, bytes]:
        rel = f"{self._tiles[key]['dir']}/{name}"
        return self.path / rel, read_verified(self.path, rel, self.manifest.get("files", {}), self.trust_files)

    def tile_layer(self, i: int, j: int, layer: str = "marking_mask") -> np.ndarray:
        """Any raster layer of tile (i, j), decoded (row 0 = north): masks uint8, ``intensity`` / ``elevation_*``
        float64 with NaN = no data, ``point_count`` uint16 (mapformat/layers.py). Not cached. The sidecar and
        the layer's file are checked against the manifest (sha256, inside the version) before decoding."""
        from mapformat.layers import read_layer, sidecar_layers

        key = (int(i), int(j))
        marking = self.tile_entry(i, j).get("marking")
        if not marking:
            raise UnknownNameError(f"{self.path}: tile ({i},{j}) has no raster layers")
        tile_dir = self.path / self._tiles[key]["dir"]
        if (tile_dir / "raster.json").is_file():
            self._read(key, "raster.json")
        entry = sidecar_layers(tile_dir, marking).get(layer)
        data = self._read(key, str(entry["file"]))[1] if entry else None
        return read_layer(tile_dir, marking, layer, data)

    def _load_corners(self, key: tuple[int, int]) -> tuple[pa.Table, np.ndarray, np.ndarray]:
        """A tile's corners: ``decode_table`` bounded by the rows the manifest records for the tile (``n_corners``)."""
        path, data = self._read(key, layout.CORNERS_FILE)
        recorded = self._tiles[key].get("n_corners")
        table = decode_table(data, path, recorded if isinstance(recorded, int) else None)
        try:
            table = table.cast(self._schema)
        except (pa.ArrowInvalid, ValueError) as exc:
            raise MapFormatError(f"{path}: cannot read tile corners ({exc}); hint: run `cornermap tiles verify`") \
                from exc
        return table, table["east_m"].to_numpy(), table["north_m"].to_numpy()

    def _load_marking(self, key: tuple[int, int]) -> np.ndarray:
        from mapformat.layers import decode_png, expected_shape

        marking = self._tiles[key]["marking"]
        path, data = self._read(key, str(marking["mask_file"]))
        return decode_png(data, path, expected_shape(marking))

    # -- queries -----------------------------------------------------------------------------------------
    def _keys_in_box(self, e0: float, n0: float, e1: float, n1: float) -> list[tuple[int, int]]:
        if any(np.isnan(v) for v in (e0, n0, e1, n1)):
            raise LimitError(f"box ({e0}, {n0}, {e1}, {n1}) m has a NaN bound")
        if not all(np.isfinite(v) for v in (e0, n0, e1, n1)):  # an unbounded box: the map's tiles it meets
            s = self.tile_size_m
            return [k for k in sorted(self._tiles) if k[0] * s <= e1 and (k[0] + 1) * s > e0
                    and k[1] * s <= n1 and (k[1] + 1) * s > n0]
        i0, j0 = (int(k) for k in tile_key_of(e0, n0, self.tile_size_m))
        i1, j1 = (int(k) for k in tile_key_of(e1, n1, self.tile_size_m))
        if (i1 - i0 + 1) * (j1 - j0 + 1) > len(self._tiles):  # a huge box: filter the map's tiles instead
            return [k for k in sorted(self._tiles) if i0 <= k[0] <= i1 and j0 <= k[1] <= j1]
        return [(i, j) for i in range(i0, i1 + 1) for j in range(j0, j1 + 1) if (i, j) in self._tiles]

    def _select(self, e0, n0, e1, n1, keep: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> pa.Table:
        parts = []
        for key in self._keys_in_box(e0, n0, e1, n1):
            table, east, north = self._corners.get(key)
            mask = keep(east, north)
            if mask.all():
                parts.append(table)
            elif mask.any():
                parts.append(table.filter(pa.array(mask)))
        if not parts:
            return self._empty
        return parts[0] if len(parts) == 1 else pa.concat_tables(parts)

    def corners_in_bbox(self, e0: float, n0: float, e1: float, n1: float) -> pa.Table:
        """Corners with e0 <= east < e1 and n0 <= north < n1 (map ENU metres), corner_map columns."""
        return self._select(e0, n0, e1, n1, lambda e, n: (e >= e0) & (e < e1) & (n >= n0) & (n < n1))

    def corners_within(self, east_m: float, north_m: float, radius_m: float) -> pa.Table:
        """Corners within ``radius_m`` (inclusive) of (east_m, north_m); ``radius_m`` = inf: every corner. A NaN or
        negative radius, or a non-finite centre, is a LimitError."""
        if not (np.isfinite(east_m) and np.isfinite(north_m)) or np.isnan(radius_m) or radius_m < 0:
            raise LimitError(f"corners_within: centre ({east_m}, {north_m}) m and radius {radius_m} m: expected a "
                             "finite centre and a radius >= 0 (inf for every corner)")
        if np.isinf(radius_m):
            return self.all_corners()
        r2 = radius_m * radius_m
        return self._select(east_m - radius_m, north_m - radius_m, east_m + radius_m, north_m + radius_m,
                            lambda e, n: (e - east_m) ** 2 + (n - north_m) ** 2 <= r2)

    def all_corners(self) -> pa.Table:
        parts = [self._corners.get(k)[0] for k in self.tile_keys()]
        return pa.concat_tables(parts) if parts else self._empty

    def marking_window(
        self, e0: float, n0: float, e1: float, n1: float
    ) -> tuple[np.ndarray, tuple[float, float], float]:
        """Mosaic of the marking rasters over the box, on the raster cell lattice.

        Returns (mask uint8 of shape (rows, cols), (east_m, north_m) of the window's lower-left corner, cell_m).
        Row 0 is the north edge. Cells outside every published raster are 0. The window covers the box,
        extended outwards to whole cells.
        """
        return self._mosaic("marking_window", e0, n0, e1, n1, self._markings.get)

    def observed_window(
        self, e0: float, n0: float, e1: float, n1: float
    ) -> tuple[np.ndarray, tuple[float, float], float]:
        """Where the map saw the ground, on ``marking_window``'s lattice: 1 where a raster cell holds survey points
        (``point_count`` > 0), 0 elsewhere and outside every published raster. A 0 in ``marking_window`` means "no
        paint" only where this is 1; beyond the surveyed area it means "not known". A tile written without a
        ``point_count`` layer counts as observed over its whole raster."""
        return self._mosaic("observed_window", e0, n0, e1, n1, self._observed.get)

    def _load_observed(self, key: tuple[int, int]) -> np.ndarray:
        from mapformat.layers import sidecar_layers

        marking = self._tiles[key]["marking"]
        if "point_count" not in sidecar_layers(self.path / self._tiles[key]["dir"], marking):
            mask = self._markings.get(key)
            return np.ones(mask.shape[:2], np.uint8)
        return (self.tile_layer(key[0], key[1], "point_count") > 0).astype(np.uint8)

    def _mosaic(self, query: str, e0: float, n0: float, e1: float, n1: float,
                image_of: Callable[[tuple[int, int]], np.ndarray]) -> tuple[np.ndarray, tuple[float, float], float]:
        """One layer of the tiles' rasters (``image_of(key)``, row 0 north) over the box, on the cell lattice;
        ``query`` names the public method in the errors."""
        if self.cell_m is None:
            raise UnknownNameError(f"{self.path}: this map has no marking rasters")
        cell = self.cell_m
        if not all(np.isfinite(v) for v in (e0, n0, e1, n1)):
            raise LimitError(f"{query}: box ({e0}, {n0}, {e1}, {n1}) m is not finite")
        c0, c1 = int(np.floor(e0 / cell + 1e-9)), int(np.ceil(e1 / cell - 1e-9))
        s0, s1 = int(np.floor(n0 / cell + 1e-9)), int(np.ceil(n1 / cell - 1e-9))
        cells = max(0, s1 - s0) * max(0, c1 - c0)
        if cells > MAX_WINDOW_CELLS:
            raise LimitError(f"{query}: {c1 - c0} x {s1 - s0} cells of {cell} m = {cells} cells, more than the "
                             f"limit of {MAX_WINDOW_CELLS}; hint: query smaller windows")
        out = np.zeros((max(0, s1 - s0), max(0, c1 - c0)), np.uint8)
        for key in self._keys_in_box(e0, n0, e1, n1):
            meta = self._tiles[key].get("marking")
            if not meta or not meta.get("mask_file"):
                continue
            img = image_of(key)
            if img.ndim == 3:
                img = img[..., 0]
            tc0 = int(round(meta["origin_east_m"] / cell))
            ts0 = int(round(meta["origin_north_m"] / cell))
            h, w = img.shape[:2]
            # overlap in global (south-up row, column) cell indices
            a_c, b_c = max(c0, tc0), min(c1, tc0 + w)
            a_s, b_s = max(s0, ts0), min(s1, ts0 + h)
            if a_c >= b_c or a_s >= b_s:
                continue
            src = img[(ts0 + h - b_s):(ts0 + h - a_s), (a_c - tc0):(b_c - tc0)]
            out[(s1 - b_s):(s1 - a_s), (a_c - c0):(b_c - c0)] = src.astype(np.uint8, copy=False)
        return out, (c0 * cell, s0 * cell), cell

    def tile_localizability(self, i: int, j: int) -> pa.Table | None:
        """Tile (i, j)'s cells of the localizability layer (``mapformat/localizability.py``'s columns; verified,
        bounded, cached like the corners), None for a tile without one (a version published before the layer)."""
        from mapformat.localizability import LOCALIZABILITY_FILE

        entry = self._tiles.get((int(i), int(j)))
        if entry is None or LOCALIZABILITY_FILE not in (entry.get("files") or {}):
            return None
        return self._localizability.get((int(i), int(j)))[0]

    def _load_localizability(self, key: tuple[int, int]) -> tuple[pa.Table, np.ndarray, np.ndarray]:
        from mapformat.localizability import LOCALIZABILITY_FILE, SCHEMA

        entry = self._tiles[key]
        path, data = self._read(key, LOCALIZABILITY_FILE)
        recorded = entry.get("n_localizability_cells")
        table = decode_table(data, path, recorded if isinstance(recorded, int) else None)
        try:
            table = table.select(SCHEMA.names).cast(SCHEMA)
        except (KeyError, pa.ArrowInvalid, ValueError) as exc:
            raise MapFormatError(f"{path}: not a localizability layer ({exc}); hint: run `cornermap tiles verify`") \
                from exc
        return table, table["east_m"].to_numpy(), table["north_m"].to_numpy()

    def localizability_in_bbox(self, e0: float, n0: float, e1: float, n1: float,
                               keep: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None) -> pa.Table:
        """The localizability cells whose road point lies in [e0, e1) x [n0, n1) and, with ``keep(east, north)``,
        where it says so (both methods; an empty table of the layer's columns when the version has none)."""
        from mapformat.localizability import LOCALIZABILITY_FILE, SCHEMA

        got = [self._localizability.get(key) for key in self._keys_in_box(e0, n0, e1, n1)
               if LOCALIZABILITY_FILE in (self._tiles[key].get("files") or {})]
        if not got:
            return SCHEMA.empty_table()
        e, n = np.concatenate([g[1] for g in got]), np.concatenate([g[2] for g in got])
        mask = (e >= e0) & (e < e1) & (n >= n0) & (n < n1)
        if keep is not None:
            mask &= keep(e, n)
        table = got[0][0] if len(got) == 1 else pa.concat_tables([g[0] for g in got])
        return table if mask.all() else table.take(np.flatnonzero(mask))  # take: 4x a filter on many chunks

    def query_latlon(self, lat_deg: float, lon_deg: float, radius_m: float, *, heading_deg: float | None = None,
                     fov_deg: float | None = None, markings: bool = True):
        """Corners (with lat_deg / lon_deg), marking window and localizability cells within ``radius_m`` of a WGS84
        latitude / longitude, within ``fov_deg`` about ``heading_deg`` (ENU, from east) when both are given
        (``mapformat.query.MapQuery``)."""
        from mapformat.query import query_latlon

        return query_latlon(self, lat_deg, lon_deg, radius_m, heading_deg=heading_deg, fov_deg=fov_deg,
                            markings=markings)

    def query_pose(self, east_m: float, north_m: float, yaw_rad: float, fov_rad: float, range_m: float, *,
                   markings: bool = True):
        """What a sensor at pose (east_m, north_m, yaw_rad) (map ENU) sees within ``range_m`` and ``fov_rad`` about
        its heading (``mapformat.query.MapQuery``; the marking window covers the range's square)."""
        from mapformat.query import query

        return query(self, east_m, north_m, range_m, heading_rad=yaw_rad, fov_rad=fov_rad, markings=markings)

    @staticmethod
    def covariances(corners: pa.Table) -> np.ndarray:
        """(N, 2, 2) east/north covariances in m^2 of a corner table."""
        ee, en, nn = (corners[c].to_numpy() for c in ("cov_ee_m2", "cov_en_m2", "cov_nn_m2"))
        return np.stack([np.stack([ee, en], -1), np.stack([en, nn], -1)], -2)

    def clear_cache(self) -> None:
        self._corners.clear()
        self._markings.clear()
        self._observed.clear()
        self._localizability.clear()


def _corner_schema() -> pa.Schema:
    """The corner_map schema (with units) in the published column order."""
    from schemas import schema_of

    schema = schema_of("corner_map")
    return pa.schema([schema.field(name) for name in layout.CORNER_COLUMNS], metadata=schema.metadata)


def open_map(path: str | Path, version: str | int = "LATEST", cache_tiles: int = 64, *,
             trust_files: bool = False) -> MapReader:
    """Open ``ROOT/maps/NAME`` at ``version`` ("LATEST", "v0003", 3), or a version directory itself.

    Through ``ROOT/maps/NAME`` the manifest is checked against the digest chain that starts at LATEST (a
    version directory opened directly has no digest outside itself: only its files are verified).

    ``s3://BUCKET/ROOT/maps/NAME`` (endpoint and credentials from the AWS environment): LATEST, the manifests and the
    version are downloaded to a temporary folder kept for this process (``pipeline.store_maps.snapshot_map``), then
    opened and verified the same way; the bytes checked are the bucket's."""
    from pipeline.storage import uri_scheme

    if uri_scheme(path) is not None:
        return _open_remote(str(path), version, cache_tiles, trust_files)
    path = Path(path)
    if (path / MANIFEST_NAME).is_file():
        return MapReader(path, cache_tiles, trust_files=trust_files)
    if not path.is_dir():
        raise UnknownNameError(f"{path}: no such map directory; expected ROOT/maps/NAME or a vNNNN directory")
    vdir = resolve_version(path, version)
    expected = trusted_manifest_digests(path).get(int(vdir.name[1:]))
    return MapReader(vdir, cache_tiles, manifest_sha256=expected, trust_files=trust_files)


_SNAPSHOTS: list[Any] = []  # temporary folders of maps opened from an object store, removed at exit


def _open_remote(uri: str, version: str | int, cache_tiles: int, trust_files: bool) -> MapReader:
    import tempfile
    from pathlib import PurePosixPath

    from pipeline.errors import ObjectStoreError
    from pipeline.storage import Store, normalise_uri, object_store_error_line, uri_scheme
    from pipeline.store_maps import snapshot_map
    from pipeline.version_read import parse_version

    uri = normalise_uri(uri)
    scheme = uri_scheme(uri)
    loc = PurePosixPath(uri[len(scheme) + 3:])
    if re_version(loc.name):
        version, loc = loc.name, loc.parent
    if loc.parent.name != "maps" or len(loc.parts) < 3:
        raise UnknownNameError(f"{uri}: expected {scheme}://BUCKET/ROOT/maps/NAME (or .../maps/NAME/vNNNN)")
    store = Store.open(f"{scheme}://{loc.parent.parent.as_posix()}")
    tmp = tempfile.TemporaryDirectory(prefix="cornermap-map-")
    _SNAPSHOTS.append(tmp)
    latest = isinstance(version, str) and version.upper() == "LATEST"
    try:
        mdir = snapshot_map(store, loc.name, Path(tmp.name), "latest" if latest else [parse_version(version)])
    except ObjectStoreError as exc:  # the store names the object it asked for; a user asked for the map
        raise ObjectStoreError.at(uri, exc.line or str(exc)) from exc
    except Exception as exc:  # a client error raised outside the store's operations: named the same way
        line = object_store_error_line(exc)
        if line is None:
            raise
        raise ObjectStoreError.at(uri, line) from exc
    return open_map(mdir, version, cache_tiles, trust_files=trust_files)


def re_version(name: str) -> bool:
    from pipeline.storage import VERSION_RE

    return VERSION_RE.match(name) is not None
