"""The guided pairs' start: each wheel guide corrected by the previous pair's registration, the guided tolerance,
and a registration the gate would reject never steering the next pair (``core.register_pairs``)."""
from __future__ import annotations

import numpy as np
import pytest

import stages.odometry.core as core
from stages.common.geometry import se3_from_xyz_rpy, se3_inverse
from stages.common.registration import RegistrationResult
from stages.odometry.params import OdometryParams

CFG = OdometryParams(deskew="none", span_scans=(), information={"rot_sigma_per_rad": 0.0})  # else the stage's
T_VL = se3_from_xyz_rpy(0.3, 0.0, 1.8, 0.0, 0.0, np.deg2rad(1.0))  # lidar in the vehicle frame
T_LV = se3_inverse(T_VL)


class _Prepared:
    def __init__(self, k: int):
        self.structure = k  # register_clouds is replaced: the cloud is the scan's position


def _run(monkeypatch, guides: dict, truth: dict, n: int, fitness: dict | None = None):
    """register_pairs over n scans with register_clouds answering the truth (vehicle frame); returns the starts
    (vehicle frame) and tolerances it was called with, by pair."""
    calls = {}

    def register(src, tgt, T_init, **kw):
        calls[src] = (T_VL @ T_init @ T_LV, kw["relative_tolerance"])
        return RegistrationResult(T_LV @ truth[src] @ T_VL, (fitness or {}).get(src, 0.9), 0.05, np.eye(6), True,
                                  np.eye(6))
    monkeypatch.setattr(core, "register_clouds", register)
    pairs = core._Pairs(list(range(1, n)), {k: 0.1 for k in range(1, n)}, dict(guides), set(guides))
    core.register_pairs([_Prepared(k) for k in range(n)], pairs, T_VL, CFG)
    return calls


def test_guide_corrected_by_the_previous_registration(monkeypatch):
    """A wheel guide 2 % short and 0.05 deg off in heading: the first pair starts from its guide, each later one
    from its guide times the previous pair's correction (exactly), at the guided tolerance."""
    step = se3_from_xyz_rpy(1.0, 0.0, 0.01, 0.0, 0.002, np.deg2rad(0.5))
    truth = {k: step for k in range(1, 6)}
    guide = se3_from_xyz_rpy(0.98, 0.0, 0.0, 0.0, 0.0, np.deg2rad(0.45))
    calls = _run(monkeypatch, {k: guide for k in range(1, 6)}, truth, 6)
    np.testing.assert_allclose(calls[1][0], guide, atol=1e-12)
    correction = se3_inverse(guide) @ step
    for k in range(2, 6):
        np.testing.assert_allclose(calls[k][0], guide @ correction, atol=1e-12)
        np.testing.assert_allclose(calls[k][0], step, atol=1e-12)  # a constant guide error: the start is the truth
    assert {tol for _, tol in calls.values()} == {3e-3}


def test_unguided_pairs_and_gaps_start_as_before(monkeypatch):
    """A pair without a guide keeps the plain tolerance and the reference (here none: constant velocity), and the
    guided pair after it starts from its raw guide (no correction across an unguided pair)."""
    step = se3_from_xyz_rpy(1.0, 0.0, 0.0, 0.0, 0.0, np.deg2rad(0.5))
    guide = se3_from_xyz_rpy(0.97, 0.0, 0.0, 0.0, 0.0, 0.0)
    guides = {1: guide, 3: guide}
    calls = _run(monkeypatch, guides, {k: step for k in range(1, 4)}, 4)
    assert calls[2][1] == 1e-4 and calls[1][1] == calls[3][1] == 3e-3
    np.testing.assert_allclose(calls[2][0], step, atol=1e-12)  # constant velocity from pair 1's registration
    np.testing.assert_allclose(calls[3][0], guide, atol=1e-12)


@pytest.mark.parametrize("bad", ["translation", "heading", "fitness"])
def test_a_registration_the_gate_rejects_does_not_steer(monkeypatch, bad):
    """Pair 2's registration lies beyond the wheel gate (0.05 m, 0.0035 rad) or below the fitness floor: pair 3
    starts from its raw guide, pair 4 again from pair 3's correction."""
    guide = se3_from_xyz_rpy(1.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    good = se3_from_xyz_rpy(1.01, 0.0, 0.0, 0.0, 0.0, 0.001)
    wrong = {"translation": se3_from_xyz_rpy(1.2, 0.0, 0.0, 0.0, 0.0, 0.0),
             "heading": se3_from_xyz_rpy(1.0, 0.0, 0.0, 0.0, 0.0, 0.01), "fitness": good}[bad]
    truth = {1: good, 2: wrong, 3: good, 4: good}
    calls = _run(monkeypatch, {k: guide for k in range(1, 5)}, truth, 5, fitness={2: 0.1} if bad == "fitness" else None)
    np.testing.assert_allclose(calls[3][0], guide, atol=1e-12)
    np.testing.assert_allclose(calls[4][0], good, atol=1e-12)


def test_guide_correction_gate_is_planar():
    """Height, roll and pitch of the registration (the guide is planar) do not make the gate reject it."""
    guide = se3_from_xyz_rpy(1.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    reg = se3_from_xyz_rpy(1.02, 0.01, 0.3, 0.02, -0.02, 0.002)
    c = core.guide_correction(guide, reg, 0.9, CFG.gate)
    np.testing.assert_allclose(guide @ c, reg, atol=1e-12)
    assert core.guide_correction(guide, reg, 0.2, CFG.gate) is None


def test_params_carry_the_guided_tolerance():
    cfg = OdometryParams(icp={"guided_relative_tolerance": 2e-3})
    assert cfg.registration_kwargs(guided=True)["relative_tolerance"] == 2e-3
    assert cfg.registration_kwargs()["relative_tolerance"] == OdometryParams().icp.relative_tolerance
