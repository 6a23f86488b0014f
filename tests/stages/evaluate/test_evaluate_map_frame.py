"""A map that states its frame's error (``map_frame``, relative corner covariances): the filters start with that
error added to the GNSS/INS fix's, so a localizer starting from a fix metres and a degree off the map's frame
converges onto the map and says honestly how far off it starts."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fixtures.evaluate import synthetic_drive
from stages.evaluate.params import EvaluateParams
from stages.evaluate.run import FrameError, evaluate_drive, first_fix, initial_covariance


def test_the_frame_error_grows_with_the_distance_from_its_reference_point():
    cov = np.diag([0.04, 0.09, np.radians(0.5) ** 2])
    frame = FrameError(np.array([100.0, 50.0]), cov)
    np.testing.assert_allclose(frame.at([100.0, 50.0]), cov)
    far = frame.at([100.0, 250.0])  # 200 m north of the reference: a rotation moves it east
    assert far[0, 0] == pytest.approx(0.04 + 200.0**2 * cov[2, 2])
    assert far[1, 1] == pytest.approx(0.09) and far[0, 2] == pytest.approx(-200.0 * cov[2, 2])
    assert FrameError.from_map(None) is None
    doc = {"reference_en_m": np.array([1.0, 2.0]), "cov_shift_rotation": cov, "source": "GNSS/INS"}
    np.testing.assert_allclose(FrameError.from_map(doc).cov, cov)
    # the raster's local error: the map's stated relative pose error, above or below the params' value; the params'
    # value where the map states none
    ekf = EvaluateParams().ekf
    stated = FrameError.from_map({**doc, "relative_std_m": 0.05, "relative_std_deg": 0.01}).marking_offset(ekf)
    assert stated.markings.map_sigma_m == pytest.approx(0.05)
    assert stated.markings.map_sigma_yaw_rad == pytest.approx(np.radians(0.01))
    assert FrameError.from_map(doc).marking_offset(ekf) == ekf


def _rotated_frame(d, reference, shift_m, rotation_rad):
    """The drive's GNSS/INS as a receiver gives it when the map's frame sits ``shift_m`` and ``rotation_rad`` off the
    true one about ``reference``: the fixes are in the true frame, the map's corners and raster in the map's."""
    c, s = np.cos(-rotation_rad), np.sin(-rotation_rad)
    R = np.array([[c, -s], [s, c]])
    xy = (d.gnss_q[:, :2] - reference - shift_m) @ R.T + reference
    q = np.column_stack([xy, d.gnss_q[:, 2] - rotation_rad])
    return dataclasses.replace(d, gnss_q=q)


def test_a_localizer_starting_off_the_maps_frame_converges_onto_it_when_the_frame_error_is_stated():
    d, cmap, fetch, truth, stamps = synthetic_drive(400, np.random.default_rng(5))
    reference = np.array([150.0, 20.0])
    d = _rotated_frame(d, reference, np.array([1.2, -0.9]), np.radians(1.2))
    refs = {"truth_in_map": (stamps, truth)}
    cov = np.diag([0.8**2, 0.8**2, np.radians(0.8) ** 2])
    frame = FrameError(reference, cov)
    p = EvaluateParams(methods=["ekf"])
    cfg = p
    k0 = first_fix(d)
    P0 = initial_covariance(d, k0, cfg.ekf, frame)
    np.testing.assert_allclose(P0 - initial_covariance(d, k0, cfg.ekf, None), frame.at(d.gnss_q[k0, :2]))
    start = np.hypot(*(d.gnss_q[k0, :2] - truth[k0, :2]))
    assert start > 2.0 and abs(d.gnss_q[k0, 2] - truth[k0, 2]) > np.radians(0.8)
    ev = evaluate_drive(d, cmap, fetch, refs, cfg, frame)
    s = ev.metrics["ekf"]["truth_in_map"]
    assert s["rms_2d_m"] < 0.08 and s["heading_rms_deg"] < 0.15
    assert s["nees_share_below_q95"] > 0.9
    # where it starts, the stated covariance holds the error
    r = ev.runs["ekf"]
    e0 = np.r_[r.q[k0, :2] - truth[k0, :2], r.q[k0, 2] - truth[k0, 2]]
    assert e0 @ np.linalg.solve(r.P[k0], e0) < 11.34  # chi-square 3 dof, 99 %
