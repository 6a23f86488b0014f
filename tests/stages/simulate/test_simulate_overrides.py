"""Preset overrides (``--set``, ``preset_overrides``): validated, recorded in simulation.json, and honoured when
the corner truth is recounted from a simulator folder."""
from __future__ import annotations

import json

import pytest

from pipeline.errors import ConfigError
from stages.simulate.cli import parse_overrides
from stages.simulate.presets import get_preset, preset_overrides


def test_overrides_are_checked_and_typed():
    p = get_preset("demo", lead_vehicle_share=0.7, n_cols=3.0, corner_radius_m=(2.0, 3.0))
    assert p.lead_vehicle_share == 0.7 and p.n_cols == 3 and isinstance(p.n_cols, int)
    assert preset_overrides(p) == {"lead_vehicle_share": 0.7, "n_cols": 3, "corner_radius_m": (2.0, 3.0)}
    with pytest.raises(ConfigError) as err:
        get_preset("demo", lead_vehicle_shar=0.7, mixed_pixel_share=1.5, n_rows=2.5)
    text = str(err.value)
    assert "3 problems" in text and "'lead_vehicle_shar'" in text and "within 0..1" in text and "integer" in text


def test_set_strings_parse_to_numbers_and_pairs():
    assert parse_overrides(["lead_vehicle_share=0.7", "corner_radius_m=1,5"]) == {
        "lead_vehicle_share": 0.7, "corner_radius_m": (1.0, 5.0)}
    with pytest.raises(ConfigError, match="expected KEY=NUMBER"):
        parse_overrides(["lead_vehicle_share", "x=a", "y=1,2,3"])


def test_overridden_city_is_recorded_and_rebuilt(tmp_path):
    from stages.simulate.core import simulate
    from stages.simulate.corner_views import sensed_corner_truth

    simulate(get_preset("tiny", rounded_corner_share=0.6, furniture_per_km=30.0), 3, tmp_path, n_drives=1,
             scan_limit=3)
    meta = json.loads((tmp_path / "simulation.json").read_text())
    assert meta["preset_overrides"] == {"rounded_corner_share": 0.6, "furniture_per_km": 30.0}
    assert 0.0 <= meta["vehicles_ahead_scan_share"]["drive_0"] <= 1.0
    sensed = sensed_corner_truth(tmp_path, "drive_0")
    city = json.loads((tmp_path / "truth/city.json").read_text())
    assert len(sensed.views) == sum(len(b["footprint_en"]) for b in city["buildings"])
    assert sum(s == "rounded" for b in city["buildings"] for s in b["corner_shape"]) >= 3
