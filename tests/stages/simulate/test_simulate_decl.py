"""Stage declaration and CLI of simulate."""
from __future__ import annotations

import pytest
from pydantic import ValidationError


def test_declaration_and_params():
    from stages.simulate.decl import STAGE, SimulateParams

    assert STAGE.name == "simulate" and STAGE.outputs == {"drives": "raw_drives"} and STAGE.inputs == {}
    assert STAGE.load_compute().__name__ == "compute"
    p = SimulateParams()
    assert (p.preset, p.seed, p.drives, p.motion_distortion) == ("tiny", 0, None, True)
    with pytest.raises(ValidationError):
        SimulateParams(preset="manhattan")
    with pytest.raises(ValidationError):
        SimulateParams(seeds=3)


def test_unknown_preset_is_a_config_error(tmp_path):
    from pipeline.errors import ConfigError
    from stages.simulate.core import simulate

    with pytest.raises(ConfigError, match="unknown preset 'manhattan'"):
        simulate("manhattan", 0, tmp_path)


def test_cli_writes_a_drive(tmp_path):
    import typer
    from typer.testing import CliRunner

    from stages.simulate.cli import register

    app = typer.Typer()
    register(app)
    app.command("noop")(lambda: None)
    res = CliRunner().invoke(app, ["simulate", "--preset", "tiny", "--out", str(tmp_path), "--drives", "1",
                                   "--max-scans", "2", "--quiet", "--no-motion-distortion"])
    assert res.exit_code == 0, res.output
    assert "drive_0: 2 scans" in res.output
    assert (tmp_path / "drive_0/scans/000001.pcd").is_file() and not (tmp_path / "drive_1").exists()
