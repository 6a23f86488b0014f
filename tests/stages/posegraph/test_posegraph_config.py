"""The posegraph params are nested sections: every key of the flat params of before is refused with its new place,
that place exists and a value written there reaches the section the algorithm receives; dotted keys and nested
mappings say the same."""

from __future__ import annotations

import functools

import pytest
from pydantic import ValidationError

from stages.posegraph.params import PosegraphParams

CHANGED = {"kernel": "cauchy", "span_edge_kernel": "cauchy", "lever_arm_m": (0.1, -0.2, 1.5)}


def _at(obj, place: str):
    return functools.reduce(getattr, place.split("."), obj)


def _changed(place: str, default):
    name = place.rsplit(".", 1)[-1]
    if name in CHANGED and CHANGED[name] != default:
        return CHANGED[name]
    if place == "loops.kernel":
        return "gnc"
    if isinstance(default, bool):
        return not default
    if isinstance(default, int):
        return default + 1
    if isinstance(default, float):
        return default * 0.5 if default else 0.01
    if name == "raster":
        return {"cell_m": default.cell_m * 0.5}
    raise AssertionError(f"add a changed value for {place!r} to CHANGED")


def test_sections_derive_the_algorithm_values():
    p = PosegraphParams(
        factors={"wheel": {"bridges": False}, "registration": {"yaw_deg": 0.5}},
        anchors={"use_markings": False},
        gnss={"lever_arm_m": [0.5, 0, 1]},
    )
    assert p.factors.wheel_bridge is None and p.factors.wheel_fusion is not None and p.factors.uses_wheel
    assert p.factors.wheel_fusion.height_sigma_m == p.factors.wheel.height_sigma_m
    assert p.factors.registration_sigma.yaw_rad == pytest.approx(0.5 * 3.141592653589793 / 180)
    assert p.gnss.lever_arm_m == (0.5, 0.0, 1.0) and not p.anchors.use_markings
    assert p.solve.lm_kwargs() == {"max_iterations": 100, "relative_error_tol": p.solve.lm_relative_error_tol}
    n = p.loops.parallel_min_items
    assert p.loops.workers(n) is None and p.loops.workers(n - 1) == 1


def test_dotted_keys_and_nested_mappings_are_the_same_params():
    a = PosegraphParams().updated({"loops.radius_m": 20.0, "loops.wide.enabled": False})
    b = PosegraphParams(loops={"radius_m": 20.0, "wide": {"enabled": False}})
    assert a == b and a.loops.radius_m == 20.0 and a.loops.stride_m == PosegraphParams().loops.stride_m


def test_a_misspelt_section_key_names_the_nearest():
    with pytest.raises(ValidationError, match="did you mean 'radius_m'"):
        PosegraphParams(loops={"radus_m": 20.0})
