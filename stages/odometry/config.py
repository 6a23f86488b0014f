"""The odometry algorithm's settings in sections, one per step of ``estimate_edges`` (built from the stage's
params by ``OdometryParams.edge_config()``; tests and benches build them directly or with ``EdgeConfig.flat``).
"""
from __future__ import annotations

from dataclasses import dataclass, fields


@dataclass(frozen=True)
class PrepareConfig:
    """Per scan: range crop, voxel downsampling with ``knn`` neighbours for covariances / normals, and the road
    plane split (``ground_split``: points within ``ground_tolerance_m`` of the fitted plane are ground)."""

    voxel_m: float
    knn: int
    min_range_m: float
    max_range_m: float
    ground_split: bool = True
    ground_tolerance_m: float = 0.25


@dataclass(frozen=True)
class IcpConfig:
    """Registration of the structure clouds (open3d GICP or point-to-plane ICP). ``guided_relative_tolerance``:
    the convergence criterion of a consecutive pair that starts from its wheel guide corrected by the previous pair's
    registration (``core.register_pairs``); every other registration stops at ``relative_tolerance``."""

    method: str
    max_corr_m: float
    max_iterations: int
    relative_tolerance: float
    guided_relative_tolerance: float | None = None  # None: relative_tolerance


@dataclass(frozen=True)
class InformationConfig:
    """An edge's 6x6 information: the point-to-plane Hessian at ``point_sigma_m`` per point, floored at
    ``min_sigma_m`` / ``min_sigma_rad``, plus a rotation std of ``rot_sigma_per_rad`` per radian turned."""

    point_sigma_m: float
    min_sigma_m: float
    min_sigma_rad: float
    rot_sigma_per_rad: float = 0.0


@dataclass(frozen=True)
class GateConfig:
    """Acceptance of an edge: fitness, and deviation from the reference increment (GNSS/INS, or the tighter
    ``_guide`` limits where a wheel-odometry guide exists)."""

    min_fitness: float
    max_deviation_m: float
    max_deviation_rad: float
    max_deviation_guide_m: float = 0.05
    max_deviation_guide_rad: float = 0.0035


@dataclass(frozen=True)
class KeyframeConfig:
    """Pairs of scans further apart in time than ``min_dt_s`` (keyframes, metres apart; ``keyframes.py``): GICP in
    ``stages`` of (voxel m, correspondence m); started from the prior, the GNSS/INS, else a global registration
    (FPFH + RANSAC at ``global_voxel_m``); gated within hypot(the reference's limit, ``deviation_*_per_m`` x the
    pair's distance); information floored at ``sigma_*_per_m`` x that distance; rejected when its chord leaves the
    heading by more than ``max_sideslip_rad`` (a car follows its heading: ``keyframes.plausible_motion``).
    ``prior_gate_sigmas``: a prior's limit in its stated std (times sqrt 2: two poses)."""

    min_dt_s: float = 0.35
    stages: tuple[tuple[float, float], ...] = ((1.0, 2.0), (0.5, 0.5))
    deviation_m_per_m: float = 0.05
    deviation_rad_per_m: float = 0.0035
    sigma_m_per_m: float = 0.015
    sigma_rad_per_m: float = 0.0015
    global_voxel_m: float = 1.0
    prior_gate_sigmas: float = 3.0
    max_sideslip_rad: float = 0.26  # the chord of a keyframe pair within this of the arc's (heading + turn / 2)


@dataclass(frozen=True)
class EdgeConfig:
    """All of ``estimate_edges``' settings: the sections, own-sweep ``deskew`` and the ``span_scans``."""

    prepare: PrepareConfig
    icp: IcpConfig
    information: InformationConfig
    gate: GateConfig
    deskew: bool
    span_scans: tuple[int, ...] = ()
    keyframe: KeyframeConfig = KeyframeConfig()

    @classmethod
    def flat(cls, *, deskew: bool, span_scans: tuple[int, ...] | list[int] = (), **values) -> "EdgeConfig":
        """Build from flat keywords named like the sections' fields; an unknown or missing one is a TypeError."""
        sections = {"prepare": PrepareConfig, "icp": IcpConfig, "information": InformationConfig,
                    "gate": GateConfig}  # keyframe: its defaults (``EdgeConfig(..., keyframe=KeyframeConfig(...))``)
        built = {}
        for key, section in sections.items():
            names = {f.name for f in fields(section)}
            built[key] = section(**{k: v for k, v in values.items() if k in names})
        unknown = set(values) - {f.name for s in sections.values() for f in fields(s)}
        if unknown:
            raise TypeError(f"EdgeConfig.flat: unknown settings {sorted(unknown)}")
        return cls(**built, deskew=deskew, span_scans=tuple(int(n) for n in span_scans))

    def registration_kwargs(self, guided: bool = False) -> dict:
        """The keywords of ``stages.common.registration.register_clouds`` (``guided``: of a consecutive pair started
        from its corrected wheel guide)."""
        i, icp = self.information, self.icp
        guided_tol = icp.guided_relative_tolerance
        tol = guided_tol if guided and guided_tol is not None else icp.relative_tolerance
        return dict(method=icp.method, max_corr_m=icp.max_corr_m, max_iterations=icp.max_iterations,
                    relative_tolerance=tol, point_sigma_m=i.point_sigma_m, min_sigma_m=i.min_sigma_m,
                    min_sigma_rad=i.min_sigma_rad)
