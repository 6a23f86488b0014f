"""Synthetic truth for pose-graph oracles: a two-lap block circuit, noisy ICP edges, biased GNSS."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stages.common.geometry import se3_from_xyz_rpy, se3_inverse
from stages.posegraph.factors.drive import DriveInput
from stages.posegraph.params import PosegraphParams

# The synthetic drives' registrations state their own noise exactly; the registration noise the stage adds by default
# (real ICP's information is overconfident, docs/posegraph.md Known limits) would misstate them. A test that models
# overconfident registrations asks for it.
HONEST_REGISTRATIONS = {"factors": {"registration": {"along_m": 0.0, "cross_m": 0.0, "yaw_deg": 0.0}}}


def posegraph_config(overrides: dict | None = None) -> PosegraphParams:
    """The pose graph's params (its config sections) with ``overrides`` (dotted keys, ``{"loops.stride_m": 4.0}``)
    over the stage's defaults (the registrations taken as honest unless ``overrides`` say otherwise)."""
    return PosegraphParams.model_validate(HONEST_REGISTRATIONS).updated(overrides or {})


def base_sections(overrides: dict | None = None):
    """The two sections ``base_problem`` takes: odometry factors and GNSS/INS priors."""
    cfg = posegraph_config(overrides)
    return cfg.factors, cfg.gnss


def circuit_truth(n_laps: int = 2, side_m: float = 60.0, step_m: float = 1.0, z_amp_m: float = 1.5) -> np.ndarray:
    """Vehicle poses (N,4,4) driving a rounded square ``n_laps`` times with a gentle hill."""
    per_side = int(side_m / step_m)
    yaws = []
    for lap in range(n_laps):
        for side in range(4):
            yaws += [side * np.pi / 2] * (per_side - 5) + list(
                np.linspace(side * np.pi / 2, (side + 1) * np.pi / 2, 6)[1:]
            )
    yaws = np.array(yaws)
    xy = np.cumsum(step_m * np.column_stack([np.cos(yaws), np.sin(yaws)]), axis=0)
    z = z_amp_m * np.sin(2 * np.pi * xy[:, 0] / (2 * side_m))
    pitch = -np.gradient(z) / step_m
    T = np.array([se3_from_xyz_rpy(x, y, zz, 0.0, p, yw) for (x, y), zz, p, yw in zip(xy, z, pitch, yaws)])
    return T


def perturb(T: np.ndarray, sigma_rot: float, sigma_t: float, rng: np.random.Generator) -> np.ndarray:
    xi = rng.normal(0, 1, 6) * np.array([sigma_rot] * 3 + [sigma_t] * 3)
    D = np.eye(4)
    D[:3, :3] = Rotation.from_rotvec(xi[:3]).as_matrix()
    D[:3, 3] = xi[3:]
    return T @ D


def gnss_bias(n: int, dt_s: float, sigma_m: float, tau_s: float, rng: np.random.Generator) -> np.ndarray:
    """(n,3) first-order Gauss-Markov bias with stationary std ``sigma_m`` (slowly varying, like canyons)."""
    a = np.exp(-dt_s / tau_s)
    b = np.zeros((n, 3))
    b[0] = rng.normal(0, sigma_m, 3)
    w = rng.normal(0, sigma_m * np.sqrt(1 - a * a), (n, 3))
    for k in range(1, n):
        b[k] = a * b[k - 1] + w[k]
    return b


def make_drive(T_true: np.ndarray, rng: np.random.Generator, *, name: str = "d0", dt_s: float = 0.1,
               t0_s: float = 0.0, edge_sigma_m: float = 0.005, edge_sigma_rad: float = 0.0003,
               gnss_sigma_m: float = 0.85, gnss_tau_s: float = 20.0, reported_std_m: float = 0.3,
               outage: slice | None = None) -> DriveInput:
    n = len(T_true)
    edge_T = np.tile(np.eye(4), (n, 1, 1))
    for k in range(1, n):
        edge_T[k] = perturb(se3_inverse(T_true[k - 1]) @ T_true[k], edge_sigma_rad, edge_sigma_m, rng)
    info = np.diag([edge_sigma_rad ** -2] * 3 + [edge_sigma_m ** -2] * 3)
    gnss = np.array([perturb(T, 0.002, 0.0, rng) for T in T_true])
    gnss[:, :3, 3] += gnss_bias(n, dt_s, gnss_sigma_m, gnss_tau_s, rng) * np.array([1, 1, 0.7])
    valid = np.ones(n, bool)
    if outage is not None:
        valid[outage] = False
    ok = np.ones(n, bool)
    ok[0] = False
    return DriveInput(name, np.arange(n), (t0_s + np.arange(n) * dt_s) * 1e9 // 1, gnss,
                      np.tile([reported_std_m, reported_std_m, 2 * reported_std_m], (n, 1)),
                      np.full(n, 0.005), valid, edge_T, np.tile(info, (n, 1, 1)), ok, np.eye(4))


@pytest.fixture
def two_lap_drive():
    T_true = circuit_truth()
    drive = make_drive(T_true, np.random.default_rng(11))
    drive.stamps_ns = drive.stamps_ns.astype(np.int64)
    return T_true, drive
