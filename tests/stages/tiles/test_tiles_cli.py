"""`cornermap tiles ls|diff|export|verify` through typer's runner (the same functions the root app registers)."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from pipeline.errors import ChecksumError, UnknownNameError
from stages.tiles.cli import register
from tests.stages.tiles.tiles_synth import publish_two_versions


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return publish_two_versions(tmp_path_factory.mktemp("cli"))


@pytest.fixture(scope="module")
def app():
    app = typer.Typer()
    register(app)
    return app


def _run(app, *args):
    return CliRunner().invoke(app, ["tiles", *args], catch_exceptions=True)


def test_ls_lists_versions_with_latest_marked(app, root):
    res = _run(app, "ls", "--root", str(root))
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    assert "LATEST = v0002" in lines[0]
    assert lines[1].startswith("  v0001") and lines[2].startswith("* v0002") and "parent=v0001" in lines[2]


def test_diff_json_and_text(app, root):
    res = _run(app, "diff", "v1", "LATEST", "--root", str(root), "--map", "city", "--json")
    assert res.exit_code == 0, res.output
    doc = json.loads(res.output)
    assert [(t["i"], t["j"], t["corners_removed"], t["corners_added"]) for t in doc["tiles"]] == [(0, 0, 4, 0)]
    res = _run(app, "diff", "v1", "v2", "--root", str(root))
    assert "tile (0,0): +0 -4 ~0 corners" in res.output and "total: +0 -4 ~0 corners, 0 marking px" in res.output


def test_export_and_verify(app, root, tmp_path):
    out = tmp_path / "c.geojson"
    res = _run(app, "export", "--format", "geojson", "--out", str(out), "--root", str(root), "--map-version", "v1")
    assert res.exit_code == 0 and out.is_file()
    res = _run(app, "export", "--format", "shapefile", "--out", str(out), "--root", str(root))
    assert res.exit_code != 0 and "shapefile" in res.output
    rasters = tmp_path / "rasters"  # a folder of many files: one line, and every file with --json
    res = _run(app, "export", "-f", "geotiff", "-o", str(rasters), "--root", str(root), "--json")
    assert res.exit_code == 0, res.output
    files = json.loads(res.output)["files"]
    assert len(files) > 3 and all(Path(f).is_file() and Path(f).is_relative_to(rasters) for f in files)
    res = _run(app, "export", "-f", "geotiff", "-o", str(tmp_path / "again"), "--root", str(root))
    wrote = [line for line in res.output.splitlines() if line.startswith("wrote")]  # (progress lines beside)
    assert res.exit_code == 0 and len(wrote) == 1, res.output
    assert wrote[0].startswith(f"wrote {len(files)} files under {tmp_path / 'again'}: "), res.output
    res = _run(app, "verify", "--all", "--root", str(root))
    assert res.exit_code == 0 and "v0001: ok" in res.output and "v0002: ok" in res.output


def test_verify_flags_a_flipped_byte(app, root, tmp_path):
    import shutil

    copy = tmp_path / "root"
    shutil.copytree(root, copy)
    target = copy / "maps" / "city" / "v0002" / "tiles" / "0_0" / "marking_mask.png"
    data = bytearray(target.read_bytes())
    data[100] ^= 0xFF
    target.write_bytes(bytes(data))
    res = _run(app, "verify", "--root", str(copy))
    assert isinstance(res.exception, ChecksumError) and res.exception.exit_code == 1
    assert "v0002: 1 problem(s)" in res.output and "tiles/0_0/marking_mask.png" in res.output


def test_unknown_map_suggests(app, root):
    res = _run(app, "ls", "--root", str(root), "--map", "citty")
    assert isinstance(res.exception, UnknownNameError) and "did you mean 'city'" in str(res.exception)
