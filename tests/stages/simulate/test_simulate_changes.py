"""Dated city variants (stages/simulate/changes.py): what changes, its truth, and which drives see it."""
from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.errors import ConfigError
from stages.simulate.changes import CROSSWALK_SHIFT_M, changed_city, changes_truth, plan_changes, repainted
from stages.simulate.city import generate_city
from stages.simulate.core import component_rng
from stages.simulate.markings import generate_markings, rasterize_markings
from stages.simulate.presets import get_preset
from stages.simulate.trajectory import choose_loop_cells, loop_nodes
from stages.simulate.truth import building_corners


@pytest.fixture(scope="module", params=[0, 7, 11])
def planned(request):
    seed = request.param
    p = get_preset("tiny")
    city = generate_city(p, component_rng(seed, "city"))
    loop = loop_nodes(choose_loop_cells(p.n_rows, p.n_cols, city.nodes_en, p.lap_length_m,
                                        component_rng(seed, "route")))
    marks = rasterize_markings(generate_markings(city), city.bounds_en)
    plan = plan_changes(city, loop, p.sidewalk_m, 2, component_rng(seed, "changes"))
    after = changed_city(city, plan)
    marks_after = repainted(marks, plan)
    doc = changes_truth(plan, city, building_corners(city), building_corners(after), marks, marks_after)
    return city, plan, after, marks, marks_after, doc


def test_removed_corners_are_the_demolished_buildings_and_added_the_new_ones(planned):
    city, plan, after, _, _, doc = planned
    gone = city.buildings[plan.demolished].footprint_en
    removed = np.array([[c["east_m"], c["north_m"]] for c in doc["corners"]["removed"]])
    added = np.array([[c["east_m"], c["north_m"]] for c in doc["corners"]["added"]])
    # every removed corner is a vertex of the demolished building (a shared vertex may survive), all 4 new ones added
    assert 1 <= len(removed) <= len(gone)
    assert np.abs(removed[:, None] - gone[None]).sum(axis=2).min(axis=1).max() < 1e-3
    assert (
        len(added) == 4 and np.abs(added[:, None] - plan.built.footprint_en[None]).sum(axis=2).min(axis=1).max() < 1e-3
    )
    assert len(after.buildings) == len(city.buildings)  # one down, one up
    assert doc["corners"]["n_before"] - len(removed) + len(added) == doc["corners"]["n_after"]
    before = building_corners(city)
    ids = [c["id"] for c in doc["corners"]["removed"]]  # ids of truth/corners.csv
    np.testing.assert_allclose(np.column_stack([before["east_m"][ids], before["north_m"][ids]]), removed, atol=1e-3)


def test_the_new_building_stands_on_vacant_land(planned):
    from stages.simulate.geom2d import point_in_polygon

    city, plan, *_ = planned
    new = plan.built.footprint_en
    probe = np.vstack([new, new.mean(axis=0, keepdims=True)])
    for b in city.buildings:
        assert not point_in_polygon(probe, b.footprint_en).any()
        assert not point_in_polygon(b.footprint_en, new).any()
    for curb in city.curbs_en:  # not on a block: across an outer street
        assert not point_in_polygon(probe, curb).any()


def test_crosswalk_moves_and_nothing_else_is_repainted(planned):
    _, plan, _, marks, marks_after, doc = planned
    changed = (marks.data > 0) != (marks_after.data > 0)
    assert changed.sum() == doc["markings"][0]["pixels_changed"] > 0
    rows, cols = np.nonzero(changed)
    east = marks.west_m + (cols + 0.5) * marks.res_m
    north = marks.north_m - (rows + 0.5) * marks.res_m
    stripes = np.vstack(plan.crosswalk_old_en + plan.crosswalk_new_en)
    lo, hi = stripes.min(axis=0) - 0.2, stripes.max(axis=0) + 0.2
    assert ((east >= lo[0]) & (east <= hi[0]) & (north >= lo[1]) & (north <= hi[1])).all()
    shift = np.mean(plan.crosswalk_new_en[0], axis=0) - np.mean(plan.crosswalk_old_en[0], axis=0)
    assert np.linalg.norm(shift) == pytest.approx(abs(CROSSWALK_SHIFT_M), abs=1e-9)
    assert len(plan.crosswalk_old_en) == len(plan.crosswalk_new_en) > 3


def test_changes_need_a_drive_before_and_after(tmp_path):
    from stages.simulate.core import simulate

    with pytest.raises(ConfigError, match="--drives 2 or more"):
        simulate("tiny", 0, tmp_path / "one", n_drives=1, scan_limit=1, changes=True)
    with pytest.raises(ConfigError, match="drive 1..1"):
        simulate("tiny", 0, tmp_path / "two", n_drives=2, scan_limit=1, changes=True, changes_from_drive=0)


def test_later_drives_see_the_changed_city(tmp_path):
    """Two drives, 3 scans each: drive 1 (the last) sees the change and references the changed city's survey.
    That its scans see the changed buildings is checked end to end (tests/test_changed_city.py)."""
    import yaml

    from stages.simulate.core import simulate

    out = tmp_path / "sim"

    simulate("tiny", 7, out, n_drives=2, scan_limit=3, changes=True)
    doc = json.loads((out / "truth" / "changes.json").read_text())
    assert doc["from_drive"] == 1 and (out / "truth" / "corners_after.csv").is_file()
    assert json.loads((out / "simulation.json").read_text())["changes"]["from_drive"] == 1
    y0 = yaml.safe_load((out / "drive_0" / "drive.yaml").read_text())
    y1 = yaml.safe_load((out / "drive_1" / "drive.yaml").read_text())
    assert y0["survey"]["file"] == "../survey/survey.las" and y1["survey"]["file"] == "../survey_changed/survey.las"
    assert (out / "survey_changed" / "survey.las").is_file()
