"""The params of the stages that had flat ones (evaluate, corners, posegraph, odometry) are nested sections that
are their algorithms' configs: every default is written once (in its section's class; no dataclass, function
default or parent field of the stage restates it), no params class has more than 25 top-level fields, and every
flat key of the earlier params is refused with the place it moved to."""

from __future__ import annotations

import ast
import typing
from pathlib import Path

import pytest
from pydantic import ValidationError

from pipeline.declare import Params
from stages.corners.params import CornerParams
from stages.evaluate.params import EvaluateParams
from stages.odometry.params import OdometryParams
from stages.posegraph.params import PosegraphParams

ROOT = Path(__file__).resolve().parents[2]
STAGES = {"evaluate": EvaluateParams, "corners": CornerParams, "posegraph": PosegraphParams,
          "odometry": OdometryParams}

# The flat keys of the params before they had sections (each must be refused with its new place).
OLD_KEYS = {
    "evaluate": """init_sigma_xy_m init_sigma_yaw_deg icp_sigma_frac icp_sigma_xy_m icp_sigma_yaw_deg icp_sigma_yaw_frac
        icp_wheel_gate_deg ekf_motion ekf_gyro_bias_sigma_deg_s ekf_gyro_bias_rw_deg_s_per_sqrt_s ekf_wheel_scale_sigma
        ekf_wheel_scale_rw_per_sqrt_m ekf_wheel_sigma_frac ekf_wheel_sigma_lateral_frac ekf_gyro_sigma_yaw_deg
        ekf_gyro_sigma_yaw_frac ekf_icp_gate_probability sensor_range_m gate_probability angle_gate_deg association
        range_sigma_floor_m bearing_sigma_floor_deg wall_heading_sigma_deg ekf_map_consider ekf_map_cov_scale
        ekf_map_corr_share ekf_map_corr_length_m ekf_map_corr_source ekf_icp_gyro_bias_state ekf_icp_gyro_fusion
        ekf_heading_rw_deg_per_sqrt_s ekf_icp_gyro_gate ekf_markings ekf_corner_decorrelation_m ekf_marking_min_info
        ekf_marking_map_sigma_m ekf_marking_map_sigma_deg ekf_marking_map_length_m n_particles seed
        mcl_init_sigma_xy_m mcl_init_sigma_yaw_deg mcl_sigma_frac mcl_sigma_lateral_frac mcl_sigma_xy_m
        mcl_sigma_yaw_deg mcl_sigma_yaw_frac mcl_init_sigma_scale mcl_sigma_scale_per_sqrt_m
        mcl_init_sigma_gyro_bias_deg_s mcl_sigma_gyro_bias_deg_s_per_sqrt_s mcl_init_sigma_gyro_gain
        mcl_decorrelation_m mcl_sharpness mcl_effective_points mcl_max_features mcl_max_inject mcl_inject_sigma_xy_m
        raster_field raster_sigma_m raster_blur_m raster_coverage raster_coverage_margin_m feature_deskew
        feature_voxel_m feature_window_m feature_offset_sigma feature_ground_model feature_ground_band_m
        feature_max_range_m reference_max_gap_s reference_frame coverage_min_in_range coverage_min_associated
        target_ekf_rms_2d_m target_ekf_p99_2d_m target_ekf_max_2d_m target_ekf_heading_rms_deg ekf_judge_after_startup
        target_ekf_startup_s target_nees_share_below_q95 target_mcl_mean_abs_x_m target_mcl_mean_abs_y_m
        target_mcl_mean_abs_heading_deg""".split(),
    "corners": """layer_selection n_upper_layers min_elevation_deg min_range_m max_range_m deskew break_incidence_deg
        range_sigma_m max_azimuth_gap_deg split_distance_m merge_max_angle_deg end_trim_points max_residual_var_m2
        min_points min_length_m max_corner_gap_m min_interior_angle_deg max_interior_angle_deg min_wall_length_m
        min_long_wall_length_m obtuse_angle_deg min_obtuse_wall_length_m max_vertex_gap_spacings cluster_radius_m
        cluster_max_angle_deg min_layers min_corner_range_m max_passover_height_m angular_sigma_mrad
        min_sigma_m""".split(),
    "posegraph": """failed_edge_sigma_m failed_edge_sigma_rad wheel_bridges wheel_sigma_m wheel_scale_sigma
        wheel_sigma_rad
        wheel_height_sigma_m wheel_tilt_sigma_rad wheel_fusion wheel_fusion_sigma_m wheel_fusion_scale_sigma
        wheel_fusion_sigma_rad icp_edge_sigma_along_m icp_edge_sigma_cross_m icp_edge_sigma_yaw_deg
        span_edges span_edge_kernel span_edge_kernel_k gnss_std_inflation gnss_min_std_m gnss_every_s
        gnss_bias_tau_s gnss_white_sigma_m gnss_kernel gnss_kernel_k gnss_lever_arm_m attitude_sigma_rad
        unknown_roll_pitch_sigma_rad heading_prior heading_std_inflation prior_every_s prior_kernel
        prior_kernel_k loop_radius_m loop_min_separation_s loop_stride_m loop_max_per_scan
        loop_reference_stride_m loop_survey_window_m loop_survey_sigma_m loop_wide loop_wide_sigmas
        loop_wide_min_sigma_m loop_wide_stride_m loop_wide_max_per_scan loop_wide_target_spacing_m
        loop_wide_rounds loop_wide_global_voxel_m loop_wide_yaw_slack_deg loop_wide_min_consistent
        loop_pcm_probability loop_pcm_window_m loop_coarse_voxel_m loop_coarse_corr_m loop_voxel_m
        loop_max_corr_m loop_relative_tolerance loop_ground_split loop_inlier_m loop_plane_tol_m
        loop_min_fitness loop_max_rmse_m loop_max_correction_m loop_max_correction_rad loop_consistency_m
        loop_kernel loop_kernel_k loop_max_whitened_residual loop_min_sigma_m loop_min_sigma_rad
        survey_stride_m survey_crop_m survey_max_height_m survey_min_fitness survey_max_rmse_m
        survey_min_sigma_m survey_min_sigma_rad survey_vertical_only survey_markings
        survey_marking_half_travel_m survey_marking_max_scans survey_marking_scan_step
        survey_marking_search_m survey_marking_sigma_scale survey_marking_min_sigma_m
        survey_marking_yaw_search_deg survey_marking_yaw_step_deg survey_marking_yaw_sigma_deg
        survey_marking_consensus_window_m survey_marking_consensus_drift_sigma_m
        survey_marking_consensus_probability survey_rounds survey_round_tol_m survey_round_tol_deg
        parallel_min_items survey_marking_block survey_marking_raster max_iterations lm_relative_error_tol
        fixed_prior_sigma_m loop_incremental_max_per_scan compute_marginals error_kernel_pairs_per_bin
        region_max_poses region_rounds region_tol_m""".split(),
    "odometry": """method voxel_m knn max_corr_m max_iterations relative_tolerance guided_relative_tolerance min_range_m
        max_range_m ground_split ground_tolerance_m min_fitness max_deviation_m max_deviation_rad
        max_deviation_wheel_m max_deviation_wheel_rad point_sigma_m min_sigma_m min_sigma_rad rot_sigma_per_rad
        keyframe_min_dt_s keyframe_stages keyframe_deviation_m_per_m keyframe_deviation_rad_per_m
        keyframe_sigma_m_per_m keyframe_sigma_rad_per_m keyframe_global_voxel_m keyframe_max_sideslip_deg
        prior_gate_sigmas""".split(),
}


def sections(model: type[Params], prefix: str = "") -> dict[str, type[Params]]:
    """Dotted place -> params class of the model and every section below it ('' is the model)."""
    out = {prefix: model}
    for name, info in model.model_fields.items():
        if isinstance(info.annotation, type) and issubclass(info.annotation, Params):
            out.update(sections(info.annotation, f"{prefix}{name}."))
    return out


def field_names(model: type[Params]) -> set[str]:
    return {name for cls in sections(model).values() for name in cls.model_fields}


def value_at(params: Params, dotted: str):
    for part in dotted.split("."):
        params = getattr(params, part)
    return params


@pytest.mark.parametrize("stage", sorted(STAGES))
def test_no_params_class_has_more_than_25_fields(stage):
    wide = {place or stage: len(cls.model_fields) for place, cls in sections(STAGES[stage]).items()
            if len(cls.model_fields) > 25}
    assert not wide, wide


@pytest.mark.parametrize("stage", sorted(STAGES))
def test_a_section_default_is_its_class_default(stage):
    """A parent holds each section at the section's own defaults: no parent restates (or overrides) one."""
    for place, cls in sections(STAGES[stage]).items():
        for name, info in cls.model_fields.items():
            if isinstance(info.annotation, type) and issubclass(info.annotation, Params):
                assert info.get_default(call_default_factory=True) == info.annotation(), f"{stage}.{place}{name}"


def literal(node: ast.expr):
    """The value of a literal default (``-1.0`` too), else None."""
    try:
        return ast.literal_eval(node)
    except ValueError:
        return None


def field_defaults(model: type[Params]) -> dict[str, list]:
    """Setting name -> its defaults (the sections themselves aside: a name like ``loops`` is no setting)."""
    out: dict[str, list] = {}
    for cls in sections(model).values():
        for name, info in cls.model_fields.items():
            if not (isinstance(info.annotation, type) and issubclass(info.annotation, Params)):
                out.setdefault(name, []).append(info.default)
    return out


def place(renamed_to: str) -> str:
    """The dotted place a moved key names (a note after it, e.g. where its twin went, aside)."""
    return renamed_to.split(" ", 1)[0]


@pytest.mark.parametrize("stage", sorted(STAGES))
def test_no_other_code_of_the_stage_restates_a_default(stage):
    """No dataclass field of the stage's package carries a params field's name (the config dataclasses that
    mirrored the params are gone; the algorithms receive the sections), and no function restates a params default
    as its keyword default (a literal equal to the default of the params field of that name; 0 / None / False,
    a switch's off, aside)."""
    names = field_defaults(STAGES[stage])
    params_modules = {f"{m}.py" for m in ("params", "ekf_params", "mcl_params")}
    found = []
    for path in sorted((ROOT / "stages" / stage).glob("*.py")):
        if path.name in params_modules:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef):
                is_dataclass = any("dataclass" in ast.unparse(d) for d in node.decorator_list)
                found += [f"{path.name}:{node.name}.{item.target.id}" for item in node.body
                          if is_dataclass and isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name)
                          and item.value is not None and item.target.id in names]
            elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                args = node.args
                positional = (args.posonlyargs + args.args)[len(args.posonlyargs + args.args) - len(args.defaults):]
                kw_pairs = [(a, d) for a, d in zip(args.kwonlyargs, args.kw_defaults) if d is not None]
                kw, kw_defaults = [a for a, _ in kw_pairs], [d for _, d in kw_pairs]
                found += [f"{path.name}:{node.name}({a.arg}={ast.unparse(d)})"
                          for a, d in list(zip(positional, args.defaults)) + list(zip(kw, kw_defaults))
                          if a.arg in names and isinstance(d, (ast.Constant, ast.UnaryOp)) and literal(d)
                          and literal(d) in names[a.arg]]
    assert not found, found


@pytest.mark.parametrize("stage", sorted(STAGES))
def test_every_old_flat_key_is_refused_with_its_new_place(stage):
    model = STAGES[stage]
    assert set(model.renamed) == set(OLD_KEYS[stage])
    default = model()
    for old in OLD_KEYS[stage]:
        new = model.renamed[old]
        value_at(default, place(new))  # the new place exists
        with pytest.raises(ValidationError) as err:
            model.model_validate({old: value_at(default, place(new))})
        assert f"{old!r} has moved: write it as {new!r}" in str(err.value), old


@pytest.mark.parametrize("stage", sorted(STAGES))
def test_a_value_written_at_its_new_place_reaches_the_section(stage):
    model = STAGES[stage]
    for new in map(place, model.renamed.values()):
        *path, last = new.split(".")
        current = value_at(model(), new)
        data: dict = {}
        node = data
        for part in path:
            node = node.setdefault(part, {})
        node[last] = current
        assert value_at(model.model_validate(data), new) == current, new


def test_a_misspelt_nested_key_names_the_nearest():
    with pytest.raises(ValidationError) as err:
        EvaluateParams.model_validate({"ekf": {"corners": {"sensor_rang_m": 50.0}}})
    assert "did you mean 'sensor_range_m'" in str(err.value)


def test_the_evaluate_sections_are_what_the_filters_receive():
    """The EKF's and the MCL's sections are the filters' own config types, by their signatures."""
    from stages.evaluate.localize_ekf import run_ekf
    from stages.evaluate.localize_mcl import run_mcl

    assert typing.get_type_hints(run_ekf)["cfg"] is EvaluateParams.model_fields["ekf"].annotation
    assert typing.get_type_hints(run_mcl)["cfg"] is EvaluateParams.model_fields["mcl"].annotation
    assert typing.get_type_hints(run_ekf)["likelihood"] is EvaluateParams.model_fields["markings"].annotation
