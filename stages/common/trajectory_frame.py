"""The frame a trajectory file is expressed in, and moving poses between local ENU frames by geodesy.

A reference trajectory (TUM) carries its frame twice: a header comment line in the file itself
(``# frame: ENU lat_deg=... lon_deg=... h_m=... ellipsoid=WGS84``) and a sidecar JSON beside it
(``NAME.frame.json`` for ``NAME.txt``: ``{"frame": "ENU", "origin": {lat_deg, lon_deg, h_m, ellipsoid}}``).
Readers take whichever is present and refuse a file whose two statements disagree.

``T_enuB_enuA`` is the rigid transform between two local ENU frames (WGS84): through ECEF, with the full 3-D
rotation (two ENU frames 60 km apart are tilted by 0.5 deg to each other, not only shifted).
"""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from stages.common.geodesy import EnuOrigin

HEADER_PREFIX = "frame: ENU"
_HEADER_RE = re.compile(r"^#\s*frame:\s*ENU\s+lat_deg=(\S+)\s+lon_deg=(\S+)\s+h_m=(\S+)")


def frame_header(origin: EnuOrigin) -> str:
    """The header line (without the leading '# ') naming a trajectory's ENU origin."""
    return (f"{HEADER_PREFIX} lat_deg={origin.lat_deg:.10f} lon_deg={origin.lon_deg:.10f} h_m={origin.h_m:.4f} "
            "ellipsoid=WGS84; rows: t x y z qx qy qz qw (T_enu_vehicle)")


def sidecar_path(trajectory_path: Path) -> Path:
    """``drive_1_poses_tum.txt`` -> ``drive_1_poses_tum.frame.json``."""
    p = Path(trajectory_path)
    return p.with_name(p.stem + ".frame.json")


def attitude_header(planar: bool) -> str:
    """The header line (without '# ') saying whether a trajectory's attitude is 3-D or planar."""
    if planar:
        return ("attitude: planar: z = 0, roll = pitch = 0 (the estimate is x, y, yaw only; evo: compare with a planar "
                "reference, or add --project_to_plane xy against a 3-D one)")
    return "attitude: 3-D: x y z and roll, pitch, yaw as estimated (not planar)"


def sidecar_text(origin: EnuOrigin, **extra) -> str:
    """The sidecar document: ``{"frame": "ENU", "origin": {...}, **extra}``."""
    return json.dumps({"frame": "ENU", "origin": origin.as_dict(), **extra}, indent=1, sort_keys=True) + "\n"


def write_sidecar(trajectory_path: Path, origin: EnuOrigin, **extra) -> Path:
    path = sidecar_path(trajectory_path)
    path.write_text(sidecar_text(origin, **extra))
    return path


def _origin_from_header(path: Path) -> EnuOrigin | None:
    with open(path, encoding="utf-8", errors="replace") as fh:
        for line in fh:
            if not line.startswith("#"):
                return None
            m = _HEADER_RE.match(line.strip())
            if m:
                return EnuOrigin(float(m.group(1)), float(m.group(2)), float(m.group(3)))
    return None


def _origin_from_sidecar(path: Path) -> EnuOrigin | None:
    from pipeline.errors import FormatError

    side = sidecar_path(path)
    if not side.is_file():
        return None
    try:
        doc = json.loads(side.read_text())
        if doc.get("frame") != "ENU":
            raise KeyError(f"frame is {doc.get('frame')!r}, expected 'ENU'")
        return EnuOrigin.from_dict(doc["origin"])
    except (ValueError, KeyError, TypeError) as exc:
        raise FormatError(f"{side}: expected {{\"frame\": \"ENU\", \"origin\": {{\"lat_deg\", \"lon_deg\", \"h_m\"}}}} "
                          f"({exc}); hint: fix or remove the sidecar") from exc


def read_trajectory_origin(path: Path) -> EnuOrigin | None:
    """The ENU origin a trajectory file states (header line or sidecar), or None when it states none."""
    from pipeline.errors import FormatError

    path = Path(path)
    head, side = _origin_from_header(path), _origin_from_sidecar(path)
    if head is not None and side is not None and not head.same_frame(side):
        raise FormatError(f"{path}: its header names origin {head} but {sidecar_path(path).name} names {side}; "
                          "hint: one of them is stale")
    return head if head is not None else side


def R_ecef_enu(origin: EnuOrigin) -> np.ndarray:
    """Rotation taking ENU axes at ``origin`` into ECEF axes (columns: east, north, up in ECEF)."""
    lat, lon = np.deg2rad(origin.lat_deg), np.deg2rad(origin.lon_deg)
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    return np.array([[-so, -sl * co, cl * co],
                     [co, -sl * so, cl * so],
                     [0.0, cl, sl]])


def T_enuB_enuA(origin_a: EnuOrigin, origin_b: EnuOrigin) -> np.ndarray:
    """4x4 rigid transform mapping ENU-about-``origin_a`` coordinates into ENU-about-``origin_b``."""
    import pymap3d

    R = R_ecef_enu(origin_b).T @ R_ecef_enu(origin_a)
    t = np.array(pymap3d.geodetic2enu(origin_a.lat_deg, origin_a.lon_deg, origin_a.h_m,
                                      origin_b.lat_deg, origin_b.lon_deg, origin_b.h_m, deg=True), dtype=float)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def move_poses(T_a_body: np.ndarray, origin_a: EnuOrigin, origin_b: EnuOrigin) -> np.ndarray:
    """(N,4,4) poses in ENU about ``origin_a`` -> the same poses in ENU about ``origin_b``."""
    return T_enuB_enuA(origin_a, origin_b) @ np.asarray(T_a_body, dtype=float)
