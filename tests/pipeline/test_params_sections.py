"""Params with sections: unknown keys at any depth are refused with the nearest known name, a key that moved is
refused with its new place, and the workflow loader turns both into one line naming the stage."""
from __future__ import annotations

import pytest
from pydantic import Field, ValidationError

from pipeline.declare import Params


class Loops(Params):
    radius_m: float = Field(30.0, gt=0.0)
    min_gap_s: float = 20.0


class Graph(Params):
    renamed = {"loop_radius_m": "loops.radius_m"}
    loops: Loops = Loops()
    workers: int = 2


def test_defaults_and_a_nested_override_build() -> None:
    g = Graph.model_validate({"loops": {"radius_m": 12.5}})
    assert g.loops.radius_m == 12.5 and g.loops.min_gap_s == 20.0 and g.workers == 2
    assert Graph() == Graph.model_validate({})


def test_a_misspelt_nested_key_names_the_nearest() -> None:
    with pytest.raises(ValidationError) as err:
        Graph.model_validate({"loops": {"radus_m": 1.0}})
    text = str(err.value)
    assert "unknown key 'radus_m'" in text and "did you mean 'radius_m'" in text and "loops" in text


def test_an_old_flat_key_names_its_new_place() -> None:
    with pytest.raises(ValidationError) as err:
        Graph.model_validate({"loop_radius_m": 30.0})
    assert "'loop_radius_m' has moved: write it as 'loops.radius_m'" in str(err.value)


def test_a_key_with_no_near_name_lists_the_known_ones() -> None:
    with pytest.raises(ValidationError) as err:
        Graph.model_validate({"zzz": 1})
    assert "known: loops, workers" in str(err.value)


def test_sections_are_frozen() -> None:
    g = Graph()
    with pytest.raises(ValidationError):
        g.loops.radius_m = 3.0  # type: ignore[misc]
