"""Key lookups read only the row groups that can hold the keys, and return what a full filtered read returns."""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest

from pipeline.declare import PartitionKey
from pipeline.errors import DatasetIOError
from pipeline.reader import StoreInputReader


def _write_dataset(root, n_files=3, scans_per_file=10, rows_per_scan=7, row_group_rows=21):
    base = root / "datasets" / "scans" / "fp1"
    files, k = [], 0
    for f in range(n_files):
        drive = "d0" if f < 2 else "d1"
        sid = np.repeat(np.arange(f * scans_per_file, (f + 1) * scans_per_file), rows_per_scan)
        tab = pa.table({"drive": [drive] * len(sid), "scan_id": pa.array(sid, pa.int64()),
                        "x_m": pa.array(np.arange(len(sid), dtype=np.float32) + k, pa.float32())})
        k += len(sid)
        rel = f"data/drive={drive}/chunk={f}/part.parquet"
        (base / rel).parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(tab, base / rel, row_group_size=row_group_rows)
        files.append({"path": rel, "partition": {"drive": drive, "chunk": f}})
    (base / "_manifest.json").write_text(__import__("json").dumps({"fingerprint": "fp1", "files": files}))
    schema = pa.schema([("drive", pa.string()), ("scan_id", pa.int64()), ("x_m", pa.float32())])
    return StoreInputReader(root, {"scans": ("scans", "fp1")}, {"scans": schema})


@pytest.mark.parametrize("row_group_rows", [21, 7])  # 7: one scan a group, taken whole without a filter
@pytest.mark.parametrize("keys", [[3], [0, 9, 10, 29], list(range(0, 30, 4)), [100], []])
def test_read_in_equals_filtered_full_read(tmp_path, keys, row_group_rows):
    reader = _write_dataset(tmp_path, row_group_rows=row_group_rows)
    full = reader.read("scans")
    want = full.filter(pc.is_in(full["scan_id"], value_set=pa.array(keys, pa.int64()))).sort_by("x_m")
    got = reader.read_in("scans", "scan_id", keys).sort_by("x_m")
    assert got.schema == full.schema
    assert got.equals(want)


def test_read_in_reads_only_the_row_groups_holding_the_keys(tmp_path, monkeypatch):
    reader = _write_dataset(tmp_path)
    calls = []
    real = pq.ParquetFile.read_row_group

    def spy(self, i, *a, **kw):
        calls.append(i)
        return real(self, i, *a, **kw)

    monkeypatch.setattr(pq.ParquetFile, "read_row_group", spy)
    got = reader.read_in("scans", "scan_id", [4], columns=["scan_id", "x_m"])
    assert got.column_names == ["scan_id", "x_m"] and got.num_rows == 7
    # scan 4 spans rows 28..34 of file 0: row groups 1 (21..41) only
    assert calls == [1]


def test_read_in_honours_the_partition(tmp_path):
    reader = _write_dataset(tmp_path)
    got = reader.read_in("scans", "scan_id", [5, 25], partition=PartitionKey(drive="d1"))
    assert set(got["scan_id"].to_pylist()) == {25}


def test_read_in_names_a_missing_column(tmp_path):
    reader = _write_dataset(tmp_path)
    with pytest.raises(DatasetIOError, match="no column 'ring'"):
        reader.read_in("scans", "ring", [1])


@pytest.mark.parametrize("run_lengths,min_rows,max_rows", [
    ([5, 5, 5], 4, 100), ([3, 3, 3, 3, 3], 7, 100), ([1] * 40, 8, 100), ([250, 3, 3], 10, 100), ([7], 50, 100),
])
def test_row_group_bounds_end_on_key_changes_and_respect_the_sizes(run_lengths, min_rows, max_rows):
    from pipeline.store import row_group_bounds

    keys = np.repeat(np.arange(len(run_lengths)), run_lengths)
    bounds = row_group_bounds(keys, min_rows, max_rows)
    n = len(keys)
    assert bounds[0] == 0 and bounds[-1] == n and all(b > a for a, b in zip(bounds[:-1], bounds[1:]))
    changes = set(np.flatnonzero(keys[1:] != keys[:-1]) + 1) | {n}
    for a, b in zip(bounds[:-1], bounds[1:]):
        assert b - a <= max_rows
        if b - a < max_rows:  # a group not cut by the maximum ends where the key changes
            assert b in changes
        if b != n and b in changes:
            assert b - a >= min_rows


def test_a_keyed_schema_is_written_in_row_groups_that_read_in_can_skip(tmp_path, monkeypatch):
    """Written by the store with ``row_group_key``: the file round-trips exactly, each row group holds whole
    scans, and a lookup of one scan decodes only groups that hold it."""
    import json

    from pipeline import store
    from pipeline.store import write_pieces

    monkeypatch.setattr(store, "ROW_GROUP_MIN_ROWS", 20)
    schema = pa.schema([("drive", pa.string()), ("scan_id", pa.int64()), ("x_m", pa.float32()),
                        ("info", pa.list_(pa.float64(), 2))], metadata={"row_group_key": "scan_id"})
    rng = np.random.default_rng(3)
    sid = np.repeat(np.arange(12), rng.integers(5, 30, 12))
    n = len(sid)
    table = pa.table({"drive": ["d0"] * n, "scan_id": pa.array(sid, pa.int64()),
                      "x_m": pa.array(rng.normal(size=n).astype(np.float32)),
                      "info": pa.FixedSizeListArray.from_arrays(pa.array(rng.normal(size=2 * n)), 2)}, schema=schema)
    base = tmp_path / "datasets" / "scans" / "fp1"
    files = write_pieces(table, out_dir=base, label="p0", schema=schema, partitioning=("drive",), where="test")
    (base / "_manifest.json").write_text(json.dumps({"fingerprint": "fp1", "files": files}))
    path = base / files[0]["path"]
    assert pq.read_table(path).equals(table)
    meta = pq.ParquetFile(path).metadata
    groups = pq.ParquetFile(path)
    for g in range(meta.num_row_groups):
        ids = groups.read_row_group(g, columns=["scan_id"])["scan_id"].to_numpy()
        assert meta.row_group(g).num_rows >= 20 or g == meta.num_row_groups - 1
        for s in np.unique(ids):  # every scan of the group lies wholly inside it
            assert np.count_nonzero(ids == s) == np.count_nonzero(sid == s)
    assert meta.num_row_groups > 3
    reader = StoreInputReader(tmp_path, {"scans": ("scans", "fp1")}, {"scans": schema})
    calls = []
    real = pq.ParquetFile.read_row_group
    monkeypatch.setattr(pq.ParquetFile, "read_row_group", lambda self, i, *a, **kw: calls.append(i) or
                        real(self, i, *a, **kw))
    got = reader.read_in("scans", "scan_id", [7])
    assert got.num_rows == np.count_nonzero(sid == 7) and len(calls) == 1


def test_read_in_keeps_few_files_open_and_reads_the_same(tmp_path, monkeypatch):
    from pipeline import reader as reader_module

    monkeypatch.setattr(reader_module, "OPEN_FILES", 1)
    reader = _write_dataset(tmp_path, row_group_rows=7)
    full = reader.read("scans")
    for keys in ([1, 12, 25], [25, 1], [12]):
        got = reader.read_in("scans", "scan_id", keys).sort_by("x_m")
        want = full.filter(pc.is_in(full["scan_id"], value_set=pa.array(keys, pa.int64()))).sort_by("x_m")
        assert got.equals(want)
        assert len(reader._parquet_files) == 1


def test_a_one_key_group_with_null_keys_is_still_filtered(tmp_path):
    base = tmp_path / "datasets" / "scans" / "fp1"
    (base / "data").mkdir(parents=True)
    tab = pa.table({"scan_id": pa.array([4, None, 4], pa.int64()), "x_m": pa.array([1.0, 2.0, 3.0], pa.float32())})
    pq.write_table(tab, base / "data" / "part.parquet")
    (base / "_manifest.json").write_text(__import__("json").dumps(
        {"fingerprint": "fp1", "files": [{"path": "data/part.parquet", "partition": {}}]}))
    reader = StoreInputReader(tmp_path, {"scans": ("scans", "fp1")}, {"scans": tab.schema})
    assert reader.read_in("scans", "scan_id", [4])["x_m"].to_pylist() == [1.0, 3.0]
