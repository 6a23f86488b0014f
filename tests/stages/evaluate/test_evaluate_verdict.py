"""An evaluation that cannot mislead: references moved into the map's frame by geodesy (or refused), coverage
("no coverage" for a drive off the map, exit 3), a verdict per target, the comparison with a previous version."""
from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.errors import DataQualityError, ReferenceFrameError
from stages.common.geodesy import EnuOrigin
from stages.common.geometry import write_tum
from stages.common.records import Trajectory
from stages.common.trajectory_frame import frame_header, move_poses, sidecar_path, write_sidecar
from stages.evaluate import compute as compute_mod
from tests.stages.evaluate import test_evaluate_compute
from tests.stages.evaluate.test_evaluate_compute import MAP_ORIGIN, FakeMap, _rerun

stage_context = test_evaluate_compute.stage_context  # the shared fixture, registered here by name

OTHER_ORIGIN = EnuOrigin(MAP_ORIGIN.lat_deg + 0.021, MAP_ORIGIN.lon_deg - 0.034, MAP_ORIGIN.h_m + 31.0)  # ~3.7 km


def _metrics(ctx) -> dict:
    compute_mod.compute(ctx)
    return json.loads((ctx.artifact_dir("report") / "metrics.json").read_text())


def _absolute(doc: dict, method: str) -> dict:
    """The method's absolute metrics, nested entries (the EKF's ``startup``, ``all_epochs``) flattened."""
    out = {}
    for k, v in doc["methods"][method]["absolute"].items():
        if isinstance(v, dict):
            out.update({f"{k}.{kk}": vv for kk, vv in v.items()})
        elif k != "nees_band95":
            out[k] = v
    return out


def test_truth_in_another_frame_gives_the_same_numbers(stage_context, tmp_path):
    """The truth written in ENU about an origin 3.7 km away (header line only, then sidecar only) scores exactly as
    the truth in the map's frame; its raw coordinates are kilometres off, so an unconverted file could not."""
    ctx, _ = stage_context
    base = _metrics(_rerun(ctx, tmp_path, params={"methods": ["ekf"]}))
    truth = Trajectory.from_tum(ctx.settings["references"]["drive_1"])
    stamps_s, T_map = truth.stamp_s, truth.T
    T_other = move_poses(T_map, MAP_ORIGIN, OTHER_ORIGIN)
    assert np.linalg.norm(T_other[0, :2, 3] - T_map[0, :2, 3]) > 3000.0
    with_header = tmp_path / "truth_other_header.txt"
    write_tum(with_header, stamps_s, T_other, header=frame_header(OTHER_ORIGIN))
    with_sidecar = tmp_path / "truth_other_sidecar.txt"
    write_tum(with_sidecar, stamps_s, T_other)
    write_sidecar(with_sidecar, OTHER_ORIGIN)
    for path in (with_header, with_sidecar):
        doc = _metrics(_rerun(ctx, tmp_path, params={"methods": ["ekf"]},
                              settings={"references": {"drive_1": str(path)}}))
        for m in ("ekf", "rtk_ins", "icp_dr"):
            got, want = _absolute(doc, m), _absolute(base, m)
            assert got.keys() == want.keys()
            for k in want:
                assert got[k] == (None if want[k] is None else pytest.approx(want[k], abs=2e-5, rel=1e-5)), \
                    (path.name, m, k)
    # the same file told it is in the map frame is compared as is: the errors are the 3.7 km offset
    wrong = _metrics(_rerun(ctx, tmp_path, params={"methods": ["ekf"], "reference": {"frame": "map"}},
                            settings={"references": {"drive_1": str(with_header)}}))
    assert wrong["methods"]["ekf"]["absolute"]["rms_2d_m"] > 3000.0
    # ... and told the origin explicitly, it matches again
    given = ",".join(str(v) for v in (OTHER_ORIGIN.lat_deg, OTHER_ORIGIN.lon_deg, OTHER_ORIGIN.h_m))
    doc = _metrics(_rerun(ctx, tmp_path, params={"methods": ["ekf"], "reference": {"frame": given}},
                          settings={"references": {"drive_1": str(with_sidecar)}}))
    assert doc["methods"]["ekf"]["absolute"]["rms_2d_m"] == pytest.approx(
        base["methods"]["ekf"]["absolute"]["rms_2d_m"], abs=2e-5
    )


def test_reference_that_states_no_frame_is_refused_unless_told(stage_context, tmp_path):
    ctx, _ = stage_context
    truth = Trajectory.from_tum(ctx.settings["references"]["drive_1"])
    stamps_s, T = truth.stamp_s, truth.T
    bare = tmp_path / "bare.txt"
    write_tum(bare, stamps_s, T)
    with pytest.raises(ReferenceFrameError, match=r"bare.txt: the reference trajectory does not state its frame"):
        compute_mod.compute(_rerun(ctx, tmp_path, params={"methods": ["ekf"]},
                                   settings={"references": {"drive_1": str(bare)}}))
    doc = _metrics(_rerun(ctx, tmp_path, params={"methods": ["ekf"], "reference": {"frame": "map"}},
                          settings={"references": {"drive_1": str(bare)}}))
    assert doc["methods"]["ekf"]["absolute"]["rms_2d_m"] < 0.1


def test_header_and_sidecar_that_disagree_are_refused(tmp_path):
    from pipeline.errors import FormatError
    from stages.common.trajectory_frame import read_trajectory_origin

    path = tmp_path / "t.txt"
    write_tum(path, np.array([1.0]), np.eye(4)[None], header=frame_header(MAP_ORIGIN))
    assert read_trajectory_origin(path) == EnuOrigin(*(round(v, 10) for v in (MAP_ORIGIN.lat_deg, MAP_ORIGIN.lon_deg)),
                                                     MAP_ORIGIN.h_m)
    write_sidecar(path, OTHER_ORIGIN)
    assert sidecar_path(path).name == "t.frame.json"
    with pytest.raises(FormatError, match="stale"):
        read_trajectory_origin(path)


def test_enu_to_enu_transform_matches_pymap3d_through_geodetic():
    """T_enuB_enuA against an independent chain (enu2geodetic then geodetic2enu) on points and on directions:
    60 km apart the frames are tilted by ~0.5 deg, which a 2-D shift would miss by tens of centimetres."""
    import pymap3d

    from stages.common.trajectory_frame import T_enuB_enuA

    a = MAP_ORIGIN
    b = EnuOrigin(a.lat_deg + 0.54, a.lon_deg + 0.1, a.h_m - 20.0)
    T = T_enuB_enuA(a, b)
    rng = np.random.default_rng(3)
    p_a = rng.uniform(-500, 500, (50, 3)) * [1, 1, 0.05]
    lat, lon, h = pymap3d.enu2geodetic(p_a[:, 0], p_a[:, 1], p_a[:, 2], a.lat_deg, a.lon_deg, a.h_m)
    p_b = np.column_stack(pymap3d.geodetic2enu(lat, lon, h, b.lat_deg, b.lon_deg, b.h_m))
    np.testing.assert_allclose(p_a @ T[:3, :3].T + T[:3, 3], p_b, atol=1e-6)
    assert np.degrees(np.arccos(T[2, 2])) > 0.4  # the up axes differ: a full rotation, not a shift
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)


def test_foreign_drive_has_no_coverage(stage_context, tmp_path, monkeypatch):
    """The map 60 km away from the drive: no corner in range, no association; the report is still written and
    names the verdict, and the evaluation fails with a data-quality error (exit 3)."""
    ctx, _ = stage_context
    real = compute_mod.open_published_map(ctx)
    far = FakeMap(real.corners + [0.0, 60_000.0], real.dirs, real.mask, real.raster_origin)
    monkeypatch.setattr(compute_mod, "open_published_map", lambda ctx: far)
    run = _rerun(ctx, tmp_path, params={"methods": ["ekf"]})
    with pytest.raises(DataQualityError, match="no coverage: 0% of 40 epochs with a map corner within 60 m") as err:
        compute_mod.compute(run)
    assert err.value.exit_code == 3
    doc = json.loads((run.artifact_dir("report") / "metrics.json").read_text())
    assert doc["verdict"]["status"] == "no coverage"
    assert doc["verdict"]["coverage"]["share_corner_in_range"] == 0.0
    assert doc["verdict"]["coverage"]["share_associated"] == 0.0
    assert "no coverage" in (run.artifact_dir("report") / "report.html").read_text()


def test_missed_target_fails_only_when_asked(stage_context, tmp_path):
    ctx, _ = stage_context
    tight = {"methods": ["ekf"], "targets": {"ekf_rms_2d_m": 1e-6}}
    doc = _metrics(_rerun(ctx, tmp_path, params=tight))
    v = doc["verdict"]
    assert v["status"] == "fail" and v["coverage"]["ok"]
    assert not v["targets"]["ekf"]["rms_2d_m"]["ok"] and v["targets"]["ekf"]["max_2d_m"]["ok"]
    assert v["missed"][0].startswith("ekf rms_2d_m")
    # this synthetic EKF states a covariance ~6x larger than its errors: named pessimistic, not consistent
    assert v["targets"]["ekf"]["nees_consistent"]["state"] == "pessimistic" and v["missed"][1].startswith(
        "ekf nees_consistent")
    with pytest.raises(DataQualityError, match="verdict: fail: 2 target.*rms_2d_m.*pessimistic"):
        compute_mod.compute(_rerun(ctx, tmp_path, params={**tight, "fail_on_targets": True}))
    loose = _metrics(_rerun(ctx, tmp_path, params={"methods": ["ekf"]}))["verdict"]
    assert [m.split()[1] for m in loose["missed"]] == ["nees_consistent"]  # the other targets are met


def test_previous_version_is_compared(stage_context, tmp_path, monkeypatch):
    """A parent version with one corner fewer and one moved 0.5 m: the comparison finds exactly those, runs the
    EKF on both, and the report draws them."""
    ctx, _ = stage_context
    cur = compute_mod.open_published_map(ctx)
    cur.manifest = {"version": 2, "parent_version": 1}
    cur.version = 2
    prev_corners = cur.corners[1:].copy()
    prev_corners[0] += [0.5, 0.0]
    prev = FakeMap(prev_corners, cur.dirs[1:], cur.mask, cur.raster_origin)
    monkeypatch.setattr(compute_mod, "open_published_map", lambda ctx: cur)
    monkeypatch.setattr("stages.evaluate.compare.previous_version", lambda reader: prev)
    run = _rerun(ctx, tmp_path, params={"methods": ["ekf"]})
    doc = _metrics(run)
    c = doc["comparison"]
    assert (c["current_version"], c["previous_version"]) == (2, 1)
    assert (c["added"], c["removed"], c["moved"]) == (1, 0, 1)
    np.testing.assert_allclose(c["added_en_m"], cur.corners[:1], atol=1e-3)
    assert c["moved_by_m"] == [pytest.approx(0.5, abs=1e-3)]
    assert c["ekf"]["current"]["epochs"] == c["ekf"]["previous"]["epochs"] == 40
    page = (run.artifact_dir("report") / "report.html").read_text()
    assert "Previous version v0001" in page and "Corners changed since the previous version" in page
