"""Round trip against the simulator's tiny preset: the Parquet points equal what the simulator wrote."""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest

from pipeline.declare import PartitionKey
from pipeline.testing import make_context
from stages.ingest.compute import compute
from stages.ingest.params import IngestParams

simulate_core = pytest.importorskip("stages.simulate.core", reason="the simulate stage has not landed")
writers = pytest.importorskip("stages.simulate.writers")


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    summary = simulate_core.simulate("tiny", seed=7, out_dir=out, n_drives=1, scan_limit=4)
    return out, summary


def test_simulated_drive_round_trips_exactly(simulated):
    out, summary = simulated
    drive_file = out / "drive_0" / "drive.yaml"
    ctx = make_context("ingest", IngestParams(chunk_size_scans=2), partition=PartitionKey(drive="drive_0"),
                       drives={"drive_0": drive_file}, settings={"enu_origin": summary.enu_origin})
    result = compute(ctx)
    tables = {k: pa.concat_tables([v] if isinstance(v, pa.Table) else list(v))
              for k, v in result.items() if k != "_extra"}
    scans = tables["scans"]
    files = sorted((out / "drive_0" / "scans").glob("*.pcd"))
    assert len(files) == 4 and tables["scan_index"]["status"].to_pylist() == ["ok"] * 4
    for scan_id, path in enumerate(files):
        raw = path.read_bytes()
        records = np.frombuffer(raw[raw.index(b"DATA binary\n") + 12:], writers.PCD_DTYPE)
        finite = np.isfinite(records["x"]) & ~((records["x"] == 0) & (records["y"] == 0) & (records["z"] == 0))
        records = records[finite]
        one = scans.filter(pc.equal(scans["scan_id"], scan_id))
        for ours, theirs in (("x_m", "x"), ("y_m", "y"), ("z_m", "z"), ("intensity", "intensity"),
                             ("time_offset_s", "time")):
            np.testing.assert_array_equal(one[ours].to_numpy(), records[theirs])
        np.testing.assert_array_equal(one["ring"].to_numpy(), records["ring"].astype(np.int16))
    poses = tables["poses_gnss"]
    assert poses.num_rows == 4 and all(poses["valid"].to_pylist())
    assert tables["gnss"].num_rows > 10 and tables["survey"].num_rows > 0
    assert tables["drive_info"]["origin_lat_deg"].to_pylist() == [summary.enu_origin["lat_deg"]]
