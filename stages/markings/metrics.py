"""Pixel precision / recall of a marking mask against truth, with a tolerance in cells."""
from __future__ import annotations

import cv2
import numpy as np


def _dilate(mask: np.ndarray, tolerance_px: int) -> np.ndarray:
    if tolerance_px <= 0:
        return mask.astype(bool)
    kernel = np.ones((2 * tolerance_px + 1, 2 * tolerance_px + 1), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), kernel).astype(bool)


def match_masks(predicted: np.ndarray, truth: np.ndarray, tolerance_px: int = 1) -> dict[str, float]:
    """Precision = predicted pixels within ``tolerance_px`` (Chebyshev) of a truth pixel / predicted pixels;
    recall = truth pixels within ``tolerance_px`` of a predicted pixel / truth pixels. NaN when undefined."""
    if predicted.shape != truth.shape:
        raise ValueError(f"mask shapes differ: predicted {predicted.shape}, truth {truth.shape}")
    pred, true = predicted.astype(bool), truth.astype(bool)
    n_pred, n_true = int(pred.sum()), int(true.sum())
    hit_pred = int((pred & _dilate(true, tolerance_px)).sum())
    hit_true = int((true & _dilate(pred, tolerance_px)).sum())
    return {"precision": hit_pred / n_pred if n_pred else float("nan"),
            "recall": hit_true / n_true if n_true else float("nan"),
            "n_predicted": n_pred, "n_truth": n_true}
