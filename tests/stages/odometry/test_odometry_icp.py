"""Oracle for the odometry edge frame change (lidar -> vehicle) and its information."""
from __future__ import annotations

import gtsam
import numpy as np

from stages.common.geometry import se3_from_xyz_rpy, se3_inverse
from stages.odometry.core import lidar_to_vehicle_edge


def test_vehicle_edge_information_is_consistent_with_lidar_edge():
    """Sampling the lidar-frame edge with its covariance and mapping it to the vehicle frame reproduces the
    vehicle-frame covariance the function claims."""
    rng = np.random.default_rng(3)
    T_v_l = se3_from_xyz_rpy(1.0, 0.2, 1.7, 0.0, 0.02, 0.01)
    T_l = se3_from_xyz_rpy(1.0, 0.05, 0.0, 0.0, 0.0, 0.02)
    cov_l = np.diag([1e-4, 2e-4, 3e-4, 1e-3, 4e-3, 2e-3])
    T_v, info_v = lidar_to_vehicle_edge(T_l, np.linalg.inv(cov_l), T_v_l)
    xs = rng.multivariate_normal(np.zeros(6), cov_l, size=20000)
    P_l = gtsam.Pose3(T_l)
    P_v = gtsam.Pose3(T_v)
    T_l_v = gtsam.Pose3(se3_inverse(T_v_l))
    samples = np.array([P_v.localCoordinates(gtsam.Pose3(T_v_l).compose(P_l.retract(x)).compose(T_l_v))
                        for x in xs[:4000]])
    L = np.linalg.cholesky(info_v)  # whitened sample covariance must be the identity
    eig = np.linalg.eigvalsh(L.T @ np.cov(samples.T) @ L)
    assert eig.min() > 0.85 and eig.max() < 1.15, eig
    wrong = np.linalg.cholesky(np.linalg.inv(cov_l))  # the un-moved lidar information is not
    assert np.abs(np.linalg.eigvalsh(wrong.T @ np.cov(samples.T) @ wrong) - 1).max() > 0.5
