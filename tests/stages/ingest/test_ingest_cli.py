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
