"""The odometry params are nested sections and what ``estimate_edges`` receives: every key of the flat params of
before is refused with its new place, that place exists and a value written there changes the params."""

from __future__ import annotations

import functools

import pytest
from pydantic import ValidationError

from stages.odometry.params import OdometryParams

CHANGED = {
    "method": "point_to_plane",
    "ground_split": False,
    "knn": 7,
    "max_iterations": 3,
    "min_fitness": 0.5,
    "stages": ((2.0, 3.0),),
}


def _at(obj, place: str):
    return functools.reduce(getattr, place.split("."), obj)


def test_registration_keywords_and_spans():
    p = OdometryParams(
        icp={"guided_relative_tolerance": 2e-3}, information={"point_sigma_m": 0.15}, span_scans=[3], deskew="none"
    )
    assert p.registration_kwargs(guided=True)["relative_tolerance"] == 2e-3
    assert p.registration_kwargs()["relative_tolerance"] == p.icp.relative_tolerance
    assert p.registration_kwargs()["point_sigma_m"] == 0.15 and p.span_scans == (3,) and not p.own_sweep_deskew
    with pytest.raises(ValidationError, match="every span must be >= 2"):
        OdometryParams(span_scans=[1])
    with pytest.raises(ValidationError, match="min_range_m"):
        OdometryParams(prepare={"min_range_m": 90.0, "max_range_m": 80.0})
