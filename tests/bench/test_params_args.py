"""Dotted params overrides on a bench's command line reach the right section, and a merge keeps a section's other
fields."""

from __future__ import annotations

from bench.params_args import merged, nested
from stages.corners.params import CornerParams
from stages.evaluate.params import EvaluateParams


def test_dotted_keys_build_the_nested_params():
    p = EvaluateParams.model_validate(nested({"ekf.map.consider": False, "methods": ["ekf"]}))
    assert p.ekf.map.consider is False and p.methods == ["ekf"] and p.ekf.map.cov_scale == 1.0
    base = CornerParams(clusters={"min_layers": 4}).model_dump()
    c = CornerParams.model_validate(nested({"checks.min_corner_range_m": 0.0}, base))
    assert (c.clusters.min_layers, c.checks.min_corner_range_m) == (4, 0.0)
    assert base["checks"]["min_corner_range_m"] == 8.0  # the base is not changed


def test_a_merge_keeps_the_other_fields_of_a_section():
    workflow = {"targets": {"ekf_rms_2d_m": 0.15}, "methods": ["ekf", "mcl"]}
    out = merged(workflow, {"targets": {"ekf_p99_2d_m": 0.3}, "methods": ["ekf"]})
    assert out == {"targets": {"ekf_rms_2d_m": 0.15, "ekf_p99_2d_m": 0.3}, "methods": ["ekf"]}
    assert workflow == {"targets": {"ekf_rms_2d_m": 0.15}, "methods": ["ekf", "mcl"]}
