"""The stage adapter: scans_raw rows -> corners_per_scan rows; params and declaration."""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest
from pydantic import ValidationError

from fixtures.corners import Scene, box_building, cast_scan
from pipeline.declare import Partitioning, PartitionKey
from pipeline.testing import make_context
from schemas.registry import schema_of
from stages.corners.compute import compute
from stages.corners.core import extract_corners
from stages.corners.decl import STAGE
from stages.corners.params import CornerParams

SCENE = Scene([box_building((0.0, 0.0), (12.0, 8.0), yaw_rad=0.4, height_m=14.0),
               box_building((-30.0, 25.0), (10.0, 10.0), yaw_rad=-0.2, height_m=20.0)])
POSES = [(15.0, 14.0, 0.3), (-14.0, 12.0, -0.5), (60.0, -60.0, 0.0)]  # the last sees nothing within range


def scans_table(drive="drive_0", chunk=3):
    cols = {k: [] for k in schema_of("scans_raw").names}
    for i, pose in enumerate(POSES):
        pts, ring = cast_scan(SCENE, pose, seed=i, max_range_m=60.0)
        n = len(pts)
        cols["drive"].append(np.full(n, drive, object))
        cols["chunk"].append(np.full(n, chunk, np.int32))
        cols["scan_id"].append(np.full(n, 100 + i, np.int64))
        cols["stamp_ns"].append(np.full(n, 10**9 * (i + 1), np.int64))
        cols["x_m"].append(pts[:, 0]), cols["y_m"].append(pts[:, 1]), cols["z_m"].append(pts[:, 2])
        cols["intensity"].append(np.zeros(n, np.float32))
        cols["ring"].append(ring)
        cols["time_offset_s"].append(np.linspace(0.0, 0.1, n, dtype=np.float32))
    return pa.Table.from_pydict({k: np.concatenate(v) for k, v in cols.items()}, schema=schema_of("scans_raw"))


def test_compute_matches_per_scan_extraction_and_the_schema(tmp_path):
    table = scans_table()
    # interleave the rows of the scans: compute must group them back
    table = table.take(np.random.default_rng(0).permutation(table.num_rows))
    ctx = make_context("corners", CornerParams(), {"scans": table}, partition=PartitionKey("drive_0", 3),
                       outputs=("corners",), workdir=tmp_path)
    out = compute(ctx)["corners"]
    assert out.schema.equals(schema_of("corners_per_scan"), check_metadata=False)
    assert set(out["drive"].to_pylist()) == {"drive_0"} and set(out["chunk"].to_pylist()) == {3}
    per_scan = {sid: out.filter(pa.compute.equal(out["scan_id"], sid)) for sid in (100, 101, 102)}
    assert per_scan[102].num_rows == 0
    for i, sid in enumerate((100, 101)):
        pts, ring = cast_scan(SCENE, POSES[i], seed=i, max_range_m=60.0)
        ref = extract_corners(pts, ring)
        rows = per_scan[sid]
        assert rows.num_rows == len(ref) >= 1
        assert rows["corner_idx"].to_pylist() == list(range(len(ref)))
        assert set(rows["stamp_ns"].to_pylist()) == {10**9 * (i + 1)}
        got = np.column_stack([rows["x_m"].to_numpy(), rows["y_m"].to_numpy()])
        want = np.column_stack([ref.x_m, ref.y_m])
        d = np.linalg.norm(got[:, None] - want[None], axis=2).min(axis=1)
        assert d.max() < 1e-3  # same corners, up to summation order
        cov = np.stack([rows["cov_xx_m2"].to_numpy(), rows["cov_xy_m2"].to_numpy(), rows["cov_xy_m2"].to_numpy(),
                        rows["cov_yy_m2"].to_numpy()], axis=1).reshape(-1, 2, 2)
        assert np.linalg.eigvalsh(cov).min() >= 0.01 ** 2 * 0.999


def test_only_the_upper_layers_rows_are_read_with_every_column(tmp_path):
    """Memory: the chunk is read whole only for the layer choice (x, y, z, ring); the rows read with every column
    are the chosen layers' alone, and the corners are those of the per-scan extraction on all rows."""
    table = scans_table()
    ctx = make_context("corners", CornerParams(), {"scans": table}, partition=PartitionKey("drive_0", 3),
                       outputs=("corners",), workdir=tmp_path)
    served = []
    read = ctx.inputs.read

    def spy(arg, **kw):
        out = read(arg, **kw)
        served.append((tuple(kw.get("columns") or ()), out))
        return out

    ctx.inputs.read = spy
    out = compute(ctx)["corners"]
    full = [t for cols, t in served if "time_offset_s" in cols]
    assert len(full) == 1
    pts, ring = cast_scan(SCENE, POSES[0], seed=0, max_range_m=60.0)
    upper = set(np.flatnonzero(np.bincount(ring))[::-1][:CornerParams().layers.n_upper_layers].tolist())
    assert set(full[0]["ring"].to_numpy().tolist()) <= upper
    assert full[0].num_rows < 0.5 * table.num_rows
    for i, sid in enumerate((100, 101)):
        pts, ring = cast_scan(SCENE, POSES[i], seed=i, max_range_m=60.0)
        ref = extract_corners(pts, ring)
        rows = out.filter(pa.compute.equal(out["scan_id"], sid))
        np.testing.assert_allclose(rows["x_m"].to_numpy(), ref.x_m, atol=1e-9)
        np.testing.assert_allclose(rows["y_m"].to_numpy(), ref.y_m, atol=1e-9)


def test_compute_on_an_empty_partition_returns_an_empty_table(tmp_path):
    table = scans_table().slice(0, 0)
    ctx = make_context("corners", CornerParams(), {"scans": table}, partition=PartitionKey("drive_0", 0),
                       outputs=("corners",), workdir=tmp_path)
    out = compute(ctx)["corners"]
    assert out.num_rows == 0
    assert out.schema.equals(schema_of("corners_per_scan"), check_metadata=False)


def test_params_reject_unknown_keys_and_inconsistent_values():
    with pytest.raises(ValidationError, match="split_dist"):
        CornerParams(split_dist=0.1)
    with pytest.raises(ValidationError, match="min_range_m"):
        CornerParams(layers={"min_range_m": 90.0, "max_range_m": 80.0})
    with pytest.raises(ValidationError, match="min_layers"):
        CornerParams(layers={"n_upper_layers": 2}, clusters={"min_layers": 3})
    with pytest.raises(ValidationError, match="interior"):
        CornerParams(candidates={"min_interior_angle_deg": 120.0, "max_interior_angle_deg": 100.0})


def test_every_param_documents_its_unit_and_the_declaration_is_consistent():
    for section in CornerParams.model_fields.values():
        for name, field in section.annotation.model_fields.items():
            assert field.description and "[" in field.description or name == "layer_selection", name
    assert STAGE.name == "corners" and STAGE.partition is Partitioning.PER_SCAN_CHUNK
    assert STAGE.inputs["scans"] == "scans_raw" and STAGE.outputs == {"corners": "corners_per_scan"}
    assert set(STAGE.inputs) - STAGE.optional_inputs == {"scans"}
    assert STAGE.load_compute() is compute


@pytest.mark.parametrize("odo_step_ns", [10**7, 10**9])  # 100 Hz samples, and 1 Hz (interpolated)
def test_compute_deskews_with_odometry_when_it_is_available(tmp_path, odo_step_ns):
    box = SCENE.buildings[0]
    pose, speed, yaw_rate = (22.0 * np.cos(0.4 + np.pi / 4), 22.0 * np.sin(0.4 + np.pi / 4), -2.0), 9.0, 0.35
    pts, ring, t = cast_scan(Scene([box]), pose, speed_mps=speed, yaw_rate_radps=yaw_rate, seed=5, return_time=True)
    n = len(pts)
    scans = pa.Table.from_pydict({
        "drive": ["d"] * n, "chunk": np.zeros(n, np.int32), "scan_id": np.zeros(n, np.int64),
        "stamp_ns": np.full(n, 10**9, np.int64), "x_m": pts[:, 0], "y_m": pts[:, 1], "z_m": pts[:, 2],
        "intensity": np.zeros(n, np.float32), "ring": ring, "time_offset_s": t}, schema=schema_of("scans_raw"))
    stamps = np.arange(0, 3 * 10**9, odo_step_ns, dtype=np.int64)
    odo = pa.Table.from_pydict({"drive": ["d"] * len(stamps), "stamp_ns": stamps,
                                "speed_mps": np.full(len(stamps), speed),
                                "yaw_rate_radps": np.full(len(stamps), yaw_rate)}, schema=schema_of("odometry_raw"))

    def errors(tables):
        ctx = make_context("corners", CornerParams(), tables, partition=PartitionKey("d", 0), workdir=tmp_path)
        out = compute(ctx)["corners"]
        x, y, yaw = pose
        c, s = np.cos(yaw), np.sin(yaw)
        xw = x + c * out["x_m"].to_numpy() - s * out["y_m"].to_numpy()
        yw = y + s * out["x_m"].to_numpy() + c * out["y_m"].to_numpy()
        return np.linalg.norm(np.column_stack([xw, yw])[:, None] - box.footprint_xy_m[None], axis=2).min(axis=1)

    fixed = errors({"scans": scans, "odometry": odo})
    assert len(fixed) >= 1 and fixed.max() < 0.02
    raw = errors({"scans": scans})
    assert len(raw) == 0 or raw.max() > 0.1
    # odometry in another time base (e.g. seconds of week vs full GPS time) must not be used: same as without it
    shifted = odo.set_column(1, "stamp_ns", pa.array(stamps + 10**15))
    np.testing.assert_array_equal(errors({"scans": scans, "odometry": shifted}), raw)
