"""Params overrides with sections: a dotted key is a section's key, a ``--params`` file merges into the workflow's
params section by section, an old flat key in a workflow is refused naming its new place, and the stage's params
listing shows the sections."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.declare import merged, nested
from pipeline.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]


def test_dotted_keys_nest_and_merge_with_nested_ones():
    assert nested({"loops.radius_m": 20, "loops": {"stride_m": 4}, "loops.wide.enabled": False, "x": 1}) == {
        "loops": {"radius_m": 20, "stride_m": 4, "wide": {"enabled": False}},
        "x": 1,
    }
    assert merged({"a": {"b": 1, "c": 2}, "d": 3}, {"a": {"c": 5}, "d": {"e": 1}}) == {
        "a": {"b": 1, "c": 5},
        "d": {"e": 1},
    }


def _workflow(tmp_path: Path, params: str) -> Path:
    text = (REPO / "workflows" / "tiny.yaml").read_text()
    path = tmp_path / "wf.yaml"
    path.write_text(text.replace("params:\n", f"params:\n{params}"))
    return path


def test_a_params_file_merges_into_the_workflows_sections(tmp_path):
    from pipeline.workflow import load_workflow

    wf = load_workflow(
        _workflow(tmp_path, "  posegraph: {loops: {stride_m: 4.0}, gnss.every_s: 0.5}\n"),
        param_overrides={"posegraph": {"loops.radius_m": 20.0}, "odometry": {"icp.max_corr_m": 0.8}},
    )
    pg, odo = wf.params["posegraph"], wf.params["odometry"]
    assert (pg.loops.stride_m, pg.loops.radius_m, pg.gnss.every_s, odo.icp.max_corr_m) == (4.0, 20.0, 0.5, 0.8)


def test_an_old_flat_key_in_a_workflow_names_its_new_place(tmp_path):
    from pipeline.workflow import load_workflow

    with pytest.raises(ConfigError) as err:
        load_workflow(_workflow(tmp_path, "  posegraph: {loop_radius_m: 20.0}\n"))
    assert "'loop_radius_m' has moved: write it as 'loops.radius_m'" in str(err.value)


def test_the_stage_params_listing_shows_the_sections():
    from pipeline.engine_cli import format_params
    from pipeline.registry import get_stage

    text = format_params(get_stage("posegraph"))
    loops = text[text.index("\nloops: # loop closures\n") : text.index("\nanchors:")]
    assert "\n  radius_m: 12.0 # " in loops and "\n  wide:\n    enabled: True" in loops


@pytest.mark.parametrize("text, expected", [
    ("posegraph:\n  loop_radius_m: 20\n",
     "params of 'posegraph': 'loop_radius_m' has moved: write it as 'loops.radius_m'"),
    ("posegraph:\n  loops:\n    radus_m: 20\n",
     "params of 'posegraph': loops: unknown key 'radus_m' (did you mean 'radius_m'?)"),
    ("posegrph:\n  x: 1\n", "unknown stage 'posegrph' (did you mean 'posegraph'?)"),
])
def test_a_params_files_problem_names_that_file_not_the_workflow(tmp_path, text, expected):
    """Run as a process from a folder outside the checkout: one line naming the --params file, exit 1."""
    import subprocess
    import sys

    (tmp_path / "p.yaml").write_text(text)
    res = subprocess.run([sys.executable, "-m", "mapservice", "run", "tiny", "--root", str(tmp_path / "r"),
                          "--params", "p.yaml", "--dry-run"], cwd=tmp_path, capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 1, res.stderr
    assert f"p.yaml: {expected}" in res.stderr and "tiny.yaml" not in res.stderr and "Traceback" not in res.stderr
