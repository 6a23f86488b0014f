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


@pytest.mark.parametrize("keys", [[3], [0, 9, 10, 29], list(range(0, 30, 4)), [100], []])
def test_read_in_equals_filtered_full_read(tmp_path, keys):
    reader = _write_dataset(tmp_path)
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
