"""The tiny synthetic city through the whole workflow: simulate -> ingest -> odometry -> posegraph -> corners ->
cornermap -> markings -> tiles -> evaluate, on the synchronous scheduler and on a dask.distributed LocalCluster."""
from __future__ import annotations

import json
from pathlib import Path

import pyarrow as pa
import pytest

REPO = Path(__file__).resolve().parents[1]


def run(root: Path, scheduler: str):
    from mapservice.cli import execute_workflow

    return execute_workflow(REPO / "workflows" / "tiny.yaml", root=root, scheduler=scheduler, only=None,
                            dry_run=False, quiet=True)


def committed_table(root: Path, dataset: str) -> pa.Table:
    import pyarrow.parquet as pq

    [d] = [p for p in (root / "datasets" / dataset).iterdir() if (p / "_manifest.json").exists()]
    m = json.loads((d / "_manifest.json").read_text())
    t = pa.concat_tables([pq.read_table(d / f["path"]) for f in m["files"]])
    return t.sort_by([(c, "ascending") for c in t.column_names if not pa.types.is_list(t.schema.field(c).type)])


@pytest.fixture(scope="module")
def tiny_sync(tmp_path_factory):
    root = tmp_path_factory.mktemp("tiny_sync")
    return root, run(root, "sync")


def test_whole_workflow_publishes_a_map_and_evaluates_it(tiny_sync):
    root, result = tiny_sync
    assert all(v["decision"] == "ran" for v in result["summary"].values()), result["summary"]
    map_dir = root / "maps" / "tiny"
    latest = (map_dir / "LATEST").read_text().split()[0]
    manifest = json.loads((map_dir / latest / "manifest.json").read_text())
    assert manifest["n_corners"] > 0 and manifest["n_tiles"] > 0
    assert set(manifest["enu_origin"]) >= {"lat_deg", "lon_deg", "h_m"}
    kernel = manifest["corner_error_correlation"]  # the pose graph's own figure, which the EKF then uses
    assert 0.0 <= kernel["share"] < 1.0 and kernel["length_m"] > 0 and kernel["n_pairs"] > 0
    [metrics] = list((root / "datasets" / "eval_report").glob("*/artifacts/*/metrics.json"))
    doc = json.loads(metrics.read_text())
    used = doc["map"]["corner_error_correlation"]
    assert used["from"] == "map" and (used["share"], used["length_m"]) == (kernel["share"], kernel["length_m"])
    assert {"ekf", "mcl", "rtk_ins", "icp_dr"} <= set(doc["methods"])
    assert (metrics.parent / "report.html").stat().st_size > 10_000


def test_second_run_skips_every_stage(tiny_sync):
    root, _ = tiny_sync
    again = run(root, "sync")
    assert {v["decision"] for v in again["summary"].values()} == {"skipped"}


def test_distributed_local_cluster_gives_equal_tables(tiny_sync, tmp_path):
    distributed = pytest.importorskip("distributed")
    root, _ = tiny_sync
    with distributed.LocalCluster(n_workers=2, processes=True, threads_per_worker=1, dashboard_address=None) as cl:
        run(tmp_path, cl.scheduler_address)
    for ds in ("scans_raw", "gnss_enu", "corners_per_scan", "marking_raster"):
        assert committed_table(root, ds).equals(committed_table(tmp_path, ds)), ds
    assert (tmp_path / "maps" / "tiny" / "LATEST").is_file()


def test_a_survey_named_by_both_drives_is_read_once(tiny_sync):
    """Both tiny drive files name the city's survey.las; ingest writes it per drive and records its content hash,
    and the pose graph reads the cloud once (the points of one drive's partition, not of both)."""
    from pipeline.declare import PartitionKey
    from pipeline.execute import _context, _task_spec
    from pipeline.plan import make_plan
    from pipeline.workflow import load_workflow
    from stages.posegraph.compute import read_survey

    root, _ = tiny_sync
    [manifest] = list((root / "datasets" / "survey_enu").glob("*/_manifest.json"))
    parts = json.loads(manifest.read_text())["extra"]["partitions"]
    hashes = {label: extra.get("survey_sha256") for label, extra in parts.items()}
    assert len(hashes) == 2 and len(set(hashes.values())) == 1 and None not in hashes.values(), hashes
    plan = make_plan(load_workflow(REPO / "workflows" / "tiny.yaml"), root)
    ctx = _context(_task_spec(plan, plan.stages["posegraph"]), PartitionKey(), root / "tmp" / "test-survey", {})
    pts, intensity = read_survey(ctx)
    per_drive = ctx.inputs.read("survey", partition=PartitionKey(drive="drive_0"), columns=["east_m"]).num_rows
    assert len(pts) == len(intensity) == per_drive > 0
    assert ctx.inputs.read("survey", columns=["east_m"]).num_rows == 2 * per_drive


def test_loops_verified_from_the_store_in_blocks_equal_those_on_preloaded_clouds(tiny_sync):
    """Loop candidates of the tiny map drive verified as the stage does (each worker reads the clouds of its block of
    candidates itself, so the stage's process never holds them all) give the verdicts of the candidates verified on
    every cloud loaded beforehand (``vehicle_clouds``), in this process and in a pool with blocks of 2."""
    import numpy as np

    from stages.posegraph.compute import scan_loader
    from stages.posegraph.loops.candidates import Candidate, keyframes_by_travel
    from stages.posegraph.loops.clouds import vehicle_clouds
    from stages.posegraph.loops.verify import verify_candidates, verify_from_store
    from tests.stages.posegraph.tiny_setup import pass1_on_tiny

    ctx, drives, cfg, offsets, poses = pass1_on_tiny(tiny_sync[0], REPO / "workflows" / "tiny.yaml", "test-loops",
                                                     {"loops.parallel_min_items": 10_000})
    keys = keyframes_by_travel(poses[:, :3, 3], np.zeros(len(poses), int), 5.0)
    # consecutive keyframes as stand-in candidates (the tiny drive has too few revisits): some pairs overlap,
    # some do not, and scans recur across candidates and blocks
    cands = [Candidate(int(a), int(b), 5.0) for a, b in zip(keys[:-2], keys[2:])][:9] + \
            [Candidate(int(keys[1]), int(keys[0]), 5.0)]
    load = scan_loader(ctx)
    wanted = np.unique([c.i for c in cands] + [c.j for c in cands]).astype(np.int64)
    clouds = vehicle_clouds(drives, offsets, wanted, load, cfg.loops.verify.voxel_m)
    reference = verify_candidates(cands, poses, clouds, cfg.loops)
    pooled = ctx.params.updated({"loops.parallel_min_items": 2}).loops
    for got in (verify_from_store(cands, poses, drives, offsets, load, cfg.loops),
                verify_from_store(cands, poses, drives, offsets, load, pooled, block=2)):
        assert [(r.i, r.j) for r in got] == [(c.i, c.j) for c in cands]
        for a, b in zip(reference, got):
            assert (a.accepted, a.reason) == (b.accepted, b.reason)
            assert a.fitness == pytest.approx(b.fitness, abs=1e-6)
            np.testing.assert_allclose(a.T_i_j, b.T_i_j, atol=1e-6)
    assert any(r.accepted for r in reference)


def test_survey_anchors_in_parallel_processes_equal_the_serial_ones(tiny_sync):
    """The pose graph's survey anchors (ground GICP and marking matches) of the tiny map drive, computed in the
    stage's process and in a process pool in blocks of 3 keyframes: the same matches."""
    import numpy as np

    from stages.posegraph.anchors.survey_anchor import survey_anchor_callback
    from stages.posegraph.compute import SurveySource, scan_loader
    from tests.stages.posegraph.tiny_setup import pass1_on_tiny

    ctx, drives, _, offsets, poses = pass1_on_tiny(tiny_sync[0], REPO / "workflows" / "tiny.yaml", "test-anchors")
    results = []
    for params in (ctx.params.updated({"anchors.parallel_min_items": 10_000}),
                   ctx.params.updated({"anchors.parallel_min_items": 2, "anchors.block": 3})):
        matches: list = []
        survey_anchor_callback(drives, scan_loader(ctx), SurveySource(ctx.inputs),
                               params.anchors, matches,
                               feature_load=scan_loader(ctx, ("intensity", "ring")))(poses, offsets)
        results.append(matches)
    serial, parallel = results
    assert len(serial) == len(parallel) > 3
    assert sum(m.horizontal is not None and m.horizontal.accepted for m in serial) > 0
    for a, b in zip(serial, parallel):
        assert (a.i, a.accepted, a.horizontal.accepted) == (b.i, b.accepted, b.horizontal.accepted)
        np.testing.assert_allclose(a.T_map_vehicle, b.T_map_vehicle, atol=1e-6)
        np.testing.assert_allclose(a.horizontal.shift_en_m, b.horizontal.shift_en_m, atol=1e-6)


class _CountingLoader:
    """A scan loader that counts the scans asked of it (the stage's process only: serial anchors)."""

    def __init__(self, load):
        self.load, self.scans = load, 0

    def __call__(self, requests):
        self.scans += len(requests)
        return self.load(requests)


def test_a_second_anchoring_round_reuses_what_does_not_depend_on_the_estimate(tiny_sync):
    """An anchoring round from an estimate moved 0.36 m reads again only the scans of rejected ground registrations.
    The marking matches equal a fresh first round's from there exactly (a scan's road features do not depend on
    the estimate); the accepted vertical ground anchors are the previous registrations under the new estimate,
    within half their stated std (1 cm, 0.03 deg) of fresh ones."""
    import numpy as np

    from stages.posegraph.anchors.survey_anchor import survey_anchor_callback
    from stages.posegraph.compute import SurveySource, scan_loader
    from tests.stages.posegraph.tiny_setup import pass1_on_tiny

    ctx, drives, cfg, offsets, poses = pass1_on_tiny(tiny_sync[0], REPO / "workflows" / "tiny.yaml", "test-rounds",
                                                     {"anchors.parallel_min_items": 10_000})
    moved = poses.copy()
    moved[:, :2, 3] += [0.3, -0.2]  # what an anchoring round does to a GNSS-level estimate
    ground, features = _CountingLoader(scan_loader(ctx)), _CountingLoader(scan_loader(ctx, ("intensity", "ring")))
    rounds: list = []
    callback = survey_anchor_callback(drives, ground, SurveySource(ctx.inputs), cfg.anchors, rounds,
                                      feature_load=features)
    callback(poses, offsets)
    first, first_matches = (ground.scans, features.scans), list(rounds)
    callback(moved, offsets)
    assert first[0] > 0 and first[1] > 0
    assert features.scans == first[1]  # the second round read no scan for the markings
    # and for the ground only the keyframes whose first registration its gates rejected (matched again)
    assert ground.scans - first[0] == sum(not m.accepted for m in first_matches)
    fresh: list = []
    survey_anchor_callback(drives, scan_loader(ctx), SurveySource(ctx.inputs), cfg.anchors, fresh,
                           feature_load=scan_loader(ctx, ("intensity", "ring")))(moved, offsets)
    assert [m.i for m in rounds] == [m.i for m in fresh] and len(fresh) > 3
    assert sum(m.horizontal.accepted for m in fresh) > 0
    for a, b in zip(rounds, fresh):
        assert (a.accepted, a.horizontal.accepted, a.horizontal.reason) == \
            (b.accepted, b.horizontal.accepted, b.horizontal.reason)
        np.testing.assert_allclose(a.horizontal.shift_en_m, b.horizontal.shift_en_m, atol=1e-9)
        assert a.horizontal.yaw_rad == pytest.approx(b.horizontal.yaw_rad, abs=1e-12)
        if b.accepted:  # a registration's own start dependence, well inside the anchor's stated std
            assert abs(a.T_map_vehicle[2, 3] - b.T_map_vehicle[2, 3]) < 0.5 * cfg.anchors.ground.min_sigma_m
            tilt = np.arccos(np.clip(a.T_map_vehicle[:3, 2] @ b.T_map_vehicle[:3, 2], -1.0, 1.0))
            assert tilt < 0.5 * cfg.anchors.ground.min_sigma_rad


def _short_drive(sim: Path, dest: Path, n_scans: int, *, lat_shift_deg: float = 0.0, odometry: bool = True) -> Path:
    """The first ``n_scans`` of the simulated drive_1 as a drive of its own, its GNSS moved north by
    ``lat_shift_deg`` (0.54 deg = 60 km) and, with ``odometry=False``, no wheel odometry in its drive file."""
    import yaml

    src = sim / "drive_1"
    (dest / "scans").mkdir(parents=True)
    for k in range(n_scans):
        (dest / "scans" / f"{k:06d}.pcd").symlink_to(src / "scans" / f"{k:06d}.pcd")
    stamps = (src / "scans" / "stamps.csv").read_text().splitlines()
    (dest / "scans" / "stamps.csv").write_text("\n".join(stamps[:n_scans + 1]) + "\n")
    lines = (src / "gnss_inspva.csv").read_text().splitlines()
    col = lines[0].split(",").index("latitude_deg")
    rows = [r.split(",") for r in lines[1:]]
    for r in rows:
        r[col] = f"{float(r[col]) + lat_shift_deg:.10f}"
    (dest / "gnss_inspva.csv").write_text("\n".join([lines[0]] + [",".join(r) for r in rows]) + "\n")
    doc = yaml.safe_load((src / "drive.yaml").read_text())
    if odometry:
        (dest / "wheel_gyro.csv").symlink_to(src / "wheel_gyro.csv")
    else:
        doc.pop("odometry")
    doc.pop("survey", None)
    (dest / "drive.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    return dest / "drive.yaml"


def _evaluate(root: Path, *args: str):
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "mapservice", "evaluate", "--root", str(root), "--map", "tiny", "-q",
                           *args], capture_output=True, text=True, cwd=REPO)


def test_evaluate_a_drive_60_km_off_the_map_is_no_coverage(tiny_sync, tmp_path):
    """`cornermap evaluate` on a drive 60 km from the map: exit 3 with a one-line "no coverage" verdict, the
    report written; the truth (simulator frame, stated in its header) is moved into the map's frame."""
    root, _ = tiny_sync
    [sim] = root.glob("datasets/raw_drives/*/artifacts/all")
    drive = _short_drive(sim, tmp_path / "far", 60, lat_shift_deg=0.54)
    res = _evaluate(root, "--drive", str(drive), "--method", "ekf", "--out", str(tmp_path / "eval"),
                    "--reference", str(sim / "truth" / "drive_1_poses_tum.txt"), "--json")
    assert res.returncode == 3, res.stderr
    assert "Traceback" not in res.stderr
    assert "verdict: no coverage: 0% of 60 epochs with a map corner within 60 m" in res.stderr
    doc = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert doc["verdict"]["status"] == "no coverage" and doc["verdict"]["coverage"]["share_associated"] == 0.0
    said = json.loads(res.stdout)  # --json: the verdict on stdout, exit 3 all the same
    assert said["verdict"] == doc["verdict"] and said["map"] == "tiny" and said["report"].endswith("report.html")


def test_evaluate_a_drive_without_wheel_odometry(tiny_sync, tmp_path):
    """No odometry in the drive file: the EKF runs on ICP increments, the MCL on ICP (GNSS/INS where ICP failed),
    one warning line, no traceback; a path to the map folder in --map is a usage error (a map is named)."""
    root, _ = tiny_sync
    [sim] = root.glob("datasets/raw_drives/*/artifacts/all")
    drive = _short_drive(sim, tmp_path / "noodo", 60, odometry=False)
    res = _evaluate(root, "--drive", str(drive), "--out", str(tmp_path / "eval"),
                    "--reference", str(sim / "truth" / "drive_1_poses_tum.txt"))
    assert res.returncode == 0, res.stderr
    assert "Traceback" not in res.stderr
    assert "no wheel odometry; the EKF runs on ICP increments alone" in res.stderr
    doc = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    ekf = doc["methods"]["ekf"]["absolute"]
    assert ekf["all_epochs"]["epochs"] == 60 and doc["methods"]["mcl"]["absolute"]["epochs"] == 60
    assert ekf["epochs"] == 60 - ekf["localized_from_epoch"]  # scored from its first association on
    assert doc["methods"]["ekf"]["absolute"]["rms_2d_m"] < 1.0
    assert doc["verdict"]["coverage"]["ok"]
    a_path = _evaluate(root, "--map", str(root / "maps" / "tiny"), "--drive", str(drive), "--out",
                       str(tmp_path / "e2"))
    assert a_path.returncode == 2 and "is a path; a map is named" in a_path.stderr


@pytest.mark.slow  # the export streams its scans (0.73 GB peak, was 3.4 GB) but takes ~70 s of CPU on tiny
def test_autoware_export_of_tiny_opens_in_open3d_and_its_markings_lie_on_the_paint(tiny_sync, tmp_path):
    """The Autoware folder of the tiny map: PCD cells read by open3d inside their metadata cells, building
    corners of the map standing in the cloud; Lanelet2 OSM nodes on the simulator's painted markings."""
    import xml.etree.ElementTree as ET

    import cv2
    import numpy as np
    import open3d as o3d
    import yaml

    from mapformat.export import export_map
    from mapformat.loader import open_map
    from stages.simulate.markings import city_from_description, marking_truth_features

    root, _ = tiny_sync
    reader = open_map(root / "maps" / "tiny")
    out = tmp_path / "aw"
    export_map(reader, "autoware", out)
    assert yaml.safe_load((out / "map_projector_info.yaml").read_text())["projector_type"] == "LocalCartesian"
    meta = yaml.safe_load((out / "pointcloud_map_metadata.yaml").read_text())
    res = meta.pop("x_resolution")
    assert meta.pop("y_resolution") == res and meta
    clouds = []
    for name, (x0, y0) in meta.items():
        pts = np.asarray(o3d.io.read_point_cloud(str(out / "pointcloud_map" / name)).points)
        assert len(pts) and (pts[:, 0] >= x0).all() and (pts[:, 0] < x0 + res).all()
        assert (pts[:, 1] >= y0).all() and (pts[:, 1] < y0 + res).all()
        clouds.append(pts)
    cloud = np.vstack(clouds)
    from scipy.spatial import cKDTree

    h0 = json.loads((out / "cornermap_export.json").read_text())["frame"]["T_autoware_map"][2][3]
    assert h0 == reader.origin.h_m  # the folder's frame: ENU about the origin at 0 m (Autoware's LocalCartesian)
    walls = cKDTree(cloud[cloud[:, 2] - h0 > 2.0][:, :2])  # building walls, above cars and people
    corners = reader.all_corners()
    d, _ = walls.query(np.column_stack([corners["east_m"].to_numpy(), corners["north_m"].to_numpy()]))
    assert np.median(d) < 0.1 and (d < 0.3).mean() > 0.8, d  # the corner map's corners stand on the cloud's walls

    [city_json] = list((root / "datasets" / "raw_drives").glob("*/artifacts/all/truth/city.json"))
    truth = marking_truth_features(city_from_description(json.loads(city_json.read_text())))
    osm = ET.parse(out / "lanelet2_map.osm").getroot()
    xy = {
        n.get("id"): np.array(
            [float(n.find("tag[@k='local_x']").get("v")), float(n.find("tag[@k='local_y']").get("v"))]
        )
        for n in osm.iter("node")
    }
    kinds = {
        "line_thin": ("lane_solid", "lane_dashed"),
        "stop_line": ("stop_line",),
        "crosswalk_polygon": ("crosswalk",),
    }
    checked: dict[str, int] = {}
    worst: dict[str, float] = {}  # printed (pytest -s): the figures of docs/map-format.md
    for way in osm.iter("way"):
        tags = {t.get("k"): t.get("v") for t in way.iter("tag")}
        if tags["type"] == "virtual":  # a lanelet's boundary where nothing is painted (through an intersection)
            checked["virtual"] = checked.get("virtual", 0) + 1
            continue
        lines = [g for k, g in truth if k in kinds[tags["type"]]]
        nodes = np.array([xy[nd.get("ref")] for nd in way.iter("nd")])
        if tags["type"] == "crosswalk_polygon":  # on the outline of the simulator's painted crosswalk
            outline = painted_outline(city_json.parent, max(lines, key=lambda g: _inside_m(g, nodes.mean(axis=0))))
            signed = np.array([_inside_m(outline, p) for p in nodes])
            sides = sorted(cv2.minAreaRect(nodes[:4].astype(np.float32))[1])
            full = np.allclose(sides, sorted(cv2.minAreaRect(outline.astype(np.float32))[1]), atol=0.3)
            if full:  # every corner within 5 cm of the paint's outline
                assert np.abs(signed).max() <= 0.05, (nodes, signed)
            else:  # partly seen (the raster's coverage cut its stripes): every corner on the paint
                assert signed.min() >= -0.05, (nodes, signed)
            kind = "crosswalk" if full else "crosswalk_partial"
            checked[kind] = checked.get(kind, 0) + 1
            worst[kind] = max(worst.get(kind, 0.0), float(np.abs(signed).max() if full else max(0.0, -signed.min())))
            continue
        for p in nodes:  # on a painted line of its type: within 5 cm across it, at most 0.25 m beyond its ends
            best = np.inf
            for a, b in ((g[0], g[-1]) for g in lines):
                u = (b - a) / np.linalg.norm(b - a)
                s = (p - a) @ u
                beyond = max(0.0, -s, s - np.linalg.norm(b - a))
                if beyond <= 0.25:
                    best = min(best, abs((p - a) @ np.array([-u[1], u[0]])))
            assert best <= 0.05, (tags, p, best)
            worst[tags["type"]] = max(worst.get(tags["type"], 0.0), float(best))
        checked[tags["type"]] = checked.get(tags["type"], 0) + len(nodes)
    print("Lanelet2 nodes vs the paint, worst (m):", {k: round(v, 3) for k, v in sorted(worst.items())})
    assert checked.get("line_thin", 0) >= 10 and checked.get("stop_line", 0) >= 2, checked
    assert checked.get("crosswalk", 0) >= 2, checked
    # the real lanelet2 with the folder's projector: lanelets, and every node on the cloud's road
    lanelet2 = pytest.importorskip("lanelet2")
    from lanelet2.io import Origin
    from lanelet2.projection import LocalCartesianProjector

    o = yaml.safe_load((out / "map_projector_info.yaml").read_text())["map_origin"]
    lmap, errors = lanelet2.io.loadRobust(str(out / "lanelet2_map.osm"),
                                          LocalCartesianProjector(Origin(o["latitude"], o["longitude"], o["altitude"])))
    assert errors == [] and len(lmap.laneletLayer) > 0
    ground = cKDTree(cloud[:, :2])
    dz = []
    for p in lmap.pointLayer:
        near = cloud[ground.query_ball_point([p.x, p.y], 0.3), 2]
        if len(near) >= 3:
            dz.append(p.z - np.median(near[near < near.min() + 0.3]))
    print("Lanelet2 node heights vs the cloud's road (m): median", np.median(dz), "max", np.abs(dz).max())
    assert len(dz) > 50 and np.percentile(np.abs(dz), 95) < 0.05


def _inside_m(polygon, p) -> float:
    """Signed distance (m) of point p to a polygon: positive inside."""
    import cv2
    import numpy as np

    return cv2.pointPolygonTest(np.asarray(polygon, np.float32).reshape(-1, 1, 2), (float(p[0]), float(p[1])), True)


def painted_outline(truth_dir: Path, polygon):
    """Outline of the paint the simulator put down for a marking polygon: the convex hull of the squares of the
    truth raster's painted pixels (truth/markings.png, georeferenced by markings.json) within 0.15 m of it.
    The simulator paints every pixel a polygon's outline touches, so its paint reaches up to one pixel (0.1 m)
    beyond the polygon; the sensor, the raster and the export see this paint."""
    import cv2
    import numpy as np

    meta = json.loads((truth_dir / "markings.json").read_text())
    img = cv2.imread(str(truth_dir / "markings.png"), cv2.IMREAD_GRAYSCALE)
    res, west, north = meta["resolution_m"], meta["west_m"], meta["north_m"]
    lo, hi = np.min(polygon, axis=0) - 0.3, np.max(polygon, axis=0) + 0.3
    c0, r0 = int((lo[0] - west) / res), int((north - hi[1]) / res)
    rows, cols = np.nonzero(img[r0:int((north - lo[1]) / res) + 1, c0:int((hi[0] - west) / res) + 1])
    centres = np.column_stack([west + (cols + c0 + 0.5) * res, north - (rows + r0 + 0.5) * res])
    centres = centres[[_inside_m(polygon, c) >= -0.15 for c in centres]]
    squares = np.vstack([centres + [dx, dy] for dx in (-res / 2, res / 2) for dy in (-res / 2, res / 2)])
    return cv2.convexHull(squares.astype(np.float32))[:, 0, :].astype(float)
