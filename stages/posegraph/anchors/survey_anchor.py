"""Survey anchoring: register a scan's ground and curb points to the absolute survey cloud (ENU, cm-accurate)
and turn each verified registration into an absolute pose prior, so that every map layer shares its frame.

Registration runs in a local frame centred on the pose (float precision). By default (``vertical_only``) it
registers height, roll and pitch only, the horizontal pose held at the estimate (``ground_registration``); the
horizontal anchor comes from the road markings (``survey_markings``). Otherwise a 6-DoF GICP whose
point-to-plane Hessian keeps the directions the ground alone does not fix (along a straight curb) weak.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from stages.common.ground_plane import rotation_between
from stages.common.registration import (
    as_indices,
    floor_information,
    prepare_cloud,
    register_clouds,
    voxel_downsample,
)
from stages.posegraph.config import AnchorConfig, GroundAnchorConfig
from stages.posegraph.factors.graph import PosePrior

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SurveyMatch:
    i: int
    T_map_vehicle: np.ndarray
    information: np.ndarray
    fitness: float
    inlier_rmse_m: float
    accepted: bool
    reason: str
    horizontal: object | None = None  # marking_match.MarkingMatch when markings were tried
    T_registered: np.ndarray | None = None  # the registration's own result (T_map_vehicle is its vertical part)
    T_init: np.ndarray | None = None  # the estimate it was matched from


def build_survey_index(survey_enu_m: np.ndarray, voxel_m: float) -> tuple[np.ndarray, cKDTree]:
    """Voxel-downsample the survey cloud once and index it in 2-D for cropping."""
    pts = voxel_downsample(survey_enu_m, voxel_m)
    return pts, cKDTree(pts[:, :2])


def anchor_scan(i: int, points_vehicle_m: np.ndarray, T_map_vehicle_init: np.ndarray, survey_pts: np.ndarray,
                survey_tree: cKDTree, cfg: GroundAnchorConfig, survey_normals: np.ndarray | None = None) -> SurveyMatch:
    """The scan's low points registered onto the survey crop around the current estimate. With
    ``cfg.vertical_only`` (the default) only height, roll and pitch are registered, the horizontal position and
    heading held at the estimate (``ground_registration.register_vertical``), and the anchor constrains those three
    (``vertical_information``); otherwise a 6-DoF GICP whose Hessian gives the information. ``survey_normals``: the
    plane normals of ``survey_pts`` (``survey_plane_normals``, computed once for the survey), else those of each crop
    (which differ from the survey's only within ``knn`` points of the crop's edge)."""
    voxel_m, min_fitness, max_rmse_m = cfg.voxel_m, cfg.min_fitness, cfg.max_rmse_m
    min_sigma_m, min_sigma_rad = cfg.min_sigma_m, cfg.min_sigma_rad
    origin = T_map_vehicle_init[:3, 3].copy()
    low = points_vehicle_m[points_vehicle_m[:, 2] < cfg.max_height_m]
    near = as_indices(survey_tree.query_ball_point(origin[:2], cfg.crop_m))
    if len(low) < 100 or len(near) < 100:
        return SurveyMatch(i, T_map_vehicle_init, np.zeros((6, 6)), 0.0, float("nan"), False,
                           f"too few points (scan {len(low)}, survey {len(near)})", T_init=T_map_vehicle_init)
    T_local_init = T_map_vehicle_init.copy()
    T_local_init[:3, 3] -= origin
    if cfg.vertical_only:
        T, fitness, rmse_m, registered_ok = _register_vertical(
            low, survey_pts[near] - origin, T_local_init, voxel_m,
            None if survey_normals is None else survey_normals[near])
    else:
        target = prepare_cloud(survey_pts[near] - origin, voxel_m)
        source = prepare_cloud(low, voxel_m)
        res = register_clouds(source, target, T_local_init, method="gicp", max_corr_m=1.0, max_iterations=50,
                              min_sigma_m=min_sigma_m, min_sigma_rad=min_sigma_rad)
        T, fitness, rmse_m, registered_ok = res.T_target_source.copy(), res.fitness, res.inlier_rmse_m, True
    T[:3, 3] += origin
    reason = "accepted"
    if not registered_ok:
        reason = "too few ground points carried weight in the vertical registration"
    elif fitness < min_fitness:
        reason = f"fitness {fitness:.2f} < {min_fitness:.2f}"
    elif rmse_m > max_rmse_m:
        reason = f"rmse {rmse_m:.3f} m > {max_rmse_m:.3f} m"
    registered = T
    if cfg.vertical_only:
        T = vertical_part(T, T_map_vehicle_init)
        info = vertical_information(min_sigma_m, min_sigma_rad)
    else:
        info = floor_information(res.information, min_sigma_m, min_sigma_rad)
    return SurveyMatch(i, T, info, fitness, rmse_m, reason == "accepted", reason,
                       T_registered=registered, T_init=T_map_vehicle_init)


def _register_vertical(low_vehicle_m: np.ndarray, survey_local_m: np.ndarray, T_local_init: np.ndarray,
                       voxel_m: float, survey_normals: np.ndarray | None = None
                       ) -> tuple[np.ndarray, float, float, bool]:
    """``register_vertical`` of the scan's low points (voxel-downsampled as the survey is) onto the survey crop (with
    its plane normals, computed here when not given): (T, fitness, inlier RMSE, whether enough points carried
    weight)."""
    from stages.posegraph.anchors.ground_registration import plane_normals, register_vertical

    source = voxel_downsample(low_vehicle_m, voxel_m)
    normals = plane_normals(survey_local_m) if survey_normals is None else survey_normals
    fit = register_vertical(source, survey_local_m, normals, T_local_init, max_corr_m=1.0)
    return fit.T_target_source.copy(), fit.fitness, fit.inlier_rmse_m, fit.converged


def rematched_vertical(match: SurveyMatch, T_map_vehicle: np.ndarray, max_shift_m: float) -> SurveyMatch | None:
    """A vertical-only ground match carried to a new estimate of its keyframe: the registered ground (height and
    tilt) again, under the new estimate's position and heading (``vertical_part``). The ground registration
    fixes height, roll and pitch only and slides horizontally, so a start moved within ``max_shift_m`` finds the
    same ground: matching it again would only repeat the registration. The shift is measured from the estimate the
    registration started from (``match.T_init``, kept through any number of carries), so rounds cannot walk a match
    further than ``max_shift_m`` step by step. None (match again) when the estimate moved further, or when the match
    was not accepted: a registration's gates (fitness, RMSE) judge its start, and a start that was far off fails
    them where a better one passes (tiny seed 89: every ground match of the first round failed from an estimate
    0.75 m / 0.43 deg off, and carrying the failures left the map 1.4 m off in height)."""
    if not match.accepted or match.T_registered is None or match.T_init is None:
        return None
    if np.linalg.norm(T_map_vehicle[:2, 3] - match.T_init[:2, 3]) > max_shift_m:
        return None
    return replace(match, T_map_vehicle=vertical_part(match.T_registered, T_map_vehicle))


def vertical_part(T_registered: np.ndarray, T_init: np.ndarray) -> np.ndarray:
    """The pose a ground-only registration actually determines, nearest to ``T_init``: the registered tilt
    (the smallest rotation turning the initial up axis onto the registered one, heading kept) and the initial
    position slid along the registered up axis onto the registered ground height. A prior at the registered
    pose itself, slid metres along the road, couples its height error to horizontal position through the
    tilt (measured: the anchors moved the tiny map 0.1 m horizontally)."""
    n = T_registered[:3, 2]
    out = np.eye(4)
    out[:3, :3] = rotation_between(T_init[:3, 2], n) @ T_init[:3, :3]
    out[:3, 3] = T_init[:3, 3] - n * float(n @ (T_init[:3, 3] - T_registered[:3, 3]))
    return out


def vertical_information(sigma_z_m: float, sigma_tilt_rad: float, weak: float = 1e-12) -> np.ndarray:
    """Body-frame information fixing height, roll and pitch only. The survey holds road and sidewalk *tops*
    (no curb faces, facades or poles), so its registration pins the ground plane to centimetres but slides
    horizontally (measured on tiny: 0.0-3.6 m horizontal error after GICP, < 0.02 m vertical)."""
    return np.diag([sigma_tilt_rad ** -2, sigma_tilt_rad ** -2, weak, weak, weak, sigma_z_m ** -2])


def survey_priors(matches: list[SurveyMatch], kernel_k: float = 1.345, yaw_sigma_rad: float = 0.0
                  ) -> list[PosePrior]:
    """Accepted matches as robust (Huber) absolute pose priors: the vertical part from the ground
    registration, the horizontal part from the marking match, each where accepted; with ``yaw_sigma_rad`` > 0
    also the heading at which the marking submap matched (``survey_markings.best_yaw_match``)."""
    from stages.posegraph.anchors.survey_markings import horizontal_information_body

    out = []
    for m in matches:
        T, info = m.T_map_vehicle.copy(), (m.information if m.accepted else np.zeros((6, 6)))
        h = m.horizontal
        if h is not None and h.accepted:
            T[:2, 3] += h.shift_en_m
            info = info + horizontal_information_body(h.information_en, T[:3, :3])
            if yaw_sigma_rad > 0:
                c, s = np.cos(h.yaw_rad), np.sin(h.yaw_rad)
                T[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ T[:3, :3]
                up = T[:3, :3].T @ np.array([0.0, 0.0, 1.0])  # the map's vertical in the body frame
                info = info.copy()
                info[:3, :3] += np.outer(up, up) / yaw_sigma_rad**2
        if np.any(info):
            out.append(PosePrior(m.i, T, info, "survey", "huber", kernel_k))
    return out


COVERAGE_RADIUS_M = 5.0  # a keyframe is anchored when the downsampled survey has a point this close to it


def _use_survey_and_drives(survey, voxel_m: float, drives, load, with_normals: bool = False) -> None:
    """Worker initializer of the ground anchors: the downsampled survey (``survey_ground_points``), its 2-D index
    (and with ``with_normals`` its plane normals: vertical anchors), and the drives and scan loader with which the
    worker reads its keyframes' scans itself. The stage's process never holds the survey."""
    from pipeline.parallel import set_worker_state, worker_cache
    from stages.posegraph.loops.clouds import _use_drives

    pts, tree = worker_cache(("survey ground index", survey.key, voxel_m), lambda: _ground_index(survey, voxel_m))
    normals = worker_cache(("survey ground normals", survey.key, voxel_m),
                           lambda: _shared_normals(survey, voxel_m, pts)) if with_normals else None
    set_worker_state(survey_pts=pts, survey_tree=tree, survey_normals=normals)
    _use_drives(drives, load)


def survey_ground_points(survey, voxel_m: float) -> np.ndarray:
    """The survey downsampled to ``voxel_m`` (``registration.voxel_downsample``), built once among the processes that
    share the source's ``cache_dir`` (``pipeline.parallel.build_once``; each process built its own: on demo 2.2 s
    of reading and downsampling per process)."""
    from pipeline.memory import release_memory

    def build() -> np.ndarray:
        points = survey.read()[0]
        out = voxel_downsample(points, voxel_m) if len(points) else np.zeros((0, 3))
        del points
        release_memory()  # gangnam: the raw cloud and open3d's copy, 835 -> 350 MB resident with the 0.2 m index
        return out

    from pipeline.parallel import build_once

    return build_once(getattr(survey, "cache_dir", None), f"survey-{survey.key}-ground-{voxel_m!r}.npy", build)


def _shared_normals(survey, voxel_m: float, pts: np.ndarray) -> np.ndarray | None:
    """``survey_plane_normals`` of ``survey_ground_points``, once among the processes sharing the source's
    ``cache_dir`` (3.0 s per process on demo)."""
    from pipeline.parallel import build_once

    if len(pts) < 3:
        return None
    return build_once(getattr(survey, "cache_dir", None), f"survey-{survey.key}-normals-{voxel_m!r}.npy",
                      lambda: survey_plane_normals(pts))


def survey_plane_normals(survey_pts: np.ndarray) -> np.ndarray | None:
    """The plane normals of the downsampled survey, once for every anchor and round: each vertical anchor computed
    those of its 40 m crop, 65 ms of its ~0.2 s on gangnam (66,700 points a crop; 5.2 s for the whole 1.9 M-point
    survey, 45 MB)."""
    from pipeline.memory import release_memory
    from stages.posegraph.anchors.ground_registration import plane_normals

    normals = plane_normals(survey_pts) if len(survey_pts) >= 3 else None
    release_memory()  # open3d's per-point covariances behind the normals (135 MB on gangnam), freed but kept by malloc
    return normals


def _ground_index(survey, voxel_m: float):
    pts = survey_ground_points(survey, voxel_m)
    return (pts, cKDTree(pts[:, :2])) if len(pts) else (np.zeros((0, 3)), None)


def _anchor_block(item) -> list[SurveyMatch | None]:
    """Ground registrations of a block of keyframes against the survey held by ``_use_survey_and_drives`` (module
    level); ``None`` for a keyframe the survey does not cover. The covered keyframes' clouds are read and prepared
    here (``clouds._clouds_item``) and dropped with the block."""
    from pipeline.parallel import worker_state
    from stages.posegraph.loops.clouds import _clouds_item

    chunk, voxel_m, keyed_poses, cfg = item
    state = worker_state()
    tree = state["survey_tree"]
    covered = [tree is not None and tree.query_ball_point(pose[:2, 3], COVERAGE_RADIUS_M, return_length=True) > 0
               for _, pose in keyed_poses]
    clouds = _clouds_item(([c for c, ok in zip(chunk, covered) if ok], voxel_m)) if any(covered) else {}
    return [anchor_scan(k, clouds[k], pose, state["survey_pts"], tree, cfg, state.get("survey_normals")) if ok
            else None for (k, pose), ok in zip(keyed_poses, covered)]


def ground_blocks(keys: np.ndarray, poses: np.ndarray, offsets: np.ndarray, voxel_m: float, cfg, block: int) -> list:
    """Items of ``_anchor_block``: consecutive keyframes (global pose indices) in blocks of at most ``block``."""
    from stages.posegraph.loops.clouds import cloud_requests

    requests = cloud_requests(offsets, keys)
    return [(chunk, voxel_m, [(g, poses[g]) for g, _, _ in chunk], cfg)
            for chunk in (requests[start:start + block] for start in range(0, len(requests), block))]


class SurveyArrays:
    """A survey source over arrays already in memory (benches, tests); the stage passes
    ``stages.posegraph.compute.SurveySource``, which reads the store where it is called."""

    def __init__(self, points_enu_m: np.ndarray, intensity: np.ndarray | None = None):
        import uuid

        self.points_enu_m, self.intensity = points_enu_m, intensity
        self.has_intensity = intensity is not None
        self.key = uuid.uuid4().hex  # ``worker_cache`` keys
        self.cache_dir = None  # nothing shared between processes through files (``build_once``)

    def read(self) -> tuple[np.ndarray, np.ndarray | None]:
        return self.points_enu_m, self.intensity


def _use_survey_markings(survey, feature_load) -> None:
    """Pool/cluster worker initializer for the marking anchors: the survey's marking index (lazy: the worker reads the
    survey from its source only to compute a tile no other process has) and a scan loader."""
    from pipeline.parallel import set_worker_state, worker_cache
    from stages.posegraph.anchors.survey_markings import survey_marking_index

    index = worker_cache(("survey marking index", survey.key), lambda: survey_marking_index(survey))
    set_worker_state(marking_index=index, feature_load=feature_load)


def _marking_block(item) -> tuple[list, dict]:
    """Marking anchors of consecutive keyframes of one drive (module level), and the road features of every scan
    their submaps used ({scan index: features}). Consecutive submaps share scans, so a block keeps one feature
    cache, started with the features the item brings from a previous round; blocks are independent (a cache
    changes speed, never a result)."""
    from pipeline.parallel import worker_state
    from stages.posegraph.anchors.survey_markings import marking_anchor

    drive, poses_drive, incs_drive, keys_local, cfg, known = item
    state = worker_state()
    cache: dict = {}
    used: dict = {}
    out = []
    for k in keys_local:
        out.append(marking_anchor(k, drive, poses_drive, incs_drive, state["feature_load"], state["marking_index"],
                                  cfg, feature_cache=cache, known_features=known))
        used.update(cache)
    return out, used


def marking_blocks(keys: np.ndarray, offsets: np.ndarray, block: int) -> list[tuple[int, list[int]]]:
    """Keyframes (global indices, sorted) -> (drive index, local keyframe indices) blocks of at most ``block``."""
    out = []
    owner = np.searchsorted(offsets, keys, side="right") - 1
    for o in np.unique(owner):
        local = (keys[owner == o] - offsets[o]).astype(int).tolist()
        out += [(int(o), local[i:i + block]) for i in range(0, len(local), block)]
    return out


def survey_anchor_callback(drives, load, survey, cfg: AnchorConfig, matches_out: list | None = None,
                           feature_load=None, report_step=None):
    """A ``survey_priors(poses, offsets)`` callback for ``solve_map``: anchors keyframes every
    ``cfg.stride_m`` that the survey covers; every match of the last call (accepted or not) is left in ``matches_out``.
    ``survey``: a picklable source with ``read() -> (points, intensity or None)``, ``has_intensity`` and a ``key`` (the
    same in every process; the workers keep its indices under it)
    (``compute.SurveySource``, ``SurveyArrays``). The raw cloud is read at the first call, downsampled, and dropped;
    the marking workers read it themselves. With the survey's intensities and a ``feature_load``er (scans with
    intensity and ring), each keyframe is also matched horizontally on the painted markings (``survey_markings``)."""
    from pipeline.parallel import parallel_map
    from stages.posegraph.factors.drive import increments
    from stages.posegraph.loops.candidates import keyframes_by_travel

    with_markings = cfg.use_markings and survey.has_intensity and feature_load is not None
    features_before: dict[tuple[int, int], np.ndarray] = {}  # (drive index, scan index): road features

    def horizontal(keys: np.ndarray, poses: np.ndarray, offsets: np.ndarray) -> list:
        """The marking anchor of every keyframe, in blocks of consecutive keyframes run in parallel. A later
        round's blocks bring the road features the previous round extracted for their scans (exact: features do
        not depend on the estimate), so each scan is read and extracted once per stage, not once per round."""
        from stages.posegraph.anchors.survey_markings import submap_scan_indices

        mk = cfg.markings
        blocks = marking_blocks(keys, offsets, cfg.block)
        items = []
        for o, local in blocks:
            poses_o = poses[offsets[o]:offsets[o + 1]]
            lo = submap_scan_indices(poses_o[:, :3, 3], local[0], mk.half_travel_m, mk.max_scans)[0]
            hi = submap_scan_indices(poses_o[:, :3, 3], local[-1], mk.half_travel_m, mk.max_scans)[-1]
            known = {j: features_before[(o, j)] for j in range(int(lo), int(hi) + 1) if (o, j) in features_before}
            items.append((drives[o], poses_o, increments(drives[o]), local, mk, known))
        step = (lambda done, total: report_step("survey marking anchors", done, total)) if report_step else None
        done = parallel_map(_marking_block, items, workers=cfg.workers(len(keys)), initializer=_use_survey_markings,
                            initargs=(survey, feature_load), progress=step)
        for (o, _), (_, used) in zip(blocks, done):
            features_before.update({(o, j): f for j, f in used.items()})
        return [m for block, _ in done for m in block]

    ground_before: dict[int, SurveyMatch | None] = {}  # the previous round's ground match per keyframe

    def callback(poses: np.ndarray, offsets: np.ndarray) -> list[PosePrior]:
        group = np.repeat(np.arange(len(drives)), np.diff(offsets))
        keys = keyframes_by_travel(poses[:, :3, 3], group, cfg.stride_m)
        # a later round: an accepted vertical-only ground match whose keyframe moved less than round_tol_m is
        # carried over (rematched_vertical); every other keyframe (rejected, uncovered, new) is matched again
        carried: dict[int, SurveyMatch] = {}
        if cfg.ground.vertical_only:
            for g in keys.tolist():
                before = ground_before.get(g)
                if before is not None and (m := rematched_vertical(before, poses[g], cfg.round_tol_m)) is not None:
                    carried[g] = m
        todo = np.asarray([g for g in keys.tolist() if g not in carried], np.int64)
        # the workers hold the survey and read their block's scans: the stage's process holds neither; a keyframe
        # the survey does not cover comes back as None
        items = ground_blocks(todo, poses, offsets, cfg.ground.voxel_m, cfg.ground, cfg.block)
        n = len(todo)
        step = (lambda done, total: report_step("survey anchors", min(done * cfg.block, n), n)) if report_step \
            else None
        blocks = parallel_map(_anchor_block, items, workers=cfg.workers(n), initializer=_use_survey_and_drives,
                              initargs=(survey, cfg.ground.voxel_m, drives, load, cfg.ground.vertical_only),
                              progress=step)
        by_key = dict(zip(todo.tolist(), [m for got in blocks for m in got]))
        by_key.update(carried)
        ground_before.clear()
        ground_before.update(by_key)
        if carried:
            log.info("survey anchors: %d of %d ground matches carried over from the previous round", len(carried),
                     len(keys))
        matches = [by_key[g] for g in keys.tolist() if by_key[g] is not None]
        if with_markings:
            found = horizontal(np.asarray([m.i for m in matches], np.int64), poses, offsets)
            matches = checked_horizontal([replace(m, horizontal=h) for m, h in zip(matches, found)], poses, offsets,
                                         cfg)
        if matches_out is not None:  # the last round's matches
            matches_out[:] = matches
        return survey_priors(matches, yaw_sigma_rad=np.deg2rad(cfg.yaw_sigma_deg))

    return callback


def checked_horizontal(matches: list[SurveyMatch], poses: np.ndarray, offsets: np.ndarray,
                       cfg: AnchorConfig) -> list[SurveyMatch]:
    """Accepted marking matches that disagree with their neighbours (``anchor_consensus``) turned into rejected
    ones, with the reason; the others unchanged."""
    from scipy.stats import chi2

    from stages.posegraph.anchors.anchor_consensus import anchor_consensus
    from stages.posegraph.loops.candidates import travel_m

    acc = [k for k, m in enumerate(matches) if m.horizontal is not None and m.horizontal.accepted]
    if not acc:
        return matches
    travel = travel_m(poses[:, :3, 3], np.repeat(np.arange(len(offsets) - 1), np.diff(offsets)))
    idx = np.asarray([matches[k].i for k in acc], np.int64)
    res = anchor_consensus(np.array([matches[k].horizontal.shift_en_m for k in acc]),
                           np.array([matches[k].horizontal.information_en for k in acc]),
                           np.searchsorted(offsets, idx, side="right") - 1, travel[idx],
                           window_m=cfg.consensus_window_m, drift_sigma_m=cfg.consensus_drift_sigma_m,
                           gate_chi2_1=float(chi2.ppf(cfg.consensus_probability, 1)),
                           gate_chi2_2=float(chi2.ppf(cfg.consensus_probability, 2)))
    out = list(matches)
    for j, k in enumerate(acc):
        if not res.keep[j]:
            h = matches[k].horizontal
            out[k] = replace(matches[k], horizontal=replace(h, accepted=False, information_en=np.zeros((2, 2)),
                                                            reason=res.reason[j]))
    if (~res.keep).any():
        log.info("survey anchors: %d of %d horizontal anchors dropped as inconsistent with their neighbours",
                 int((~res.keep).sum()), len(acc))
    return out
