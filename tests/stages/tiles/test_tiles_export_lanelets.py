"""Lanelets of the driven lanes (mapformat.lanelets) written as Lanelet2 OSM and read back by the real lanelet2.

A straight two-way street: a double centre line (0.6 m wide) at north = 0, solid edge lines at +-3.5 m; drive a
goes east in the right lane (north = -1.75) twice, drive b west in the other lane. The road rises 2 % to the
east. Known truth: one chain of lanelets per lane, boundaries on the painted lines, heights on the road.
"""
from __future__ import annotations

import numpy as np
import pytest

from mapformat.autoware import lanelet2_osm
from mapformat.lanelets import LaneParams, driven_lanes, resample_path
from stages.common.geodesy import EnuOrigin
from stages.common.marking_vectors import MarkingFeature

ORIGIN = EnuOrigin(37.4979, 127.0276, 57.0)
GRADE = 0.02


def road_z(xy: np.ndarray) -> np.ndarray:
    return 3.0 + GRADE * np.asarray(xy, float).reshape(-1, 2)[:, 0]


def street() -> list[MarkingFeature]:
    line = lambda n: np.array([[-10.0, n], [210.0, n]])
    return [MarkingFeature("lane_solid", line(0.0), 0.62, 220.0), MarkingFeature("lane_solid", line(-3.5), 0.18, 220.0),
            MarkingFeature("lane_solid", line(3.5), 0.18, 220.0)]


def path(x0: float, x1: float, north: float, rng: np.random.Generator) -> np.ndarray:
    x = np.linspace(x0, x1, int(abs(x1 - x0) * 4))
    y = north + rng.normal(0.0, 0.05, len(x))  # a driver is never exactly on the lane's centre
    return np.column_stack([x, y, road_z(np.column_stack([x, y]))])


@pytest.fixture(scope="module")
def lanes():
    rng = np.random.default_rng(4)
    east = path(0.0, 200.0, -1.75, rng)
    paths = {"drive_a": np.vstack([east, path(0.0, 200.0, -1.70, rng)]),  # the same lane twice (a second lap)
             "drive_b": path(200.0, 0.0, 1.75, rng)}
    return driven_lanes(paths, street(), road_z)


def test_one_chain_of_lanelets_per_driven_lane_on_the_painted_lines(lanes):
    assert sorted(r.drive for r in lanes) == ["drive_a", "drive_b"]  # drive a's second lap is the same lane
    for run in lanes:
        assert len(run.subtypes) == 8  # 200 m in lanelets of ~25 m
        assert run.subtypes == [("solid_solid", "solid")] * 8  # centre line on the left, edge line on the right
        sign = 1.0 if run.drive == "drive_b" else -1.0
        left, right = run.left[run.left_keep], run.right[run.right_keep]
        np.testing.assert_allclose(left[:, 1], 0.0, atol=0.15)  # on the double line's centre
        np.testing.assert_allclose(right[:, 1], sign * 3.5, atol=0.15)
        np.testing.assert_allclose(left[:, 2], road_z(left[:, :2]), atol=1e-9)
        cuts = run.cuts
        assert cuts[0] == 0 and np.all(np.diff(cuts) > 0)


def test_resampling_keeps_the_arc_length():
    pts, heading = resample_path(np.array([[0.0, 0, 0], [10.0, 0, 0], [10.0, 10.0, 0]]), 1.0)
    assert len(pts) == 21 and np.allclose(np.diff(pts[:, :2], axis=0).__abs__().sum(axis=1), 1.0)
    assert heading[0] == pytest.approx(0.0) and heading[-1] == pytest.approx(np.pi / 2)


def test_a_virtual_boundary_where_nothing_is_painted():
    rng = np.random.default_rng(5)
    runs = driven_lanes({"d": path(0.0, 100.0, 30.0, rng)}, street(), road_z, LaneParams(segment_m=50.0))
    assert runs[0].subtypes == [("virtual", "virtual")] * 2
    np.testing.assert_allclose(runs[0].left[:, 1] - runs[0].right[:, 1], 3.5, atol=0.2)  # default lane width


def test_the_osm_loads_in_lanelet2_with_routable_lanelets_at_the_road_height(lanes, tmp_path):
    lanelet2 = pytest.importorskip("lanelet2")
    from lanelet2.io import Origin
    from lanelet2.projection import LocalCartesianProjector

    osm = tmp_path / "lanelet2_map.osm"
    osm.write_text(lanelet2_osm(street(), ORIGIN, road_z, lanes))
    # the projector of the Autoware folder: LocalCartesian about the origin at 0 m (map_projector_info.yaml)
    projector = LocalCartesianProjector(Origin(ORIGIN.lat_deg, ORIGIN.lon_deg, 0.0))
    lmap, errors = lanelet2.io.loadRobust(str(osm), projector)
    assert errors == []
    lls = list(lmap.laneletLayer)
    assert len(lls) == 16
    rules = lanelet2.traffic_rules.create(lanelet2.traffic_rules.Locations.Germany,
                                          lanelet2.traffic_rules.Participants.Vehicle)
    graph = lanelet2.routing.RoutingGraph(lmap, rules)
    for ll in lls:
        assert ll.attributes["type"] == "lanelet" and ll.attributes["subtype"] == "road"
        assert ll.attributes["location"] == "urban" and ll.attributes["one_way"] == "yes"
        assert rules.canPass(ll) and len(ll.leftBound) >= 2 and len(ll.rightBound) >= 2
        left = np.array([[p.x, p.y, p.z] for p in ll.leftBound])
        right = np.array([[p.x, p.y, p.z] for p in ll.rightBound])
        centre = np.array([[p.x, p.y] for p in ll.centerline])
        direction = centre[-1] - centre[0]
        # both bounds run along the lanelet, the left one on its left
        for bound in (left, right):
            assert (np.diff(bound[:, :2], axis=0) @ direction > 0).all()
        normal = np.array([-direction[1], direction[0]])
        assert ((left[:, :2] - centre.mean(axis=0)) @ normal > 0).all()
        assert ((right[:, :2] - centre.mean(axis=0)) @ normal < 0).all()
        assert not lanelet2.geometry.intersects2d(lanelet2.geometry.to2D(ll.leftBound),
                                                  lanelet2.geometry.to2D(ll.rightBound))
        # heights: the node's ele projected back is the road surface of the map frame raised by h0, within 1 cm
        for pts in (left, right):
            np.testing.assert_allclose(pts[:, 2] - ORIGIN.h_m, road_z(pts[:, :2]), atol=0.01)
    routed = sum(len(graph.following(ll)) for ll in lls)
    assert routed == 14  # 2 chains of 8: every lanelet but the last of each leads to the next
    first = min(lls, key=lambda ll: ll.leftBound[0].x if ll.leftBound[0].y < 0.5 and ll.rightBound[0].y < -1 else 1e9)
    last = max(lls, key=lambda ll: ll.leftBound[-1].x if ll.rightBound[-1].y < -1 else -1e9)
    route = graph.getRoute(first, last)
    assert route is not None and len(route.shortestPath()) == 8


def test_marking_nodes_carry_the_road_height():
    import xml.etree.ElementTree as ET

    from stages.common.geodesy import geodetic_to_enu

    root = ET.fromstring(lanelet2_osm(street(), ORIGIN, road_z))
    for node in root.findall("node"):
        tags = {t.get("k"): float(t.get("v")) for t in node.findall("tag")}
        enu = geodetic_to_enu(float(node.get("lat")), float(node.get("lon")), tags["ele"], ORIGIN)[0]
        assert abs(enu[0] - tags["local_x"]) < 1e-3 and abs(enu[1] - tags["local_y"]) < 1e-3
        assert abs(enu[2] - road_z(enu[:2])[0]) < 1e-3


def test_a_painted_boundary_ends_where_its_paint_ends():
    """The double centre line stops at east 100 m (an intersection) while the drive goes on to 200 m: the left
    boundary is ``solid_solid`` up to the paint's end, no painted boundary point lies beyond it, and the rest is
    ``virtual``; the edge line on the right runs through."""
    rng = np.random.default_rng(6)
    feats = [MarkingFeature("lane_solid", np.array([[-10.0, 0.0], [100.0, 0.0]]), 0.62, 110.0),
             MarkingFeature("lane_solid", np.array([[-10.0, -3.5], [210.0, -3.5]]), 0.18, 220.0)]
    [run] = driven_lanes({"d": path(0.0, 200.0, -1.75, rng)}, feats, road_z)
    lefts = [t for t, _ in run.subtypes]
    n = lefts.count("solid_solid")
    assert 0 < n < len(lefts) and lefts == ["solid_solid"] * n + ["virtual"] * (len(lefts) - n), lefts
    assert {t for _, t in run.subtypes} == {"solid"}
    for k, (left_type, _) in enumerate(run.subtypes):
        li, _ = run.lanelet_bounds(k)
        xy = run.left[li, :2]
        if left_type == "solid_solid":
            assert xy[:, 0].max() <= 100.25 and np.abs(xy[:, 1]).max() <= 0.15, xy
    ends = [run.left[run.lanelet_bounds(k)[0][-1], 0] for k, (t, _) in enumerate(run.subtypes) if t == "solid_solid"]
    assert max(ends) >= 99.0  # the painted boundary reaches the paint's end


def test_a_dashed_line_is_one_painted_boundary_not_a_lanelet_per_dash():
    """3 m dashes every 8 m (the simulator's and Korea's pattern): the gaps are filled, so the lanelets are cut every
    ~25 m as on a solid line, all of them ``dashed`` on the left."""
    rng = np.random.default_rng(7)
    dashes = [MarkingFeature("lane_dashed", np.array([[x, 0.0], [x + 3.0, 0.0]]), 0.15, 3.0)
              for x in np.arange(-10.0, 210.0, 8.0)]
    edge = MarkingFeature("lane_solid", np.array([[-10.0, -3.5], [210.0, -3.5]]), 0.18, 220.0)
    [run] = driven_lanes({"d": path(0.0, 200.0, -1.75, rng)}, dashes + [edge], road_z)
    assert run.subtypes == [("dashed", "solid")] * 8
