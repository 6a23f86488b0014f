"""Every posegraph param reaches the algorithm's config sections (a param that changes nothing is a lie), each
into the section of its step, and the sections carry the params' values unchanged."""
from __future__ import annotations

import pytest

from stages.posegraph.config import PosegraphConfig
from stages.posegraph.params import PosegraphParams

CHANGED = {"span_edge_kernel": "cauchy", "gnss_kernel": "cauchy", "loop_kernel": "gnc", "prior_kernel": "cauchy",
           "gnss_lever_arm_m": (0.1, -0.2, 1.5), "icp_edge_sigma_along_m": 0.005,
           "icp_edge_sigma_cross_m": 0.005, "icp_edge_sigma_yaw_deg": 0.03}
# the section each param's prefix belongs to (the first match wins)
SECTION = [("wheel_", "factors"), ("failed_edge_", "factors"), ("span_edge", "factors"), ("gnss_", "gnss"),
           ("attitude_", "gnss"), ("unknown_roll_pitch", "gnss"), ("heading_", "gnss"), ("loop_", "loops"),
           ("survey_", "anchors"), ("parallel_min_items", "loops"), ("max_iterations", "solve"),
           ("lm_", "solve"), ("fixed_prior", "solve"), ("compute_marginals", "solve"),
           ("error_kernel", "solve"), ("icp_edge_", "factors"), ("prior_", "prior"), ("region_", "regions")]


def _changed(name: str, default):
    if name in CHANGED:
        return CHANGED[name]
    if isinstance(default, bool):
        return not default
    if isinstance(default, int):
        return default + 1
    if isinstance(default, float):
        return default * 0.5
    if name == "survey_marking_raster":
        return default.model_copy(update={"cell_m": default.cell_m * 0.5})
    raise AssertionError(f"add a changed value for {name!r} to CHANGED")


@pytest.mark.parametrize("name", sorted(PosegraphParams.model_fields))
def test_every_param_changes_its_section_of_the_config(name):
    base = PosegraphParams()
    changed = PosegraphParams(**{name: _changed(name, getattr(base, name))})
    a, b = PosegraphConfig.from_params(base), PosegraphConfig.from_params(changed)
    assert a != b, f"{name} does not reach the pose graph's config"
    section = next(s for prefix, s in SECTION if name.startswith(prefix))
    assert getattr(a, section) != getattr(b, section), f"{name} does not reach the {section} section"


def test_sections_carry_the_params_values():
    p = PosegraphParams(loop_voxel_m=0.3, wheel_bridges=False, survey_markings=False, gnss_lever_arm_m=(0.5, 0, 1))
    cfg = PosegraphConfig.from_params(p)
    assert cfg.factors.wheel_bridge is None and cfg.factors.wheel_fusion is not None and cfg.factors.uses_wheel
    assert cfg.factors.wheel_fusion.height_sigma_m == p.wheel_height_sigma_m
    assert cfg.loops.verify.voxel_m == 0.3 and cfg.anchors.ground.voxel_m == 0.15  # the survey works at half
    assert cfg.gnss.lever_arm_m == (0.5, 0.0, 1.0) and not cfg.anchors.use_markings
    assert cfg.solve.lm_kwargs() == {"max_iterations": 100, "relative_error_tol": p.lm_relative_error_tol}
    assert cfg.loops.workers(p.parallel_min_items) is None and cfg.loops.workers(p.parallel_min_items - 1) == 1
