"""Figures of corner extraction on the real samples (paper Figure 9 style) and small readers for them.

    .venv/bin/python -m bench.plot_corners [--data ../shared/data] [--out docs/figures]

Writes docs/figures/corners_nuscenes.png and corners_kitti_<frame>.png and prints the counts per scan.
The readers here are local stand-ins until the ingest stage's readers exist.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from pipeline.errors import FormatError
from stages.corners.core import CornerTrace, trace_corners
from stages.corners.lines import LINE


def read_nuscenes_bin(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """nuScenes LIDAR_TOP .pcd.bin: float32 records x, y, z, intensity, ring (0 = lowest beam)."""
    raw = np.fromfile(path, np.float32)
    if raw.size % 5:
        raise FormatError(f"{path}: expected float32 records of 5 values, got {raw.size} floats")
    rec = raw.reshape(-1, 5)
    return rec[:, :3], rec[:, 4].astype(np.int16)


def read_kitti_pcd(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Binary PCD 'x y z intensity' of KITTI HDL-64E; rings from point order (a new laser starts where the
    azimuth goes from negative to non-negative), numbered so that 0 = the lowest beam."""
    raw = Path(path).read_bytes()
    marker = b"DATA binary\n"
    end = raw.find(marker)
    if end < 0:
        raise FormatError(f"{path}: no 'DATA binary' line in the PCD header")
    header = raw[:end].decode("ascii", "replace").splitlines()
    n = int(next(line.split()[1] for line in header if line.startswith("POINTS")))
    offset = end + len(marker)
    if len(raw) - offset < 16 * n:
        raise FormatError(f"{path}: header says {n} points, the data holds {(len(raw) - offset) // 16}")
    pts = np.frombuffer(raw, np.float32, count=4 * n, offset=offset).reshape(n, 4)[:, :3]
    pts = pts[np.any(pts != 0.0, axis=1)]
    az = np.arctan2(pts[:, 1], pts[:, 0])
    order_ring = np.cumsum(np.r_[False, (az[:-1] < 0) & (az[1:] >= 0)])
    return pts, (order_ring.max() - order_ring).astype(np.int16)


def plot_trace(trace: CornerTrace, title: str, path: Path, extent_m: float = 40.0) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Ellipse

    fig, ax = plt.subplots(figsize=(9, 9))
    ax.scatter(trace.xy_m[:, 0], trace.xy_m[:, 1], s=0.3, c="0.6", lw=0, label="selected layers")
    lines = trace.lines
    for label, color, name in ((LINE, "tab:green", "lines"), (2, "gold", "outliers: variance"),
                               (3, "orange", "outliers: short")):
        idx = np.flatnonzero(trace.line_label == label)
        for j, i in enumerate(idx):
            seg = trace.xy_m[lines.start[i]:lines.stop[i] + 1]
            ax.plot(seg[:, 0], seg[:, 1], color=color, lw=1.2 if label == LINE else 0.8,
                    label=name if j == 0 else None)
    cand = trace.candidates
    ax.plot(cand.x_m, cand.y_m, "k*", ms=7, label=f"candidates ({len(cand)})")
    c = trace.corners
    ax.plot(c.x_m, c.y_m, "r*", ms=14, label=f"corners ({len(c)})")
    for i in range(len(c)):
        for th in (c.theta1_rad[i], c.theta2_rad[i]):
            ax.plot([c.x_m[i], c.x_m[i] + 2.0 * np.cos(th)], [c.y_m[i], c.y_m[i] + 2.0 * np.sin(th)], "r-", lw=1.5)
        w, v = np.linalg.eigh(c.cov_m2[i])
        ang = np.degrees(np.arctan2(v[1, 1], v[0, 1]))
        ax.add_patch(Ellipse((c.x_m[i], c.y_m[i]), 2 * 3 * 5 * np.sqrt(w[1]), 2 * 3 * 5 * np.sqrt(w[0]),
                             angle=ang, fill=False, color="m", lw=1))
    ax.plot(0, 0, "b^", ms=10, label="sensor")
    ax.set_xlim(-extent_m, extent_m)
    ax.set_ylim(-extent_m, extent_m)
    ax.set_aspect("equal")
    ax.set_xlabel("x forward [m]")
    ax.set_ylabel("y left [m]")
    ax.set_title(f"{title}\nmagenta: 3-sigma covariance ellipses x5; red ticks: wall directions (2 m)", fontsize=9)
    ax.legend(loc="upper right", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "docs" / "figures")
    ap.add_argument("--kitti-frames", default="0,10,21", help="comma-separated KITTI frames to plot")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    for f in sorted((args.data / "nuscenes_hdl32e_sweep").glob("*.pcd.bin")):
        tr = trace_corners(*read_nuscenes_bin(f))
        plot_trace(tr, f"nuScenes HDL-32E sweep {f.name[:40]}...: {len(tr.corners)} corners",
                   args.out / "corners_nuscenes.png")
        print(f"nuscenes {f.name}: layers {tr.layers_used.tolist()} candidates {len(tr.candidates)} "
              f"corners {len(tr.corners)}")
    frames = {int(x) for x in args.kitti_frames.split(",") if x}
    counts = []
    for f in sorted((args.data / "kitti_raw_0048_city").glob("*.pcd")):
        tr = trace_corners(*read_kitti_pcd(f))
        counts.append(len(tr.corners))
        print(f"kitti {f.name}: layers {tr.layers_used.tolist()} candidates {len(tr.candidates)} "
              f"corners {len(tr.corners)}")
        if int(f.stem) in frames:
            plot_trace(tr, f"KITTI 0048 HDL-64E frame {f.stem}: {len(tr.corners)} corners",
                       args.out / f"corners_kitti_{f.stem[-4:]}.png")
    if counts:
        print(f"kitti: {len(counts)} scans, corners per scan mean {np.mean(counts):.1f} min {min(counts)} "
              f"max {max(counts)}")


if __name__ == "__main__":
    main()
