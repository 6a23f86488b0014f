"""Odometry step 1: each scan cropped to the range band, its road plane split off (height, roll, pitch) and the
structure above it downsampled for registration (open3d clouds with covariances for GICP)."""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
import open3d as o3d

from stages.common.ground_plane import GroundPlane, split_road
from stages.common.registration import crop_range, prepare_cloud, voxel_downsample
from stages.odometry.config import PrepareConfig

if TYPE_CHECKING:
    from stages.odometry.core import Scan


@dataclass
class PreparedScan:
    """One scan ready for registration: structure cloud (registration), road plane and ground points (height,
    roll, pitch and their information)."""

    points_m: np.ndarray
    time_offset_s: np.ndarray | None
    structure: o3d.geometry.PointCloud
    plane: GroundPlane | None
    ground_points_m: np.ndarray | None
    voxel_m: float

    @cached_property
    def ground_voxels_m(self) -> np.ndarray | None:
        """The ground points voxel-downsampled like the structure, computed on first use (only the final edges'
        information needs them, against the road plane: ``registration.plane_hessian``; scans deskewed after a
        first pass are prepared again)."""
        if self.ground_points_m is None:
            return None
        return voxel_downsample(self.ground_points_m, self.voxel_m)


def prepare_scan(points_m: np.ndarray, time_offset_s: np.ndarray | None, T_vehicle_lidar: np.ndarray,
                 cfg: PrepareConfig, with_cov: bool) -> PreparedScan:
    road = split_road(points_m, T_vehicle_lidar, cfg.ground_tolerance_m) if cfg.ground_split else None
    if road is None or road.plane is None:
        return PreparedScan(points_m, time_offset_s,
                            prepare_cloud(points_m, cfg.voxel_m, cfg.knn, with_covariances=with_cov),
                            None, None, cfg.voxel_m)
    return PreparedScan(points_m, time_offset_s,
                        prepare_cloud(road.structure_m, cfg.voxel_m, cfg.knn, with_covariances=with_cov), road.plane,
                        road.ground_m, cfg.voxel_m)


def prepare_scans(scans: list[Scan], T_vehicle_lidar: np.ndarray, cfg: PrepareConfig, with_cov: bool
                  ) -> list[PreparedScan]:
    """Step 1: crop each scan to the range band, split off its road plane, downsample the structure."""
    out = []
    for scan in scans:
        ok = crop_range(scan.points_lidar_m, cfg.min_range_m, cfg.max_range_m)
        t_s = scan.time_offset_s[ok] if scan.time_offset_s is not None else None
        out.append(prepare_scan(scan.points_lidar_m[ok], t_s, T_vehicle_lidar, cfg, with_cov))
    return out
