"""``cornermap ingest inspect`` on a synthetic PCD with known rings."""
from __future__ import annotations

import numpy as np
import typer
from typer.testing import CliRunner

from fixtures.ingest import make_scan
from stages.ingest.cli import register
from stages.ingest.pcd import write_pcd


def test_inspect_reports_header_and_ring_coverage(tmp_path):
    cols = make_scan(np.random.default_rng(0), n_per_ring=10)
    keep = cols["ring"] != 5  # ring 5 absent
    write_pcd(tmp_path / "s.pcd", {k: v[keep] for k, v in cols.items()}, "binary_compressed")
    app = typer.Typer()
    register(app)
    app.command("noop")(lambda: None)
    result = CliRunner().invoke(app, ["inspect", str(tmp_path / "s.pcd"), "--sensor", "hdl32e"])
    assert result.exit_code == 0, result.output
    assert "PCD binary_compressed" in result.output and "310 points" in result.output
    assert "rings (file): 31 present, missing [5]" in result.output


def test_inspect_says_whether_the_point_times_are_used(tmp_path):
    """Times within the sweep: their span; times of another unit (microseconds as float seconds): not used, and why."""
    cols = make_scan(np.random.default_rng(1), n_per_ring=10)
    n = len(cols["x"])
    app = typer.Typer()
    register(app)
    app.command("noop")(lambda: None)
    for name, time, expected in (
            ("sweep", np.linspace(0.0, 0.1, n), "per-point time 0.000000 .. 0.100000 s from the scan start"),
            ("micro", np.linspace(0.0, 99_000.0, n), "per-point time not used: time of point 1 lies"),
            ("none", None, "no per-point time: the scan is not deskewed")):
        fields = {k: v for k, v in cols.items() if k != "time"}
        if time is not None:
            fields["time"] = time.astype(np.float32)
        write_pcd(tmp_path / f"{name}.pcd", fields, "binary")
        result = CliRunner().invoke(app, ["inspect", str(tmp_path / f"{name}.pcd"), "--sensor", "hdl32e"])
        assert result.exit_code == 0, result.output
        assert expected in result.output, result.output
