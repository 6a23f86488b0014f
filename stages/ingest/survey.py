"""Survey (mobile-mapping) LAS/LAZ clouds in a projected or geographic CRS -> ENU, streamed in chunks."""
from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from pipeline.errors import DatasetIOError, FormatError
from stages.common.geodesy import EnuOrigin, geodetic_to_enu, projected_to_geodetic


def crs_to_enu(x: np.ndarray, y: np.ndarray, z: np.ndarray, crs: str, origin: EnuOrigin) -> np.ndarray:
    """(N,) coordinates in ``crs`` -> (N,3) ENU metres (float64): pyproj to WGS84 geodetic, then pymap3d."""
    geodetic = projected_to_geodetic(x, y, z, crs)
    return geodetic_to_enu(geodetic[:, 0], geodetic[:, 1], geodetic[:, 2], origin)


def iter_survey_enu(path: Path, crs: str, origin: EnuOrigin, chunk_points: int = 1_000_000
                    ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Yield ((N,3) ENU float64, (N,) intensity float32) per chunk of at most ``chunk_points`` points."""
    from stages.ingest.scan_formats import open_las_checked

    try:
        reader = open_las_checked(path)
    except FileNotFoundError as exc:
        raise DatasetIOError(f"{path}: survey file not found") from exc
    except FormatError:
        raise
    except Exception as exc:  # noqa: BLE001 - laspy raises several types for a corrupt header
        raise FormatError(f"{path}: not a readable LAS/LAZ survey: {type(exc).__name__}: {exc}") from exc
    with reader:
        try:
            for chunk in reader.chunk_iterator(chunk_points):
                enu = crs_to_enu(np.asarray(chunk.x), np.asarray(chunk.y), np.asarray(chunk.z), crs, origin)
                yield enu, np.asarray(chunk.intensity, np.float32)
        except (FormatError, DatasetIOError):
            raise
        except Exception as exc:  # noqa: BLE001 - truncated LAZ data surfaces as lazrs/laspy errors
            raise FormatError(f"{path}: survey point data unreadable: {type(exc).__name__}: {exc}") from exc
