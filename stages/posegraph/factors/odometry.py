"""Between factors along a drive: the accepted ICP edges, wheel increments (bridges over failed edges, or fused
beside accepted ones), weak GNSS/INS bridges, and the odometry's span edges."""
from __future__ import annotations

import numpy as np

from stages.posegraph.config import FactorConfig, RegistrationNoise
from stages.posegraph.factors.drive import DriveInput, bridge_increment, has_wheel
from stages.posegraph.factors.graph import Between
from stages.posegraph.factors.wheel import wheel_information


def span_betweens(drive: DriveInput, offset: int, cfg: FactorConfig) -> list[Between]:
    """One factor per accepted span edge, under ``cfg.span_edge_kernel`` (a span over a street with few cross
    structures can be decimetres off along-track; gangnam: 1-2 % of the 90-scan spans)."""
    if drive.spans is None:
        return []
    sp = drive.spans
    return [Between(offset + int(i), offset + int(j), T, registration_information(info, cfg.registration_sigma),
                    "span", cfg.span_edge_kernel, cfg.span_edge_kernel_k)
            for i, j, T, info in zip(sp.i, sp.j, sp.T_i_j, sp.information)]


def registration_information(information: np.ndarray, extra: RegistrationNoise | None) -> np.ndarray:
    """A registration's 6x6 information (gtsam order rx ry rz tx ty tz, body frame of the edge) with ``extra``'s
    along-track (tx), cross-track (ty) and yaw (rz) stds added to its covariance; unchanged without ``extra``."""
    if extra is None or (extra.along_m == 0 and extra.cross_m == 0 and extra.yaw_rad == 0):
        return information
    cov = np.linalg.inv(information)
    cov[[2, 3, 4], [2, 3, 4]] += np.array([extra.yaw_rad, extra.along_m, extra.cross_m]) ** 2
    out = np.linalg.inv(cov)
    return 0.5 * (out + out.T)


def odometry_betweens(drive: DriveInput, offset: int, cfg: FactorConfig) -> list[Between]:
    """One factor per consecutive pair: the ICP edge where it was accepted; else a wheel-odometry increment
    (kind "wheel", when the drive has one and ``cfg.wheel_bridge`` is set); else a weak bridge (GNSS/INS
    increment). With ``cfg.wheel_fusion``, every accepted ICP edge that has a wheel increment gets it as a second
    factor (kind "wheel_fused"): the calibrated wheel is the better along-track sensor over a few scans (gangnam:
    1.2 mm per scan against ICP's 3.7 mm, which a street with few cross structures biases by 1-4 cm per edge)."""
    bridge_info = np.diag([cfg.failed_edge_sigma_rad ** -2] * 3 + [cfg.failed_edge_sigma_m ** -2] * 3)
    wheel_noise, fusion_noise = cfg.wheel_bridge, cfg.wheel_fusion
    out = []
    for k in range(1, drive.n):
        if drive.edge_ok[k]:
            out.append(Between(offset + k - 1, offset + k, drive.edge_T[k],
                               registration_information(drive.edge_info[k], cfg.registration_sigma), "odometry"))
            if fusion_noise is not None and has_wheel(drive, k):
                out.append(Between(offset + k - 1, offset + k, drive.wheel_T[k],
                                   wheel_information(drive.wheel_T[k], fusion_noise), "wheel_fused"))
        elif wheel_noise is not None and has_wheel(drive, k):
            out.append(Between(offset + k - 1, offset + k, drive.wheel_T[k],
                               wheel_information(drive.wheel_T[k], wheel_noise), "wheel"))
        else:
            out.append(Between(offset + k - 1, offset + k, bridge_increment(drive, k), bridge_info, "bridge"))
    return out
