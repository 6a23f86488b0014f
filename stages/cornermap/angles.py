"""Direction-angle conventions of a corner's two walls (pure numpy).

Canonical order, stated once for the whole product: a corner's two wall directions (the directions from the
corner along each wall) are an unordered pair physically. We store them so that **turning counter-clockwise
from theta1 by less than 180 degrees reaches theta2**, i.e. ``wrap(theta2 - theta1)`` lies in ``(0, pi]``.
Both angles are wrapped to ``[-pi, pi)``. The rule is invariant under rotation, so a pair canonical in the lidar
frame stays canonical after the yaw rotation into ENU. Near a straight wedge (theta2 - theta1 close to 180
degrees) noise can flip the order, which is why comparisons also try the swapped pair.
"""
from __future__ import annotations

import numpy as np


def wrap_rad(angle: np.ndarray) -> np.ndarray:
    """Wrap to [-pi, pi)."""
    return (np.asarray(angle, dtype=float) + np.pi) % (2.0 * np.pi) - np.pi


def canonicalize_pairs(theta_rad: np.ndarray) -> np.ndarray:
    """(N,2) wall directions -> (N,2) wrapped, ordered so that wrap(theta2 - theta1) is in (0, pi]."""
    theta = wrap_rad(theta_rad)
    swap = wrap_rad(theta[:, 1] - theta[:, 0]) < 0.0
    out = theta.copy()
    out[swap] = theta[swap][:, ::-1]
    return out


def pair_difference_rad(a_rad: np.ndarray, b_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Largest absolute wall-direction difference between pairs a and b (N,2), trying b as given and swapped.

    Returns (difference, swapped): ``swapped[i]`` is True when b[i] matches a[i] better in reversed order.
    """
    direct = np.maximum(np.abs(wrap_rad(a_rad[:, 0] - b_rad[:, 0])), np.abs(wrap_rad(a_rad[:, 1] - b_rad[:, 1])))
    crossed = np.maximum(np.abs(wrap_rad(a_rad[:, 0] - b_rad[:, 1])), np.abs(wrap_rad(a_rad[:, 1] - b_rad[:, 0])))
    swapped = crossed < direct
    return np.where(swapped, crossed, direct), swapped


def circular_mean_by_label(theta_rad: np.ndarray, labels: np.ndarray, n_labels: int,
                           weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Weighted circular mean of angles grouped by label -> (mean_rad (n_labels,), resultant length in [0,1])."""
    w = np.ones(len(theta_rad)) if weights is None else np.asarray(weights, dtype=float)
    c = np.bincount(labels, w * np.cos(theta_rad), minlength=n_labels)
    s = np.bincount(labels, w * np.sin(theta_rad), minlength=n_labels)
    total = np.bincount(labels, w, minlength=n_labels)
    with np.errstate(invalid="ignore", divide="ignore"):
        resultant = np.hypot(c, s) / total
    return wrap_rad(np.arctan2(s, c)), np.nan_to_num(resultant)
