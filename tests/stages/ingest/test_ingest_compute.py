"""The ingest compute on synthetic drives with known truth: exact round trip, poses, bad input handling."""
from __future__ import annotations

import csv

import numpy as np
import pyarrow as pa
import pytest
from scipy.spatial.transform import Rotation

from fixtures.ingest import write_synthetic_drive
from pipeline.declare import PartitionKey
from pipeline.testing import make_context
from schemas import SCHEMAS
from stages.ingest.compute import compute
from stages.ingest.origin import resolve_enu_origin
from stages.ingest.params import IngestParams
from stages.ingest.pcd import write_pcd


def _run(drive, origin=None, **params):
    ctx = make_context("ingest", IngestParams(**params), partition=PartitionKey(drive="drive_0"),
                       drives={"drive_0": drive.drive_file},
                       settings={"enu_origin": origin.as_dict() if origin else None})
    out = compute(ctx)
    tables = {}
    for key, value in out.items():
        if key != "_extra":
            pieces = [value] if isinstance(value, pa.Table) else list(value)
            for piece in pieces:
                assert piece.schema.equals(pieces[0].schema)
            tables[key] = (pieces, pa.concat_tables(pieces))
    return tables, out["_extra"]


@pytest.mark.parametrize("encoding", ["binary", "binary_compressed", "ascii"])
def test_synthetic_drive_round_trips_exactly(tmp_path, encoding):
    drive = write_synthetic_drive(tmp_path, n_scans=5, encoding=encoding, n_per_ring=20)
    tables, extra = _run(drive, drive.origin, chunk_size_scans=2)
    pieces, scans = tables["scans"]
    assert [p["chunk"].unique().to_pylist() for p in pieces] == [[0], [1], [2]]
    assert scans.schema.equals(SCHEMAS["scans_raw"], check_metadata=True)
    for i, cols in enumerate(drive.scans):
        one = scans.filter(pa.compute.equal(scans["scan_id"], i))
        for ours, theirs in (("x_m", "x"), ("y_m", "y"), ("z_m", "z"), ("intensity", "intensity"),
                             ("time_offset_s", "time")):
            np.testing.assert_array_equal(one[ours].to_numpy(), cols[theirs])
        np.testing.assert_array_equal(one["ring"].to_numpy(), cols["ring"].astype(np.int16))
        assert set(one["stamp_ns"].to_pylist()) == {int(drive.scan_stamps_ns[i])}
    index = tables["scan_index"][1]
    assert index["status"].to_pylist() == ["ok"] * 5 and index["rings_present"].to_pylist() == [32] * 5
    assert extra["enu_origin"]["lat_deg"] == drive.origin.lat_deg


def test_poses_follow_the_truth_with_lever_arm(tmp_path):
    drive = write_synthetic_drive(tmp_path, n_scans=6, n_per_ring=5)
    tables, _ = _run(drive, drive.origin)
    poses = tables["poses_gnss"][1]
    assert poses["valid"].to_pylist() == [True] * 6
    # truth at the scan stamps (constant speed and yaw rate: the arc interpolated between 10 ms fixes)
    from fixtures.ingest import vehicle_truth

    t_s = (drive.scan_stamps_ns - drive.gnss_stamps_ns[0]) / 1e9
    xyz, yaw = vehicle_truth(t_s)
    got = np.column_stack([poses[c].to_numpy() for c in ("x_m", "y_m", "z_m")])
    np.testing.assert_allclose(got, xyz, atol=2e-4)  # chord error of 10 ms linear interpolation on the arc
    got_yaw = Rotation.from_quat(np.column_stack([poses[c].to_numpy() for c in ("qx", "qy", "qz", "qw")]))
    np.testing.assert_allclose(got_yaw.as_euler("ZYX")[:, 0], yaw, atol=1e-8)
    gnss = tables["gnss"][1]
    np.testing.assert_allclose(gnss["east_m"].to_numpy(), drive.vehicle_xyz_enu_m[:, 0], atol=1e-6)
    np.testing.assert_allclose(gnss["up_m"].to_numpy(), drive.vehicle_xyz_enu_m[:, 2], atol=1e-6)


def test_bad_scans_are_quarantined_and_the_drive_continues(tmp_path):
    drive = write_synthetic_drive(tmp_path, n_scans=5, n_per_ring=10)
    scans_dir = drive.drive_file.parent / "scans"
    (scans_dir / "000001.pcd").write_bytes((scans_dir / "000001.pcd").read_bytes()[:-50])  # truncated
    (scans_dir / "000003.pcd").write_bytes(b"\x89garbage\x00" * 20)
    cols = dict(drive.scans[4])
    cols["x"] = cols["x"].copy()
    cols["x"][:3] = [np.nan, np.inf, 0.0]
    cols["y"] = cols["y"].copy()
    cols["y"][2] = 0.0
    cols["z"] = cols["z"].copy()
    cols["z"][2] = 0.0
    write_pcd(scans_dir / "000004.pcd", cols)
    with open(scans_dir / "stamps.csv", "a", newline="") as fh:  # a listed scan whose file is missing
        csv.writer(fh).writerow([5, "345600.55", 2200])
    tables, _ = _run(drive, drive.origin)
    index = tables["scan_index"][1].to_pylist()
    assert [r["status"] for r in index] == ["ok", "quarantined", "ok", "quarantined", "ok", "quarantined"]
    assert "truncated binary data" in index[1]["reason"] and "missing" in index[5]["reason"]
    assert index[4]["n_dropped_nonfinite"] == 2 and index[4]["n_dropped_zero"] == 1
    assert index[4]["n_points"] == 320 - 3
    assert tables["scans"][1]["scan_id"].unique().to_pylist() == [0, 2, 4]
    report = tables["report"][1].to_pylist()
    kinds = sorted(r["kind"] for r in report)
    assert kinds == ["dropped_points", "dropped_points", "quarantined_file", "quarantined_file", "quarantined_file"]
    assert tables["drive_info"][1]["n_quarantined"].to_pylist() == [3]


def test_gnss_gap_and_timestamp_problems_are_reported(tmp_path):
    drive = write_synthetic_drive(tmp_path, n_scans=6, n_per_ring=5)
    gnss_file = drive.drive_file.parent / "gnss_inspva.csv"
    lines = gnss_file.read_text().splitlines()
    header, rows = lines[0], lines[1:]
    rows = rows[:5] + [rows[4]] + rows[5:20] + rows[45:]  # a duplicate at record 5, a 0.25 s gap
    gnss_file.write_text("\n".join([header] + rows) + "\n")
    tables, _ = _run(drive, drive.origin, gnss_gap_s=0.2)
    report = tables["report"][1].to_pylist()
    assert {(r["kind"], r["record"]) for r in report} == {("timestamp", 5), ("gnss_gap", 20)}
    poses = tables["poses_gnss"][1]
    assert False in poses["valid"].to_pylist()


def test_outputs_agree_whatever_order_they_are_consumed(tmp_path):
    drive = write_synthetic_drive(tmp_path, n_scans=3, n_per_ring=5)
    ctx = make_context("ingest", IngestParams(), partition=PartitionKey(drive="drive_0"),
                       drives={"drive_0": drive.drive_file})
    out = compute(ctx)
    index_first = list(out["scan_index"])[0]
    scans = pa.concat_tables(list(out["scans"]))
    assert index_first["n_points"].to_pylist() == [160, 160, 160] and scans.num_rows == 480
    assert list(out["report"])[0].num_rows == 0


def test_origin_from_the_first_drive_with_gnss(tmp_path):
    a = write_synthetic_drive(tmp_path, "drive_a", n_scans=1, n_per_ring=2)
    b = write_synthetic_drive(tmp_path, "drive_b", n_scans=1, n_per_ring=2, origin=a.origin.__class__(1, 2, 3))
    first = resolve_enu_origin(None, [a.drive_file, b.drive_file])
    assert first == resolve_enu_origin(None, [a.drive_file]) != resolve_enu_origin(None, [b.drive_file])
    assert resolve_enu_origin({"lat_deg": 1, "lon_deg": 2, "h_m": 3}, [a.drive_file]).h_m == 3.0


def test_gnss_that_does_not_overlap_the_scans_is_reported_and_fails_drive_check(tmp_path):
    """Issue 22 finding 7: GNSS a day away from the scans left 0 valid poses with nothing in the report."""
    from stages.ingest.drive_check import check_drive

    drive = write_synthetic_drive(tmp_path)
    stamps = drive.drive_file.parent / "scans" / "stamps.csv"
    rows = list(csv.reader(stamps.open()))
    stamps.write_text("\n".join([",".join(rows[0])] + [f"{r[0]},{float(r[1]) + 86_400:.9f},{r[2]}"
                                                        for r in rows[1:]]) + "\n")
    tables, _ = _run(drive, drive.origin)
    report = tables["report"][1].to_pylist()
    coverage = [r for r in report if r["kind"] == "gnss_coverage"]
    assert coverage and coverage[0]["count"] == 6 and "0 of 6 scan stamps" in coverage[0]["reason"]
    assert not any(tables["poses_gnss"][1]["valid"].to_pylist())
    check = check_drive(drive.drive_file)
    assert any("no scan stamp lies inside the GNSS time span" in p for p in check.problems), check.problems
