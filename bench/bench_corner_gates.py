"""Where corners are lost, on real scans and simulated drives with the same code: per-scan extraction rates and the
gate that drops each multi-layer cluster, and a built map's corners per km, rejection reasons and precision.

    .venv/bin/python -m bench.bench_corner_gates --kitti [--scans 0:11]        # the 22 KITTI HDL-64E scans
    .venv/bin/python -m bench.bench_corner_gates --nuscenes                    # the nuScenes HDL-32E sweep
    .venv/bin/python -m bench.bench_corner_gates --sim DIR|ROOT [--drive drive_0] [--every 2] [--max-scans 300]
    .venv/bin/python -m bench.bench_corner_gates --map-root ROOT [--drive drive_0]   # a built map (real or simulated)
    .venv/bin/python -m bench.bench_corner_gates --obs-table ROOT   # a simulated map built with cornermap.min_obs 1
    add --param NAME=VALUE (corners params) to any per-scan run

Per scan (``gate_profile``): the extraction is run with its gates switched on one after the other, in the order the
stage applies them (``stages/corners/core.py``): clusters of candidates from >= 2 layers, then the redundancy check
(``min_layers``), the small-structure check (walls), vertex support, the near-corner check, the short-object
check. Each line gives per scan the clusters entering a gate and the share it drops. Simulated scans are deskewed
with the drive's wheel speed and yaw rate as the stage does; with truth, each kept corner is also labelled: a
building corner (``truth/corners.csv`` or a chamfer vertex), a facade-detail corner (``truth/facade_corners.csv``:
an entrance's or a balcony's edge), or other (> 0.5 m from both: a false positive).

A map (``map_profile``): corners of ``corner_map`` per km of the drive's ``poses_optimized``, the rejected clusters
by reason, each kept corner's observations (``corners_per_scan`` placed with ``poses_optimized`` and the drive's
``T_vehicle_lidar``, within ``MATCH_M`` of it with both walls within 12 deg) and their spread, and the
self-consistency between the drive's two halves: the distance between the means of a corner's observations from
the first and from the second half of the scans (for independent halves, the standard error of the whole mean is
about half of it). With a simulator root, the error of each corner against the truth (rigid fit removed: the
frame's error is not the corner's), and each corner's observations placed with the drive's true poses instead
(``truth_false_true_poses``: the extraction and clustering judged apart from the pose graph; a kilometre map that
the GNSS bias bends is off by more than ``MATCH_M`` somewhere whatever the rigid fit).
"""
from __future__ import annotations

import argparse
import copy
import json
from pathlib import Path

import numpy as np

from stages.corners.core import select_scan_layers, trace_corners
from stages.corners.params import CornerParams

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
MATCH_M = 0.5
FRAME_SEARCH_M = 12.0  # largest frame offset a map without a survey is searched for against the truth
GATES = ("redundancy", "walls", "vertex", "near", "short_object")


def gate_steps(params: CornerParams) -> list[CornerParams]:
    """``params`` with its gates switched on one after the other: [all off (>= 2 layers), + redundancy, + walls,
    + vertex, + near, + short object (= params)]."""
    from bench.params_args import nested

    p = params.model_dump()
    gates = ([("clusters", "min_layers")],
             [("checks", "min_wall_length_m"), ("checks", "min_long_wall_length_m"),
              ("checks", "min_obtuse_wall_length_m")],
             [("checks", "max_vertex_gap_spacings")], [("checks", "min_corner_range_m")],
             [("checks", "max_passover_height_m")])
    off = nested({"clusters.min_layers": 2, **{f"{s}.{k}": 0.0 for keys in gates[1:] for s, k in keys}}, p)
    steps = [copy.deepcopy(off)]
    for keys in gates:
        off = nested({f"{s}.{k}": p[s][k] for s, k in keys}, off)
        steps.append(copy.deepcopy(off))
    return [CornerParams.model_validate(s) for s in steps]


def gate_profile(scans, params: CornerParams, labeller=None) -> dict:
    """``scans``: iterable of (points (N, 3), ring (N,), context) -> counts per scan at every gate, and with a
    ``labeller(context, corners) -> labels`` the kept corners by label."""
    steps = gate_steps(params)
    counts, labels, n, layers = np.zeros(len(steps)), {}, 0, None
    candidates = 0.0
    for pts, ring, ctx in scans:
        if layers is None:
            layers = select_scan_layers(pts, ring, params)
        for k, p in enumerate(steps):
            trace = trace_corners(pts, ring, p, layers=layers)
            counts[k] += len(trace.corners)
            if k == 0:
                candidates += len(trace.candidates)
        if labeller is not None and len(trace.corners):
            for lab in labeller(ctx, trace.corners):
                labels[lab] = labels.get(lab, 0) + 1
        n += 1
    per_scan = counts / max(n, 1)
    drops = {g: (1.0 - per_scan[k + 1] / per_scan[k]) if per_scan[k] else float("nan") for k, g in enumerate(GATES)}
    return {"scans": n, "candidates_per_scan": candidates / max(n, 1), "clusters_per_scan": per_scan[0],
            "corners_per_scan": per_scan[-1], "entering_per_scan": dict(zip(GATES, per_scan[:-1])),
            "dropped_share": drops, "labels": labels, "layers": None if layers is None else np.asarray(layers).tolist()}


def print_profile(title: str, prof: dict) -> None:
    print(f"{title}: {prof['scans']} scans, layers {prof['layers']}")
    print(f"  candidates {prof['candidates_per_scan']:.1f}/scan, clusters of >= 2 layers "
          f"{prof['clusters_per_scan']:.2f}/scan -> corners {prof['corners_per_scan']:.2f}/scan")
    print("  gate: clusters entering per scan, share dropped")
    for g in GATES:
        print(f"    {g:13s} {prof['entering_per_scan'][g]:5.2f}  {100 * prof['dropped_share'][g]:5.1f} %")
    if prof["labels"]:
        total = sum(prof["labels"].values())
        print("  kept corners: " + ", ".join(f"{k} {v} ({100 * v / total:.1f} %)" for k, v in
                                            sorted(prof["labels"].items())))


def read_kitti_scan(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A KITTI HDL-64E PCD of ../shared/data: points and ring from point order (the first laser in the file is the
    top one; a new laser starts where the azimuth steps from negative to non-negative; its README)."""
    raw = path.read_bytes()
    end = raw.index(b"DATA binary\n") + len(b"DATA binary\n")
    n = int(next(ln.split()[1] for ln in raw[:end].decode().splitlines() if ln.startswith("POINTS")))
    pts = np.frombuffer(raw, np.float32, count=4 * n, offset=end).reshape(n, 4)[:, :3]
    pts = pts[np.any(pts != 0, axis=1)]
    az = np.arctan2(pts[:, 1], pts[:, 0])
    order_ring = np.cumsum(np.r_[False, (az[:-1] < 0) & (az[1:] >= 0)])
    return pts.astype(np.float64), (order_ring.max() - order_ring).astype(np.int16)


def kitti_scans(data: Path, sl: slice):
    for f in sorted((data / "kitti_raw_0048_city").glob("*.pcd"))[sl]:
        yield (*read_kitti_scan(f), f.stem)


def nuscenes_scans(data: Path):
    for f in sorted((data / "nuscenes_hdl32e_sweep").glob("*.pcd.bin")):
        rec = np.fromfile(f, np.float32).reshape(-1, 5)
        yield rec[:, :3].astype(np.float64), rec[:, 4].astype(np.int16), f.name


class SimDrive:
    """A simulated drive's scans (deskewed to the scan start with its wheel speed and yaw rate, as the stage does)
    and a labeller of corners against the truth."""

    def __init__(self, sim_dir: Path, drive: str):
        import yaml

        from stages.common.records import Trajectory

        self.dir, self.drive = sim_dir, drive
        spec = yaml.safe_load((sim_dir / drive / "drive.yaml").read_text())
        self.T_vl = np.asarray(spec["T_vehicle_lidar"], float)
        odo = np.genfromtxt(sim_dir / drive / spec["odometry"]["file"], delimiter=",", names=True)
        self.odo_t = odo["gps_seconds"] + 604800.0 * odo["gps_week"]
        self.speed, self.yaw_rate = odo["wheel_speed_mps"], odo["yaw_rate_radps"]
        poses = Trajectory.from_tum(sim_dir / "truth" / f"{drive}_poses_tum.txt")
        self.stamp_s, self.T = poses.stamp_s, poses.T
        self.truth_en, self.detail_en = truth_corner_sets(sim_dir)

    def scans(self, every: int, max_scans: int | None):
        from bench.bench_corners import read_pcd_binary
        from stages.common.deskew import deskew_with_wheel

        files = sorted((self.dir / self.drive / "scans").glob("*.pcd"))[:max_scans][::every]
        for f in files:
            rec = read_pcd_binary(f)
            pts = np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(np.float64)
            i = int(f.stem)
            near = np.flatnonzero(np.abs(self.odo_t - self.stamp_s[i] - 0.05) < 0.1)
            pts = deskew_with_wheel(pts, rec["time"].astype(np.float64), self.speed[near], self.yaw_rate[near],
                                    self.T_vl, odo_time_s=self.odo_t[near] - self.stamp_s[i])
            yield pts, rec["ring"].astype(np.int16), i

    def labels(self, scan: int, corners) -> list[str]:
        from scipy.spatial import cKDTree

        M = self.T[scan] @ self.T_vl
        en = (np.column_stack([corners.x_m, corners.y_m, np.zeros(len(corners)), np.ones(len(corners))]) @ M.T)[:, :2]
        d_b = cKDTree(self.truth_en).query(en)[0]
        d_f = cKDTree(self.detail_en).query(en)[0] if len(self.detail_en) else np.full(len(en), np.inf)
        return ["building" if a <= MATCH_M else "facade_detail" if b <= MATCH_M else "other" for a, b in zip(d_b, d_f)]


def truth_corner_sets(sim_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """(building corners incl. chamfer vertices, facade-detail corners) in ENU, (K, 2) each."""
    from bench.bench_cornermap import chamfer_vertices

    truth = np.genfromtxt(sim_dir / "truth" / "corners.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    building = np.vstack([np.column_stack([truth["east_m"], truth["north_m"]]), chamfer_vertices(sim_dir)[0]])
    detail = np.zeros((0, 2))
    path = sim_dir / "truth" / "facade_corners.csv"
    if path.is_file():
        rows = np.genfromtxt(path, delimiter=",", names=True, dtype=None, encoding="utf-8")
        detail = np.column_stack([np.atleast_1d(rows["east_m"]), np.atleast_1d(rows["north_m"])])
    return building, detail


def map_profile(root: Path, drive: str, tables=None) -> dict:
    """Corners per km, rejection reasons, observations, spread and halves self-consistency of a built map
    (``tables``: (corner_map, corner_map_rejected, corners_per_scan) of ``variant_map``; default the root's)."""
    import pyarrow.dataset as ds

    from bench.roots import dataset, read
    from stages.common.records import Extrinsics, pose_matrices

    if tables is None:
        cmap, rejected = read(root, "corner_map"), read(root, "corner_map_rejected")
        obs = dataset(root, "corners_per_scan").to_table(filter=ds.field("drive") == drive)
    else:
        cmap, rejected, obs = tables
    poses = dataset(root, "poses_optimized").to_table(filter=ds.field("drive") == drive).sort_by("scan_id")
    path = np.column_stack([poses["x_m"].to_numpy(), poses["y_m"].to_numpy()])
    km = float(np.sum(np.hypot(*np.diff(path, axis=0).T))) / 1000.0
    reasons: dict[str, int] = {}
    for r in rejected["reason"].to_pylist() if "reason" in rejected.column_names else []:
        for part in r.split("; "):
            reasons[part.split(":")[0]] = reasons.get(part.split(":")[0], 0) + 1
    T_vl = Extrinsics.from_table(read(root, "drive_info", columns=["drive", "T_vehicle_lidar"])).of(drive)
    row = {int(s): k for k, s in enumerate(poses["scan_id"].to_pylist())}
    scan = obs["scan_id"].to_numpy()
    has = np.array([int(s) in row for s in scan], bool)
    T = pose_matrices(poses, np.array([row.get(int(s), 0) for s in scan], np.int64)) @ T_vl
    p = np.column_stack([obs["x_m"].to_numpy(), obs["y_m"].to_numpy(), np.zeros(len(scan)), np.ones(len(scan))])
    en = np.einsum("nij,nj->ni", T, p)[:, :2]
    yaw = np.arctan2(T[:, 1, 0], T[:, 0, 0])
    th = np.column_stack([obs["theta1_rad"].to_numpy() + yaw, obs["theta2_rad"].to_numpy() + yaw])
    c_en = np.column_stack([cmap["east_m"].to_numpy(), cmap["north_m"].to_numpy()])
    c_th = np.column_stack([cmap["theta1_rad"].to_numpy(), cmap["theta2_rad"].to_numpy()])
    sigma = np.sqrt(0.5 * (cmap["cov_ee_m2"].to_numpy() + cmap["cov_nn_m2"].to_numpy()))
    half = np.median(scan) if len(scan) else 0
    true_en = _true_pose_positions(root, drive, scan, p, T_vl)
    spread, halves, n_obs, true_mean = [], [], [], np.full((len(c_en), 2), np.nan)
    for k in range(len(c_en)):
        m = has & (np.hypot(*(en - c_en[k]).T) < MATCH_M) & _walls_agree(th, c_th[k])
        n_obs.append(int(m.sum()))
        if true_en is not None and m.any():
            true_mean[k] = true_en[m].mean(axis=0)
        if m.sum() >= 2:
            spread.append(float(np.sqrt(np.mean(np.sum((en[m] - en[m].mean(0)) ** 2, axis=1)))))
        a, b = m & (scan <= half), m & (scan > half)
        if a.sum() >= 2 and b.sum() >= 2:
            halves.append(float(np.hypot(*(en[a].mean(0) - en[b].mean(0)))))
    out = {"drive_km": round(km, 4), "map_corners": len(c_en),
           "corners_per_km": round(len(c_en) / km, 1) if km > 0 else None,
           "rejected_clusters": rejected.num_rows, "rejected_reasons": reasons, "observations": obs.num_rows,
           "obs_per_corner_median": float(np.median(n_obs)) if n_obs else None,
           "map_sigma_m_median": round(float(np.median(sigma)), 4) if len(sigma) else None,
           "obs_spread_m_median": round(float(np.median(spread)), 4) if spread else None,
           "halves_distance_m_median": round(float(np.median(halves)), 4) if halves else None,
           "halves_distance_m_rms": round(float(np.sqrt(np.mean(np.square(halves)))), 4) if halves else None,
           "halves_n": len(halves)}
    out.update(_truth_error(root, c_en, cmap["n_obs"].to_numpy()))
    if true_en is not None:
        from scipy.spatial import cKDTree

        building, detail = truth_corner_sets(_sim_dir(root))
        ok = np.isfinite(true_mean[:, 0])
        d = cKDTree(np.vstack([building, detail])).query(true_mean[ok])[0]
        out["truth_false_true_poses"] = int(np.sum(d > MATCH_M))
    return out


def _sim_dir(root: Path) -> Path | None:
    from bench.roots import simulator_dir

    try:
        sim = simulator_dir(root)
    except SystemExit:
        return None
    return sim if (sim / "truth" / "corners.csv").is_file() else None


def _true_pose_positions(root: Path, drive: str, scan: np.ndarray, p_lidar: np.ndarray, T_vl: np.ndarray):
    """(N, 2) the observations placed with the simulator's true pose of their scan (None: not a simulator root)."""
    from stages.common.records import Trajectory

    sim = _sim_dir(root)
    if sim is None or not (sim / "truth" / f"{drive}_poses_tum.txt").is_file():
        return None
    T = Trajectory.from_tum(sim / "truth" / f"{drive}_poses_tum.txt").T
    idx = np.clip(scan.astype(np.int64), 0, len(T) - 1)
    return np.einsum("nij,nj->ni", T[idx] @ T_vl, p_lidar)[:, :2]


def obs_threshold_table(root: Path, thresholds=(2, 3, 4, 5, 6, 8, 10)) -> list[dict]:
    """With a simulator root whose corner map was built with a low ``min_obs`` (e.g. 1): per threshold, the map
    corners with at least that many observations, how many of them are true (building or facade-detail corner
    within ``MATCH_M`` after the frame fit) and false: what ``min_obs`` trades."""
    from scipy.spatial import cKDTree

    from bench.roots import read, simulator_dir

    cmap = read(root, "corner_map")
    c_en = np.column_stack([cmap["east_m"].to_numpy(), cmap["north_m"].to_numpy()])
    n_obs = cmap["n_obs"].to_numpy()
    building, detail = truth_corner_sets(simulator_dir(root))
    truth = np.vstack([building, detail]) if len(detail) else building
    fitted = _fit_to_truth(c_en, truth)
    true = cKDTree(truth).query(fitted)[0] <= MATCH_M
    return [{"min_obs": k, "corners": int(np.sum(n_obs >= k)), "true": int(np.sum(true & (n_obs >= k))),
             "false": int(np.sum(~true & (n_obs >= k)))} for k in thresholds]


def _fit_to_truth(c_en: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """The map corners moved onto the truth: the translation matching most corners (over every map corner -> truth
    corner pair within FRAME_SEARCH_M; the frame may be off by the GNSS bias), then two rigid fits on the matches."""
    from scipy.spatial import cKDTree

    tree = cKDTree(truth)
    pairs = tree.query_ball_point(c_en, FRAME_SEARCH_M)
    shifts = np.array([truth[j] - c_en[i] for i, js in enumerate(pairs) for j in js]).reshape(-1, 2)
    if not len(shifts):
        return c_en
    votes = [np.sum(tree.query(c_en + t)[0] <= MATCH_M) for t in shifts]
    fitted = c_en + shifts[int(np.argmax(votes))]
    for radius in (1.0, MATCH_M):
        d, j = tree.query(fitted)
        near = d <= radius
        if near.sum() >= 2:
            R, t = _rigid_fit(c_en[near], truth[j[near]])
            fitted = c_en @ R.T + t
    return fitted


def variant_map(root: Path, drive: str, corner_params: CornerParams | None, map_overrides: dict, scans=None,
                keep_share: float = 1.0, seed: int = 0):
    """The corner map of ``drive`` with other gates, in process: the corners stage's extraction of ``scans`` with
    ``corner_params`` (None: the root's committed corners_per_scan), then the corner map stage on the root's
    optimized poses with ``map_overrides``. ``keep_share`` < 1 keeps that share of the observations, drawn at random
    (``seed``): a simulated drive thinned to a real sensor's lower per-scan extraction rate (independent draws: real
    misses come in runs, behind a parked van, so this is the kinder case for the count gate).
    Returns (corner_map, corner_map_rejected, corners_per_scan) tables."""
    import pyarrow as pa
    import pyarrow.dataset as ds

    from bench.roots import dataset, read
    from pipeline.testing import make_context
    from stages.cornermap.compute import compute
    from stages.cornermap.params import CornerMapParams
    from stages.corners.compute import corners_table
    from stages.corners.core import extract_corners

    if corner_params is None:
        obs = dataset(root, "corners_per_scan").to_table(filter=ds.field("drive") == drive)
    else:
        index = dataset(root, "scan_index").to_table(filter=ds.field("drive") == drive)
        stamp = dict(zip(index["scan_id"].to_pylist(), index["stamp_ns"].to_pylist()))
        ids, stamps, found, layers = [], [], [], None
        for pts, ring, scan_id in scans:
            if layers is None:
                layers = select_scan_layers(pts, ring, corner_params)
            ids.append(int(scan_id))
            stamps.append(int(stamp[int(scan_id)]))
            found.append(extract_corners(pts, ring, corner_params, layers=layers))
        obs = corners_table(drive, 0, ids, stamps, found)
    if keep_share < 1.0:
        obs = obs.filter(pa.array(np.random.default_rng(seed).random(obs.num_rows) < keep_share))
    poses = dataset(root, "poses_optimized").to_table(filter=ds.field("drive") == drive)
    info = read(root, "drive_info")
    ctx = make_context("cornermap", CornerMapParams(**map_overrides),
                       {"corners": obs, "poses": poses, "drive_info": info}, settings={"map_drives": [drive]})
    out = compute(ctx)
    return out["corner_map"], out["rejected"], pa.table(obs)


def _walls_agree(theta: np.ndarray, ref: np.ndarray, tol_rad: float = np.radians(12.0)) -> np.ndarray:
    wrap = lambda a: np.abs((a + np.pi) % (2 * np.pi) - np.pi)  # noqa: E731
    same = np.maximum(wrap(theta[:, 0] - ref[0]), wrap(theta[:, 1] - ref[1]))
    swap = np.maximum(wrap(theta[:, 0] - ref[1]), wrap(theta[:, 1] - ref[0]))
    return np.minimum(same, swap) < tol_rad


def _truth_error(root: Path, c_en: np.ndarray, n_obs: np.ndarray) -> dict:
    """With a simulator root: map corners against the truth (building corners and facade-detail corners), after the
    rigid 2-D fit of the matched corners (the frame's error removed: the map's shape is judged, not its frame)."""
    from scipy.spatial import cKDTree

    from bench.roots import simulator_dir

    try:
        sim = simulator_dir(root)
    except SystemExit:
        return {}
    if not (sim / "truth" / "corners.csv").is_file() or not len(c_en):
        return {}
    building, detail = truth_corner_sets(sim)
    meta = json.loads((sim / "simulation.json").read_text())
    truth = np.vstack([building, detail]) if len(detail) else building
    d, j = cKDTree(truth).query(_fit_to_truth(c_en, truth))
    ok = d <= MATCH_M
    return {"truth_matched": int(ok.sum()), "truth_false": int((~ok).sum()),
            "truth_false_n_obs": sorted(int(v) for v in n_obs[~ok]),
            "truth_on_facade_detail": int(np.sum(ok & (j >= len(building)))),
            "truth_rms_m_after_fit": round(float(np.sqrt(np.mean(d[ok] ** 2))), 4) if ok.any() else None,
            "preset": meta.get("preset"), "seed": meta.get("seed")}


def _rigid_fit(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotation and translation mapping src onto dst (2-D Kabsch)."""
    ms, md = src.mean(0), dst.mean(0)
    u, _, vt = np.linalg.svd((src - ms).T @ (dst - md))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    R = vt.T @ np.diag([1.0, d]) @ u.T
    return R, md - R @ ms


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kitti", action="store_true", help="the KITTI HDL-64E scans of ../shared/data")
    ap.add_argument("--scans", default=":", help="with --kitti: a slice of the 22 scans, e.g. 0:11")
    ap.add_argument("--nuscenes", action="store_true", help="the nuScenes HDL-32E sweep of ../shared/data")
    ap.add_argument("--sim", type=Path, help="a cornermap simulate output folder, or a workflow root that simulated")
    ap.add_argument("--drive", default="drive_0")
    ap.add_argument("--every", type=int, default=1, help="with --sim: every Nth scan")
    ap.add_argument("--max-scans", type=int, default=None)
    ap.add_argument("--map-root", type=Path, help="a workflow root with a built corner map")
    ap.add_argument("--obs-table", type=Path, metavar="ROOT", help="a simulator root whose corner map was built with "
                    "a low cornermap.min_obs: true and false corners per min_obs threshold")
    ap.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", help="a corners param (repeatable)")
    ap.add_argument("--data", type=Path, default=DATA)
    args = ap.parse_args(argv)
    from bench.params_args import nested

    params = CornerParams.model_validate(nested({k: json.loads(v) for k, v in (p.split("=", 1) for p in args.param)}))
    if args.kitti:
        sl = slice(*[int(v) if v else None for v in args.scans.split(":")])
        print_profile(f"KITTI 0048 HDL-64E scans [{args.scans}]", gate_profile(kitti_scans(args.data, sl), params))
    if args.nuscenes:
        print_profile("nuScenes HDL-32E sweep", gate_profile(nuscenes_scans(args.data), params))
    if args.sim:
        if (args.sim / "datasets").is_dir():  # a workflow root: its simulate stage's output
            from bench.roots import simulator_dir

            args.sim = simulator_dir(args.sim)
        sim = SimDrive(args.sim, args.drive)
        print_profile(f"simulated {args.sim} {args.drive} (every {args.every})",
                      gate_profile(sim.scans(args.every, args.max_scans), params, sim.labels))
    if args.map_root:
        print(json.dumps(map_profile(args.map_root, args.drive)))
    if args.obs_table:
        for row in obs_threshold_table(args.obs_table):
            print(json.dumps(row))


if __name__ == "__main__":
    main()
