"""Reference trajectories for the evaluation, moved into the map's ENU frame (the I/O edge of references).

A truth file states its frame (``stages.common.trajectory_frame``: a header line or a sidecar JSON); it is moved
into the map's frame by geodesy (ENU about its origin -> ECEF -> ENU about the map's origin, full 3-D rotation)
before any yaw is taken from it. A file that states no frame is refused unless the caller says which frame it is
in (``reference.frame``: 'map' or 'LAT,LON,H'): comparing in two frames gave 15-216 m "errors" (issue 28).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stages.common.geodesy import EnuOrigin

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Reference:
    stamps_ns: np.ndarray  # (N,)
    q: np.ndarray  # (N,3) x, y, yaw in the map's ENU frame
    T_map_origin_ref: np.ndarray  # 4x4: the reference file's frame -> the map's frame (identity for 'map')
    frame: str  # how the frame was known: 'stated', 'given' or 'map'


def reference_origin(path: Path, frame) -> tuple[EnuOrigin | None, str]:
    """The ENU origin of a reference file under ``frame`` ('auto', 'map' or an EnuOrigin): (origin, how)."""
    from pipeline.errors import ReferenceFrameError
    from stages.common.trajectory_frame import read_trajectory_origin, sidecar_path

    if frame == "map":
        return None, "map"
    stated = read_trajectory_origin(path)
    if isinstance(frame, EnuOrigin):
        if stated is not None and not stated.same_frame(frame):
            log.warning("%s states origin %s; using the given %s", path, stated, frame)
        return frame, "given"
    if stated is None:
        raise ReferenceFrameError(
            f"{path}: the reference trajectory does not state its frame (no '# frame: ENU lat_deg=... lon_deg=... "
            f"h_m=...' header line, no {sidecar_path(path).name}); hint: pass --reference-frame map if it is in the "
            "map's ENU frame, or --reference-frame LAT,LON,H for ENU about that WGS84 origin")
    return stated, "stated"


def read_reference(path: Path, map_origin: EnuOrigin, frame) -> Reference:
    """A TUM trajectory as (stamps, x y yaw) in the map's ENU frame."""
    from stages.common.records import Trajectory
    from stages.common.trajectory_frame import T_enuB_enuA

    path = Path(path)
    origin, how = reference_origin(path, frame)
    truth = Trajectory.from_tum(path)
    T_move = np.eye(4) if origin is None else T_enuB_enuA(origin, map_origin)
    T = T_move @ truth.T
    if origin is not None:
        log.info("reference %s: ENU about %s moved into the map's frame (shift %.3f m, tilt %.4f deg)", path.name,
                 origin, float(np.linalg.norm(T_move[:3, 3])),
                 float(np.degrees(np.arccos(np.clip(T_move[2, 2], -1.0, 1.0)))))
    q = np.column_stack([T[:, 0, 3], T[:, 1, 3], np.arctan2(T[:, 1, 0], T[:, 0, 0])])
    return Reference(truth.stamp_ns, q, T_move, how)


def read_truth_corners(reference_path: Path, T_map_ref: np.ndarray) -> np.ndarray | None:
    """(K,2) east/north (map frame) of the simulator's ``corners.csv`` beside the truth trajectory, or None."""
    path = Path(reference_path).with_name("corners.csv")
    if not path.is_file():
        return None
    try:
        rows = np.genfromtxt(path, delimiter=",", names=True)
        en = np.column_stack([np.atleast_1d(rows["east_m"]), np.atleast_1d(rows["north_m"])])
    except (ValueError, KeyError) as exc:
        from pipeline.errors import FormatError

        raise FormatError(f"{path}: expected a CSV with east_m, north_m columns ({exc}); hint: it is the simulator's "
                          "truth/corners.csv, remove it if it is something else") from exc
    xyz = np.column_stack([en, np.zeros(len(en))]) @ T_map_ref[:3, :3].T + T_map_ref[:3, 3]
    return xyz[:, :2]
