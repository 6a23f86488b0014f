"""The bench's information bound: the rigid 2-D fit recovers a known rotation and translation."""
from __future__ import annotations

import numpy as np
import pytest

from bench.bench_posegraph_root import rigid_fit_2d


def test_rigid_fit_recovers_a_known_transform_and_is_a_rotation():
    rng = np.random.default_rng(3)
    src = rng.uniform(-500, 500, (400, 2))
    a = np.deg2rad(0.3)
    R_true = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    dst = src @ R_true.T + np.array([0.4, -0.2]) + rng.normal(0, 0.01, src.shape)
    R, t = rigid_fit_2d(src, dst)
    assert np.rad2deg(np.arctan2(R[1, 0], R[0, 0])) == pytest.approx(0.3, abs=1e-3)
    assert t == pytest.approx([0.4, -0.2], abs=5e-3)
    assert np.linalg.det(R) == pytest.approx(1.0)
    R_m, _ = rigid_fit_2d(src, src * np.array([1.0, -1.0]))  # a mirror is not a rigid motion
    assert np.linalg.det(R_m) == pytest.approx(1.0)
