"""Evaluate one drive: run every localizer and baseline on arrays, then score them against each reference.

``evaluate_drive`` is the whole evaluation without I/O: ``compute`` (the stage) and ``cli`` feed it arrays
read through the store and the map loader. Methods: ``ekf`` (corners), ``mcl`` (markings), and the paper's
baselines ``rtk_ins`` (the GNSS/INS solution alone) and ``icp_dr`` (ICP dead reckoning alone).
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from stages.evaluate.ekf_params import EkfConfig
from stages.evaluate.localize_ekf import CornerMap, CornerObservations, dead_reckon, run_ekf
from stages.evaluate.localize_mcl import RasterFetcher, run_mcl
from stages.evaluate.metrics import JUDGE_ORDER, compute_errors, interpolate_poses, summarize, summarize_localized
from stages.evaluate.params import EvaluateParams

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DriveArrays:
    """Everything a vehicle has on one drive, one epoch per scan."""

    stamps_ns: np.ndarray  # (E,)
    icp_increments: np.ndarray  # (E,3) dx, dy, dyaw from epoch k-1 in its vehicle frame; NaN where missing
    odo_increments: np.ndarray  # (E,3) the same from wheel speed + gyro (no wheel odometry: ICP, else GNSS/INS)
    gnss_q: np.ndarray  # (E,3) GNSS/INS x, y, yaw at each epoch
    gnss_std: np.ndarray  # (E,3) std of east, north, yaw
    gnss_valid: np.ndarray  # (E,) bool
    corners: CornerObservations
    feature_epoch: np.ndarray  # (F,) int, sorted
    features_vehicle_m: np.ndarray  # (F,2)
    icp_raw_increments: np.ndarray | None = None  # (E,3) ICP increments alone (NaN = failed), no wheel fallback
    icp_cov: np.ndarray | None = None  # (E,3,3) their covariance from the registration's information
    features_deskewed: bool = True  # road features motion-compensated (the EKF's marking measurement needs it)
    where_q: np.ndarray | None = None  # (E,3) where the vehicle roughly is, for the map's area and the coverage:
    # None: the GNSS/INS fixes; a drive without GNSS: ICP dead reckoning from its start pose

    @property
    def roughly(self) -> tuple[np.ndarray, np.ndarray]:
        """(E,3) positions and (E,) valid that say which part of the map the drive covers."""
        if self.where_q is None:
            return self.gnss_q, self.gnss_valid
        return self.where_q, np.all(np.isfinite(self.where_q), axis=1)


@dataclass(frozen=True)
class FrameError:
    """How far the map's frame may sit from the true ENU frame, as the map states it (its manifest's ``map_frame``):
    a shift at ``reference_en_m`` and a rotation about it, covariance ``cov`` of (shift east m, shift north m,
    rotation rad). A GNSS/INS fix is in the true frame; placed in the map's, its error gains this. Beside it, the
    map's poses' own error relative to the frame (``relative_std_m`` per axis, ``relative_std_deg``): what a layer
    painted from them, the marking raster, is locally off by."""

    reference_en_m: np.ndarray  # (2,)
    cov: np.ndarray  # (3,3)
    relative_std_m: float = 0.0
    relative_std_deg: float = 0.0

    def at(self, en_m: np.ndarray) -> np.ndarray:
        """(3,3) covariance of the frame's displacement of a pose at ``en_m`` (east, north, yaw)."""
        d = np.asarray(en_m, float)[:2] - self.reference_en_m
        G = np.array([[1.0, 0.0, -d[1]], [0.0, 1.0, d[0]], [0.0, 0.0, 1.0]])
        return G @ self.cov @ G.T

    @classmethod
    def from_map(cls, doc: dict | None) -> FrameError | None:
        """From ``MapReader.map_frame`` (None: the map states none; its corner covariances hold it)."""
        if doc is None:
            return None
        return cls(np.asarray(doc["reference_en_m"], float), np.asarray(doc["cov_shift_rotation"], float),
                   float(doc.get("relative_std_m") or 0.0), float(doc.get("relative_std_deg") or 0.0))

    def marking_offset(self, cfg: EkfConfig) -> EkfConfig:
        """The EKF's section with the marking raster's local error set to the map's stated relative pose error (a
        raster painted from the map drives' scans is off by it); the params' value only where the map states none.
        Not a floor: the params' 0.036 m / 0.092 deg were one old map's poses (tiny seed 7 at 2026-11-25), and a
        consider offset is never reduced, so a stated error above the real one holds the filter's covariance above
        its error at every epoch (tiny calibration seeds 201-203 without a survey: the raster's persistent offset
        at the true pose 0.009-0.019 m across and 0.018-0.060 deg, the maps state 0.011-0.021 m and 0.050-0.068 deg;
        position NEES 0.45-0.69 of 2 with the floor; docs/evaluation.md, "NEES")."""
        m = cfg.markings
        return cfg.replace(markings={"map_sigma_m": self.relative_std_m if self.relative_std_m > 0 else m.map_sigma_m,
                                     "map_sigma_deg": (self.relative_std_deg if self.relative_std_deg > 0
                                                       else m.map_sigma_deg)})


@dataclass
class MethodRun:
    q: np.ndarray  # (E,3)
    P: np.ndarray | None  # (E,3,3)
    n_associated: np.ndarray  # (E,)
    seconds: float = 0.0
    assoc_epoch: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    assoc_map_idx: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    marking_rows: np.ndarray | None = None  # (E,) EKF: directions the road markings measured (-1: gated out)


@dataclass
class Evaluation:
    stamps_ns: np.ndarray
    runs: dict[str, MethodRun]
    references: dict[str, np.ndarray]  # name -> (E,3) reference at the epochs (NaN where none)
    metrics: dict[str, dict[str, dict]]  # method -> reference name -> summary
    primary: str | None  # reference the per-epoch errors and the targets use


def gyro_increments(d: DriveArrays) -> np.ndarray | None:
    """(E,) True where the ICP motion model's increment is the wheel/gyro one (ICP failed or was gated); None for
    a drive without wheel odometry (its fallback is the GNSS/INS pose difference, which has no gyro bias)."""
    if d.icp_raw_increments is None:
        return None
    with np.errstate(invalid="ignore"):
        return np.any(d.icp_increments != d.icp_raw_increments, axis=1)


def first_fix(d: DriveArrays) -> int:
    """Index of the first epoch with a valid, finite GNSS/INS fix (the filters start there)."""
    ok = d.gnss_valid & np.all(np.isfinite(d.gnss_q), axis=1) & np.all(np.isfinite(d.gnss_std), axis=1)
    if not ok.any():
        from pipeline.errors import DataQualityError

        raise DataQualityError(f"no valid GNSS/INS fix among {len(ok)} epochs: the filters cannot be initialised; "
                               "hint: check poses_gnss.valid of this drive")
    return int(np.argmax(ok))


def initial_covariance(d: DriveArrays, k0: int, cfg: EkfConfig, frame: FrameError | None) -> np.ndarray:
    """(3,3) the filters' start: the fix's own std (floored: urban GNSS/INS understates it) and, in the map's frame,
    the map frame's error at the fix (``frame``; a map that states none holds it in its corner covariances)."""
    P0 = np.diag(np.maximum(d.gnss_std[k0], [cfg.init_sigma_xy_m, cfg.init_sigma_xy_m, cfg.init_sigma_yaw_rad]) ** 2)
    return P0 if frame is None else P0 + frame.at(d.gnss_q[k0, :2])


def run_methods(d: DriveArrays, cmap: CornerMap | None, fetch: RasterFetcher | None, cfg: EvaluateParams,
                frame: FrameError | None = None) -> dict[str, MethodRun]:
    k0 = first_fix(d)
    q0 = d.gnss_q[k0]
    P0 = initial_covariance(d, k0, cfg.ekf, frame)
    runs: dict[str, MethodRun] = {}
    n = len(d.stamps_ns)
    valid = d.gnss_valid[:, None] & np.isfinite(d.gnss_q)
    rtk_P = np.zeros((n, 3, 3))
    rtk_P[:, [0, 1, 2], [0, 1, 2]] = d.gnss_std**2
    runs["rtk_ins"] = MethodRun(np.where(valid, d.gnss_q, np.nan), rtk_P, np.zeros(n, np.int32))
    runs["icp_dr"] = MethodRun(dead_reckon(d.icp_increments, q0, k0), None, np.zeros(n, np.int32))
    if "ekf" in cfg.methods and cmap is not None:
        t0 = time.perf_counter()
        marks = {}
        if cfg.ekf.markings.enabled and fetch is not None and len(d.feature_epoch) and d.features_deskewed:
            marks = {"feature_epoch": d.feature_epoch, "features_vehicle_m": d.features_vehicle_m, "fetch": fetch}
        elif cfg.ekf.markings.enabled:
            # a scan's points are up to 0.1 s late: not deskewed, they place the paint up to 0.8 m behind at 8 m/s
            # (tiny seed 7 without deskew: EKF RMS 0.053 -> 0.204 m, NEES 14)
            why = ("map has no marking raster" if fetch is None else "drive has no road features"
                   if not len(d.feature_epoch) else "road features are not deskewed (no wheel odometry)")
            log.warning("ekf: the road-marking measurement is on, but the %s; the EKF runs on corners alone", why)
        ekf_cfg = cfg.ekf if marks or not cfg.ekf.markings.enabled else cfg.ekf.replace(markings={"enabled": False})
        marks["likelihood"] = cfg.markings
        if frame is not None:
            ekf_cfg = frame.marking_offset(ekf_cfg)
        if cfg.ekf.motion == "wheel_bias" and d.icp_raw_increments is not None:
            r = run_ekf(d.icp_raw_increments, d.corners, cmap, q0, P0, k0, ekf_cfg,
                        wheel_increments=d.odo_increments, stamps_ns=d.stamps_ns, icp_cov=d.icp_cov, **marks)
        elif (cfg.ekf.icp.gyro_gate_chi2 > 0 and cfg.ekf.icp.gyro_fusion and cfg.ekf.icp.gyro_bias_state
              and d.icp_raw_increments is not None):
            failed = ~np.all(np.isfinite(d.icp_raw_increments), axis=1)  # the gate is the filter's, not the angle
            inc = np.where(failed[:, None], d.odo_increments, d.icp_raw_increments)
            r = run_ekf(inc, d.corners, cmap, q0, P0, k0, ekf_cfg, stamps_ns=d.stamps_ns, from_gyro=failed,
                        gyro_yaw_rad=d.odo_increments[:, 2], wheel_fallback=d.odo_increments, icp_cov=d.icp_cov,
                        **marks)
        else:
            r = run_ekf(d.icp_increments, d.corners, cmap, q0, P0, k0, ekf_cfg, stamps_ns=d.stamps_ns,
                        from_gyro=gyro_increments(d), gyro_yaw_rad=d.odo_increments[:, 2], icp_cov=d.icp_cov,
                        **marks)
        runs["ekf"] = MethodRun(r.q, r.P, r.n_associated, time.perf_counter() - t0, r.assoc_epoch, r.assoc_map_idx,
                                r.marking_rows)
        log.info("ekf: %d epochs in %.2f s, %d associations", n - k0, runs["ekf"].seconds, len(r.assoc_epoch))
    if "mcl" in cfg.methods and fetch is not None:
        t0 = time.perf_counter()
        spread = None
        if frame is not None:  # the particles spread over the frame's error too
            F = frame.at(q0[:2])
            spread = (float(np.sqrt(cfg.mcl.init_sigma_xy_m**2 + np.linalg.eigvalsh(F[:2, :2])[-1])),
                      float(np.hypot(cfg.mcl.init_sigma_yaw_rad, np.sqrt(F[2, 2]))))
        r = run_mcl(d.odo_increments, d.feature_epoch, d.features_vehicle_m, fetch, q0, k0,
                    np.random.default_rng(cfg.mcl.seed), cfg.mcl, stamps_ns=d.stamps_ns, likelihood=cfg.markings,
                    init_spread=spread)
        runs["mcl"] = MethodRun(r.q, r.P, r.n_features, time.perf_counter() - t0)
        log.info("mcl: %d epochs in %.2f s", n - k0, runs["mcl"].seconds)
    return runs


def evaluate_drive(d: DriveArrays, cmap: CornerMap | None, fetch: RasterFetcher | None,
                   references: dict[str, tuple[np.ndarray, np.ndarray]], cfg: EvaluateParams,
                   frame: FrameError | None = None) -> Evaluation:
    """Run the methods and score them. ``references``: name ('map', 'truth', 'truth_in_map') -> (stamps_ns, (R,3)
    x y yaw). The primary reference (per-epoch errors, targets) is the first of ``JUDGE_ORDER`` given. With
    ``cfg.targets.ekf_judge_after_startup`` the EKF is scored from its first map-corner association on
    (``metrics.summarize_localized``). ``frame``: the map frame's stated error (``FrameError.from_map``), added to
    the filters' start."""
    runs = run_methods(d, cmap, fetch, cfg, frame)
    gap = int(cfg.reference.max_gap_s * 1e9)
    refs = {name: interpolate_poses(d.stamps_ns, st, q, gap) for name, (st, q) in references.items() if len(st)}
    k0 = first_fix(d)

    def score(method: str, r: MethodRun, ref: np.ndarray) -> dict:
        errors = compute_errors(r.q, ref, r.P)
        if method == "ekf" and cfg.targets.ekf_judge_after_startup:
            return summarize_localized(errors, r.n_associated, d.stamps_ns, k0)
        return summarize(errors)

    metrics = {m: {name: score(m, r, ref) for name, ref in refs.items()} for m, r in runs.items()}
    primary = next((name for name in JUDGE_ORDER if name in refs), None)
    return Evaluation(d.stamps_ns, runs, refs, metrics, primary)
