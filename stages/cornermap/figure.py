"""Figure of a corner map over building footprints with covariance ellipses (after Im et al. 2016 Fig. 13)."""
from __future__ import annotations

import numpy as np


def ellipse_points(cov_m2: np.ndarray, n_sigma: float, n: int = 32) -> np.ndarray:
    """(K,2,2) covariances -> (K,n,2) offsets of the n_sigma ellipse."""
    vals, vecs = np.linalg.eigh(cov_m2)
    t = np.linspace(0.0, 2.0 * np.pi, n)
    circle = np.stack([np.cos(t), np.sin(t)], -1)  # (n,2)
    scaled = circle[None] * (n_sigma * np.sqrt(np.clip(vals, 0.0, None)))[:, None, :]
    return np.einsum("kij,knj->kni", vecs, scaled)


def plot_corner_map(path, buildings, corner_map, poses0, truth_en, zoom_m: float = 120.0,
                    ellipse_scale: float = 20.0) -> None:
    """Overview + zoomed panel: footprints (grey), drive 0 (blue), true corners (x), map corners (red) with
    wall-direction ticks and 3-sigma covariance ellipses magnified ``ellipse_scale`` times."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection, PolyCollection

    en = np.column_stack([corner_map["east_m"].to_numpy(), corner_map["north_m"].to_numpy()])
    th = np.column_stack([corner_map["theta1_rad"].to_numpy(), corner_map["theta2_rad"].to_numpy()])
    cov = np.stack([np.stack([corner_map["cov_ee_m2"].to_numpy(), corner_map["cov_en_m2"].to_numpy()], -1),
                    np.stack([corner_map["cov_en_m2"].to_numpy(), corner_map["cov_nn_m2"].to_numpy()], -1)], -2)
    route = np.column_stack([poses0["x_m"].to_numpy(), poses0["y_m"].to_numpy()])
    fig, axes = plt.subplots(1, 2, figsize=(16, 8), gridspec_kw={"width_ratios": [1.3, 1]})
    centre = en[np.argmin(np.linalg.norm(en - np.median(en, axis=0), axis=1))] if len(en) else np.zeros(2)
    for ax, zoom in zip(axes, (False, True)):
        ax.add_collection(PolyCollection([np.asarray(b) for b in buildings], facecolor="0.85", edgecolor="0.5",
                                         linewidth=0.5))
        ax.plot(route[:, 0], route[:, 1], color="tab:blue", lw=0.6, alpha=0.6, label="drive 0 (optimized)")
        ax.plot(truth_en[:, 0], truth_en[:, 1], "x", color="0.3", ms=3, label="true corners")
        tick = 4.0 if zoom else 8.0
        segs = [np.array([p, p + tick * np.array([np.cos(a), np.sin(a)])]) for p, t in zip(en, th) for a in t]
        ax.add_collection(LineCollection(segs, colors="darkred", linewidths=0.8))
        if zoom:
            ell = en[:, None, :] + ellipse_scale * ellipse_points(cov, 3.0)
            ax.add_collection(PolyCollection(list(ell), facecolor="none", edgecolor="magenta", linewidth=0.8))
            ax.set_xlim(centre[0] - zoom_m / 2, centre[0] + zoom_m / 2)
            ax.set_ylim(centre[1] - zoom_m / 2, centre[1] + zoom_m / 2)
            ax.set_title(f"zoom: 3-sigma map covariance x{ellipse_scale:g} (magenta), walls (red)")
        else:
            ax.autoscale()
            ax.set_title(f"corner map: {len(en)} corners")
        ax.plot(en[:, 0], en[:, 1], "o", color="red", ms=2.5 if not zoom else 4, label="map corners")
        ax.set_aspect("equal")
        ax.set_xlabel("east (m)")
        ax.set_ylabel("north (m)")
    axes[0].legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
