"""The on-disk map format, stated once (docs/map-format.md is the human-readable twin of this module)."""
from __future__ import annotations

import re

FORMAT_NAME = "cornermap-tiles"
FORMAT_VERSION = 1  # bump on any incompatible change; readers refuse versions they do not know
SUPPORTED_FORMAT_VERSIONS = frozenset({1})

TILES_DIR = "tiles"
TRAJECTORIES_DIR = "trajectories"
CORNERS_FILE = "corners.parquet"
# The marking mask the loader mosaics: the markings stage writes marking_mask.png (stages/markings/raster_io.py);
# marking.png is what tile_{i}_{j}_marking.png artifacts become. First match wins.
MARKING_MASK_FILES = ("marking_mask.png", "marking.png")
RASTER_SIDECAR = "raster.json"  # the markings stage's per-tile JSON sidecar

# Markings stage artifact names: tile_{i}_{j}_{layer}.png and tile_{i}_{j}.json.
_TILE_FILE_RE = re.compile(r"^tile_(-?\d+)_(-?\d+)(?:_(.+)|(\.[^_]+))$")

CORNER_COLUMNS = ("corner_id", "east_m", "north_m", "theta1_rad", "theta2_rad", "cov_ee_m2", "cov_en_m2",
                  "cov_nn_m2", "n_obs", "n_drives", "drives", "first_seen_ns", "last_seen_ns",
                  "interior_angle_rad", "convex")


def tile_dir_name(i: int, j: int) -> str:
    """``tiles/{i}_{j}`` with signed decimal keys, e.g. ``tiles/-3_12``."""
    return f"{TILES_DIR}/{int(i)}_{int(j)}"


def parse_tile_dir_name(name: str) -> tuple[int, int]:
    i, _, j = name.rpartition("/")[2].partition("_")
    return int(i), int(j)


def published_name_of(filename: str, i: int, j: int) -> str | None:
    """Name a markings artifact gets inside tile (i, j)'s directory; None when it belongs to another tile.

    ``tile_3_-2_marking.png`` -> ``marking.png``; ``tile_3_-2.json`` -> ``raster.json``; a file without a
    tile prefix (a per-partition artifact directory) keeps its name.
    """
    m = _TILE_FILE_RE.match(filename)
    if m is None:
        return filename
    if (int(m.group(1)), int(m.group(2))) != (int(i), int(j)):
        return None
    if m.group(3) is not None:
        return m.group(3)
    return "raster" + m.group(4)


def trajectory_file_name(drive: str) -> str:
    safe = re.sub(r"[^A-Za-z0-9_.-]", "_", drive)
    return f"{TRAJECTORIES_DIR}/{safe}.tum"
