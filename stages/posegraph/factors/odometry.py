"""Between factors along a drive: the accepted ICP edges, wheel increments (bridges over failed edges, or fused
beside accepted ones), weak GNSS/INS bridges, and the odometry's span edges."""
from __future__ import annotations

import numpy as np

from stages.posegraph.config import FactorConfig
from stages.posegraph.factors.drive import DriveInput, bridge_increment, has_wheel
from stages.posegraph.factors.graph import Between
from stages.posegraph.factors.wheel import wheel_information


def span_betweens(drive: DriveInput, offset: int, cfg: FactorConfig) -> list[Between]:
    """One factor per accepted span edge, under ``cfg.span_edge_kernel`` (a span over a street with few cross
    structures can be decimetres off along-track; gangnam: 1-2 % of the 90-scan spans)."""
    if drive.spans is None:
        return []
    sp = drive.spans
    return [Between(offset + int(i), offset + int(j), T, info, "span", cfg.span_edge_kernel, cfg.span_edge_kernel_k)
            for i, j, T, info in zip(sp.i, sp.j, sp.T_i_j, sp.information)]


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
            out.append(Between(offset + k - 1, offset + k, drive.edge_T[k], drive.edge_info[k], "odometry"))
            if fusion_noise is not None and has_wheel(drive, k):
                out.append(Between(offset + k - 1, offset + k, drive.wheel_T[k],
                                   wheel_information(drive.wheel_T[k], fusion_noise), "wheel_fused"))
        elif wheel_noise is not None and has_wheel(drive, k):
            out.append(Between(offset + k - 1, offset + k, drive.wheel_T[k],
                               wheel_information(drive.wheel_T[k], wheel_noise), "wheel"))
        else:
            out.append(Between(offset + k - 1, offset + k, bridge_increment(drive, k), bridge_info, "bridge"))
    return out
