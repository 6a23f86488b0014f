"""Issue 22 finding 6 and 5 (PCD part): every per-file problem quarantines that scan with a named reason; the
drive goes on. Each hostile file below failed the whole drive with a bare error, or passed as an "ok" scan."""
from __future__ import annotations

import numpy as np
import pytest

from fixtures.ingest import write_synthetic_drive
from pipeline.errors import FormatError
from stages.ingest.drive_file import load_drive_file
from stages.ingest.lzf import compress_literal_lzf
from stages.ingest.pcd import MAX_DECOMPRESSED_BYTES, decode_pcd, encode_pcd
from stages.ingest.scan_formats import points_from_pcd, read_kitti_bin
from stages.ingest.scan_pass import ScanFile, process_scan
from tests.stages.ingest.test_ingest_compute import _run

HEADER = ("VERSION 0.7\nFIELDS {fields}\nSIZE {sizes}\nTYPE {types}\nCOUNT {counts}\nWIDTH {n}\nHEIGHT 1\n"
          "POINTS {n}\nDATA {enc}\n")


def _header(fields, sizes, types, counts, n, enc="binary") -> bytes:
    j = " ".join
    return HEADER.format(fields=j(fields), sizes=j(map(str, sizes)), types=j(types), counts=j(map(str, counts)),
                         n=n, enc=enc).encode()


def count2_x() -> bytes:  # x has two values per point
    return _header("x y z".split(), [4, 4, 4], "FFF", [2, 1, 1], 3) + np.ones((3, 4), "<f4").tobytes()


def padding_clash() -> bytes:  # a real field named like the reader's old padding name
    return _header("x _pad1 _ y z".split(), [4] * 5, "FFFFF", [1] * 5, 2) + np.ones((2, 5), "<f4").tobytes()


def huge_count_no_points() -> bytes:
    return _header("x y z".split(), [4, 4, 4], "FFF", [1, 1, 10**12], 0)


def points_smaller_than_data() -> bytes:
    data = np.arange(30, dtype="<f4").reshape(10, 3) + 1
    return _header("x y z".split(), [4, 4, 4], "FFF", [1, 1, 1], 4) + data.tobytes()


def all_nan() -> bytes:
    return encode_pcd({"x": np.full(20, np.nan, np.float32), "y": np.zeros(20, np.float32),
                       "z": np.zeros(20, np.float32)})


def compression_bomb() -> bytes:
    """240 MB announced from 4 kB (LZF back references of 264 bytes each): within the point limit, beyond the
    compression-ratio cap."""
    n = 15_000_000
    head = _header("x y z intensity".split(), [4] * 4, "FFFF", [1] * 4, n, "binary_compressed")
    return head + np.array([4096, n * 16], "<u4").tobytes() + b"\x00\x00" + b"\xe0\xff\x00" * 1364


HOSTILE = {"count2_x": (count2_x, "COUNT"), "padding_clash": (padding_clash, None),
           "huge_count": (huge_count_no_points, "limit"), "points_smaller": (points_smaller_than_data, "POINTS"),
           "all_nan": (all_nan, "no valid points"), "bomb": (compression_bomb, "limit")}


def test_hostile_pcd_files_give_named_errors_from_the_reader():
    with pytest.raises(FormatError, match="COUNT"):
        points_from_pcd(decode_pcd(count2_x()))
    cloud = decode_pcd(padding_clash())  # legal: '_' is padding, '_pad1' is a field like any other
    assert set(cloud.columns) == {"x", "_pad1", "y", "z"}
    with pytest.raises(FormatError, match="limit"):
        decode_pcd(huge_count_no_points())
    with pytest.raises(FormatError, match="POINTS is smaller"):
        decode_pcd(points_smaller_than_data())
    with pytest.raises(FormatError, match="decompression bomb"):
        decode_pcd(compression_bomb())
    ok = encode_pcd({"x": np.ones(4, np.float32), "y": np.ones(4, np.float32), "z": np.ones(4, np.float32)})
    assert decode_pcd(ok + bytes(100)).trailing_bytes == 100  # zero padding stays tolerated
    assert MAX_DECOMPRESSED_BYTES < 1 << 30  # the 1 GiB expansion is refused by size alone


def test_every_hostile_scan_is_quarantined_and_the_drive_continues(tmp_path):
    drive = write_synthetic_drive(tmp_path, n_scans=len(HOSTILE) + 1, n_per_ring=5)
    scans = drive.drive_file.parent / "scans"
    for k, (make, _) in enumerate(HOSTILE.values(), start=1):
        (scans / f"{k:06d}.pcd").write_bytes(make())
    tables, _ = _run(drive, drive.origin)
    index = tables["scan_index"][1].to_pylist()
    by_id = {r["scan_id"]: r for r in index}
    assert by_id[0]["status"] == "ok"
    for k, (name, (_, reason)) in enumerate(HOSTILE.items(), start=1):
        row = by_id[k]
        if name == "padding_clash":  # a valid file: read, not quarantined, and without the padding
            assert row["status"] == "ok" and row["n_points"] == 2, row
            continue
        assert row["status"] == "quarantined" and row["reason"], (name, row)
        assert reason in row["reason"], (name, row["reason"])
    assert sorted(tables["scans"][1]["scan_id"].unique().to_pylist()) == [0, 2]


def test_zero_byte_kitti_scan_is_quarantined(tmp_path):
    drive = write_synthetic_drive(tmp_path, n_scans=1, n_per_ring=5)
    spec = load_drive_file(drive.drive_file)
    spec = spec.model_copy(update={"scans": spec.scans.model_copy(update={"format": "kitti_bin"})})
    empty = tmp_path / "0000000000.bin"
    empty.write_bytes(b"")
    assert len(read_kitti_bin(empty)) == 0
    result = process_scan(ScanFile(0, empty, 10**18), spec, 0, 0.0, 0.5)
    assert result.index_row["status"] == "quarantined" and "no valid points" in result.index_row["reason"]
    assert result.points is None


def test_literal_lzf_of_a_normal_scan_is_not_mistaken_for_a_bomb():
    cols = {"x": np.random.default_rng(0).normal(size=5000).astype(np.float32),
            "y": np.zeros(5000, np.float32), "z": np.zeros(5000, np.float32)}
    cloud = decode_pcd(encode_pcd(cols, "binary_compressed"))
    np.testing.assert_array_equal(cloud.columns["x"], cols["x"])
    assert compress_literal_lzf(b"") == b""


def test_a_scan_link_whose_target_is_gone_is_quarantined_not_skipped(tmp_path):
    drive = write_synthetic_drive(tmp_path, n_scans=3, n_per_ring=5)
    scans = drive.drive_file.parent / "scans"
    gone = tmp_path / "elsewhere" / "000001.pcd"
    (scans / "000001.pcd").unlink()
    (scans / "000001.pcd").symlink_to(gone)  # e.g. links into a data folder that was moved
    tables, _ = _run(drive, drive.origin)
    by_id = {r["scan_id"]: r for r in tables["scan_index"][1].to_pylist()}
    assert by_id[1]["status"] == "quarantined" and "No such file" in by_id[1]["reason"], by_id[1]
    assert by_id[0]["status"] == by_id[2]["status"] == "ok"
    report = tables["report"][1].to_pylist()
    assert any(r["kind"] == "quarantined_file" and r["record"] == 1 for r in report)


def test_a_drive_whose_scans_all_fail_is_refused_with_the_folder_and_the_first_reason(tmp_path):
    from pipeline.errors import DataQualityError

    drive = write_synthetic_drive(tmp_path, n_scans=3, n_per_ring=5)
    scans = drive.drive_file.parent / "scans"
    for path in sorted(scans.glob("*.pcd")):
        path.unlink()
        path.symlink_to(tmp_path / "gone" / path.name)
    refused = r"none of the 3 scans in .*scans could be read; first: .*000000\.pcd.*No such"
    with pytest.raises(DataQualityError, match=refused):
        _run(drive, drive.origin)
