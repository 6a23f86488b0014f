"""Documentation figure of one marking layer: intensity, traversable mask, extracted markings side by side."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np


def plot_marking_layers(intensity_u8: np.ndarray, traversable: np.ndarray, marking: np.ndarray, path: Path,
                        title: str, extent_m: tuple[float, float, float, float] | None = None,
                        truth: np.ndarray | None = None) -> Path:
    """Write a PNG with three (four with ``truth``) panels; ``extent_m`` = (west, east, south, north) for the
    axes in metres. Row 0 of every array is the north edge."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("intensity (normalised, traversable cells)", intensity_u8, "gray"),
              ("traversable cells", traversable, "gray"), ("extracted markings", marking, "gray")]
    if truth is not None:
        overlay = np.zeros(marking.shape + (3,), np.float32)
        overlay[..., 0] = marking & ~truth  # red: false positive
        overlay[..., 1] = marking & truth  # green: hit
        overlay[..., 2] = truth & ~marking  # blue: missed
        panels.append(("vs truth (green hit, red extra, blue missed)", overlay, None))
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 4.6), constrained_layout=True)
    for ax, (name, img, cmap) in zip(axes, panels):
        ax.imshow(img.astype(np.float32) if img.ndim == 2 else img, cmap=cmap, extent=extent_m,
                  interpolation="nearest")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("east (m)" if extent_m else "col")
    axes[0].set_ylabel("north (m)" if extent_m else "row")
    fig.suptitle(title, fontsize=10)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)
    return path
