"""Where things are never decides what they are: packaged catalog and workflows, relative paths against the
workflow file, fingerprints without locations (a moved workflow + root + drives skip everything; a changed
referenced file does not), and the settings each stage reads."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml

from tests.pipeline.test_engine import decisions, run, toy_stages  # noqa: F401 - the fixture registers toy stages


def write_relative_toy(folder: Path, payload: bytes = b"scan") -> Path:
    """The toy workflow with every path relative to the workflow file; each drive names a data file."""
    (folder / "catalog").mkdir(parents=True)
    (folder / "catalog" / "toy.yaml").write_text(yaml.safe_dump({"datasets": {
        "toy_numbers": {"schema": "tests.pipeline.toy_stages:NUMBERS", "partitioning": ["drive", "chunk"]},
        "toy_squares": {"schema": "tests.pipeline.toy_stages:SQUARES", "partitioning": ["drive", "chunk"]},
        "toy_notes": {"kind": "artifacts"},
        "toy_total": {"schema": "tests.pipeline.toy_stages:TOTAL"}}}))
    for d in ("d0", "d1"):
        (folder / "drives" / d).mkdir(parents=True)
        (folder / "drives" / d / "data.bin").write_bytes(payload)
        (folder / "drives" / d / "drive.yaml").write_text(f"name: {d}\nscans: {{folder: data.bin}}\n")
    wf = {"name": "toy", "catalog": ["catalog"], "root": "out", "scheduler": "sync",
          "drives": [{"name": d, "path": f"drives/{d}/drive.yaml"} for d in ("d0", "d1")],
          "stages": ["numbers", "squares", "total"]}
    (folder / "toy.yaml").write_text(yaml.safe_dump(wf))
    return folder / "toy.yaml"


def test_relative_paths_resolve_against_the_workflow_file_not_the_cwd(tmp_path, monkeypatch):
    wf = write_relative_toy(tmp_path / "project")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    result = run(wf)
    assert set(decisions(result).values()) == {"ran"}
    assert (tmp_path / "project" / "out" / "datasets" / "toy_total").is_dir()
    assert not (elsewhere / "out").exists()


def test_moved_project_skips_every_stage_and_a_changed_drive_file_does_not(tmp_path, monkeypatch):
    wf = write_relative_toy(tmp_path / "a")
    run(wf)
    shutil.move(str(tmp_path / "a"), str(tmp_path / "b"))  # workflow, catalog, drives and root together
    monkeypatch.chdir(tmp_path)
    moved = tmp_path / "b" / "toy.yaml"
    assert set(decisions(run(moved)).values()) == {"skipped"}
    (tmp_path / "b" / "drives" / "d1" / "data.bin").write_bytes(b"scaN")  # same size, new content
    assert decisions(run(moved))["numbers"] == "ran"


def test_packaged_workflows_and_catalog_load_by_name_from_any_folder(tmp_path, monkeypatch):
    from pipeline.errors import ConfigError
    from pipeline.resources import packaged_catalog_dir, packaged_workflows, resolve_workflow

    monkeypatch.chdir(tmp_path)
    assert {"demo", "tiny", "gangnam", "map_rebuild"} <= set(packaged_workflows())
    assert (packaged_catalog_dir() / "datasets.yaml").is_file()
    for ref in ("tiny", "tiny.yaml", "workflows/tiny.yaml"):
        assert resolve_workflow(ref) == packaged_workflows()["tiny"]
    with pytest.raises(ConfigError, match="did you mean 'tiny'"):
        resolve_workflow("tinny")


def test_settings_a_stage_does_not_read_do_not_move_its_fingerprint(tmp_path, monkeypatch):
    """A renamed map re-runs only the stage that publishes (real stages: the packaged tiny workflow)."""
    from pipeline.plan import make_plan
    from pipeline.workflow import load_workflow

    monkeypatch.delenv("CORNERMAP_EXTRA_STAGES", raising=False)
    from pipeline.registry import load_stages

    load_stages.cache_clear()
    wf = load_workflow("tiny")
    renamed = wf.spec.model_copy(update={"map_name": "other"})
    a = make_plan(wf, tmp_path / "r1")
    wf.spec = renamed
    b = make_plan(wf, tmp_path / "r2")  # another root as well
    changed = {n for n in a.stages if a.stages[n].fingerprint != b.stages[n].fingerprint}
    assert changed == {"tiles", "evaluate"}, changed  # evaluate reads the published map


def test_build_origin_is_validated():
    from mapservice.build import parse_origin
    from pipeline.errors import ConfigError

    assert parse_origin("37.5, 127.0, 57") == {"lat_deg": 37.5, "lon_deg": 127.0, "h_m": 57.0}
    for bad in ("37.5,127.0", "north,127,0", "137.5,127,0", "37,200,0"):
        with pytest.raises(ConfigError):
            parse_origin(bad)
