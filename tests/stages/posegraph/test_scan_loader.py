"""The pose graph's scan loader returns each requested scan's own float64 arrays, equal to a plain filtered read,
whether the store's rows come in scan order or not."""
from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from pipeline.reader import StoreInputReader
from stages.posegraph.compute import ScanLoader

SCHEMA = pa.schema([("drive", pa.string()), ("scan_id", pa.int64()), ("x_m", pa.float32()), ("y_m", pa.float32()),
                    ("z_m", pa.float32()), ("time_offset_s", pa.float32()), ("intensity", pa.float32()),
                    ("ring", pa.int16())])


def _store(root, shuffled: bool) -> tuple[StoreInputReader, pa.Table]:
    rng = np.random.default_rng(2)
    sid = np.repeat(np.arange(20), rng.integers(3, 12, 20))
    n = len(sid)
    toff = rng.uniform(0, 0.1, n).astype(np.float32)
    toff[sid == 5] = 0.0  # a scan without per-point time
    table = pa.table({"drive": ["d0"] * n, "scan_id": pa.array(sid, pa.int64()),
                      **{c: pa.array(rng.normal(0, 30, n).astype(np.float32)) for c in ("x_m", "y_m", "z_m")},
                      "time_offset_s": pa.array(toff), "intensity": pa.array(rng.uniform(0, 100, n).astype(np.float32)),
                      "ring": pa.array(rng.integers(0, 32, n).astype(np.int16))}, schema=SCHEMA)
    if shuffled:
        table = table.take(pa.array(rng.permutation(n)))
    base = root / "datasets" / "scans" / "fp1"
    rel = "data/drive=d0/part.parquet"
    (base / rel).parent.mkdir(parents=True)
    pq.write_table(table, base / rel, row_group_size=16)
    (base / "_manifest.json").write_text(json.dumps({"fingerprint": "fp1",
                                                     "files": [{"path": rel, "partition": {"drive": "d0"}}]}))
    return StoreInputReader(root, {"scans": ("scans", "fp1")}, {"scans": SCHEMA}), table


@pytest.mark.parametrize("shuffled", [False, True])
def test_each_scan_equals_a_filtered_read(tmp_path, shuffled):
    reader, table = _store(tmp_path, shuffled)
    wanted = [1, 5, 6, 13, 19]
    got = ScanLoader(reader, ("intensity", "ring"))([("d0", s) for s in wanted])
    assert sorted(got) == [("d0", s) for s in wanted]
    for s in wanted:
        rows = table.filter(pa.compute.equal(table["scan_id"], s))
        xyz, toff, intensity, ring = got[("d0", s)]
        assert xyz.dtype == np.float64 and xyz.flags.c_contiguous
        want_xyz = np.column_stack([rows[c].to_numpy().astype(np.float64) for c in ("x_m", "y_m", "z_m")])
        np.testing.assert_array_equal(xyz, want_xyz)  # in the stored order (a stable sort when shuffled)
        if s == 5:
            assert toff is None
        else:
            np.testing.assert_array_equal(toff, rows["time_offset_s"].to_numpy().astype(np.float64))
        np.testing.assert_array_equal(intensity, rows["intensity"].to_numpy())
        np.testing.assert_array_equal(ring, rows["ring"].to_numpy())
