"""Oracles of the wheel scale taken from the span edges (``factors/wheel.py``, ``span_scale``): consecutive ICP edges
that are systematically long (demo calibration seed 201: +1,400 ppm) hand their error to a wheel calibrated on them,
and the fused wheel factors, each stated as independent, hand it to the map, which then grows by that ratio
whatever its GNSS says. Synthetic truth -> biased consecutive edges, scale-true span edges, a wheel 1 % short ->
calibrate -> solve -> the map's shape against the truth after a rigid fit."""
from __future__ import annotations

import numpy as np
import pytest

from stages.common.geometry import se3_from_xyz_rpy, se3_inverse
from stages.posegraph.factors.base import base_problem
from stages.posegraph.factors.drive import SpanEdges
from stages.posegraph.factors.graph import optimize
from stages.posegraph.factors.wheel import calibrate_wheel, calibrated_wheel_increments, span_scale
from stages.posegraph.map_frame import _fit_operator, frame_basis, travel_weights
from tests.stages.posegraph.conftest import base_sections, circuit_truth, make_drive, perturb

WHEEL_SCALE = 0.99  # the wheel measures 1 % short
ICP_LONG = 2e-3  # the consecutive registrations are 2,000 ppm long


def _drive(seed: int, span_sigma_m: float = 0.005, side_m: float = 120.0, span: int = 30, rot_sigma_rad: float = 2e-5):
    """One lap of a rounded square; consecutive edges ``ICP_LONG`` long, overlapping span edges of ``span`` scans
    true to ``span_sigma_m``, a wheel ``WHEEL_SCALE`` short with 1 mm noise, the GNSS bias of ``make_drive``."""
    rng = np.random.default_rng(seed)
    T_true = circuit_truth(n_laps=1, side_m=side_m)
    drive = make_drive(T_true, rng, gnss_sigma_m=0.6, gnss_tau_s=60.0, reported_std_m=0.2,
                       edge_sigma_rad=rot_sigma_rad)
    drive.stamps_ns = drive.stamps_ns.astype(np.int64)
    drive.edge_T[1:, :3, 3] *= 1.0 + ICP_LONG
    wheel = np.tile(np.eye(4), (drive.n, 1, 1))
    for k in range(1, drive.n):
        inc = se3_inverse(T_true[k - 1]) @ T_true[k]
        wheel[k] = se3_from_xyz_rpy(WHEEL_SCALE * inc[0, 3] + rng.normal(0, 0.001), inc[1, 3], 0.0, 0.0, 0.0,
                                    np.arctan2(inc[1, 0], inc[0, 0]) + rng.normal(0, 1e-4))
    drive.wheel_T, drive.wheel_ok = wheel, np.ones(drive.n, bool)
    i = np.arange(0, drive.n - span, span // 3)  # overlapping spans, as the odometry's are nested
    j = i + span
    T_ij = np.array([perturb(se3_inverse(T_true[a]) @ T_true[b], rot_sigma_rad, span_sigma_m, rng)
                     for a, b in zip(i, j)])
    info = np.diag([rot_sigma_rad ** -2] * 3 + [span_sigma_m ** -2] * 3)
    drive.spans = SpanEdges(i, j, T_ij, np.tile(info, (len(i), 1, 1)))
    return T_true, drive


def _shape_error(poses: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(horizontal RMS error m left after the travel-weighted rigid fit (the map frame's: ``map_frame.py``), the
    map's scale error from the similarity fit)."""
    en = T_true[:, :2, 3]
    w = travel_weights(en)
    ref = np.average(en, axis=0, weights=w)
    e = np.column_stack([poses[:, :2, 3] - en, np.zeros(len(en))])
    G = frame_basis(en, ref)
    r = e - np.einsum("nak,k->na", G, np.einsum("nak,na->k", _fit_operator(G, w), e))
    G4 = frame_basis(en, ref, scale=True)
    scale = float(np.einsum("nak,na->k", _fit_operator(G4, w), e)[3])
    return float(np.sqrt(np.mean(np.sum(r[:, :2] ** 2, axis=1)))), scale


def test_the_span_scale_recovers_the_wheel_scale_that_the_consecutive_edges_miss():
    _, drive = _drive(1)
    old = calibrate_wheel(drive, from_spans=False)
    new = calibrate_wheel(drive)
    assert new.scale_source == "span edges" and new.n_spans >= 10
    assert old.scale_source == "consecutive edges"
    true_scale = 1.0 / WHEEL_SCALE
    # the consecutive edges' error (their median over ~470 edges of 5 mm noise on 1 m: +-0.0003 per sigma)
    assert old.scale / true_scale - 1 == pytest.approx(ICP_LONG, abs=1e-3)
    assert abs(new.scale / true_scale - 1) < 1e-4, new.scale / true_scale - 1
    # the gyro bias is the consecutive edges' either way
    assert new.yaw_rate_bias_radps == old.yaw_rate_bias_radps


def test_the_span_scale_leaves_out_a_span_a_street_mismatched_and_needs_enough_spans():
    _, drive = _drive(2)
    bias = calibrate_wheel(drive).yaw_rate_bias_radps
    scale, used = span_scale(drive, bias)
    bad = drive.spans.T_i_j.copy()
    bad[3, 0, 3] += 3.0  # 10 % along a 30 m span: a registration that slid along a street without cross structure
    drive.spans = SpanEdges(drive.spans.i, drive.spans.j, bad, drive.spans.information)
    scale_bad, used_bad = span_scale(drive, bias)
    assert used_bad == used - 1 and scale_bad == pytest.approx(scale, abs=5e-5)
    few = SpanEdges(drive.spans.i[:5], drive.spans.j[:5], bad[:5], drive.spans.information[:5])
    drive.spans = few
    assert span_scale(drive, bias) is None
    assert calibrate_wheel(drive).scale_source == "consecutive edges"  # falls back
    drive.wheel_ok[drive.spans.i[0] + 3] = False  # a wheel gap inside a span leaves that span out
    drive.spans = SpanEdges(drive.spans.i, drive.spans.j, drive.spans.T_i_j, drive.spans.information)
    assert span_scale(drive, bias, min_spans=1)[1] == 3  # of 5: span 3 mismatched, span 0 across the gap


def test_the_map_keeps_its_shape_with_the_span_scale_where_the_consecutive_edges_grow_it():
    """The wheel fused beside every edge, span edges of 2 cm over 30 m: calibrated on the consecutive edges the map is
    760-790 ppm too large and 0.05 m RMS off after the rigid fit (the GNSS bias chain takes the difference as bias);
    calibrated on the span edges it keeps its shape."""
    shape, scale = {}, {}
    for from_spans in (False, True):
        out = []
        for seed in (3, 4):
            T_true, drive = _drive(seed, span_sigma_m=0.02)
            drive.wheel_T = calibrated_wheel_increments(drive, calibrate_wheel(drive, from_spans=from_spans))
            out.append(_shape_error(optimize(base_problem([drive], *base_sections())[0]), T_true))
        shape[from_spans], scale[from_spans] = max(o[0] for o in out), max(abs(o[1]) for o in out)
    assert shape[False] > 0.045 and scale[False] > 6e-4, (shape, scale)  # measured 0.054-0.057 m, 760-790 ppm
    assert shape[True] < 0.03 and shape[True] < 0.5 * shape[False], shape  # 0.012-0.024 m
    assert scale[True] < 0.5 * scale[False], scale  # 84-268 ppm
