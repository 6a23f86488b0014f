"""Figures and tables of docs/simulator.md (matplotlib Agg).

    .venv/bin/python -m stages.simulate.figures --tiny DIR_TINY --gangnam DIR_GANGNAM \
        --nuscenes ../shared/data/nuscenes_hdl32e_sweep --out docs/figures
"""
from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np

from stages.simulate.writers import PCD_DTYPE


def read_pcd(path: Path) -> np.ndarray:
    raw = path.read_bytes()
    return np.frombuffer(raw.partition(b"DATA binary\n")[2], PCD_DTYPE)


def read_nuscenes(folder: Path) -> np.ndarray:
    f = sorted(folder.glob("*.pcd.bin"))[0]
    return np.fromfile(f, np.float32).reshape(-1, 5)


def ring_table(sim: np.ndarray, real: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Valid returns (range > 1 m) per ring, simulated vs real."""
    r_sim = np.sqrt(sim["x"].astype(float) ** 2 + sim["y"] ** 2 + sim["z"] ** 2)
    r_real = np.linalg.norm(real[:, :3], axis=1)
    a = np.bincount(sim["ring"][r_sim > 1.0], minlength=32)
    b = np.bincount(real[r_real > 1.0, 4].astype(int), minlength=32)
    return a, b


def plot_rings(sim: np.ndarray, real: np.ndarray, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    a, b = ring_table(sim, real)
    a, b = a / 2250.0, b / 1084.0  # firings per ring: 2250 at 10 Hz (0.16 deg), 1084 in the 20 Hz nuScenes sweep
    r_sim = np.sqrt(sim["x"].astype(float) ** 2 + sim["y"] ** 2 + sim["z"] ** 2)
    r_real = np.linalg.norm(real[:, :3], axis=1)
    fig, ax = plt.subplots(1, 3, figsize=(16, 4.5))
    ax[0].bar(np.arange(32) - 0.2, a, 0.4, label="simulated (tiny, one scan)")
    ax[0].bar(np.arange(32) + 0.2, b, 0.4, label="nuScenes HDL-32E sweep")
    ax[0].set_xlabel("ring (0 = lowest beam)")
    ax[0].set_ylabel("share of firings with a return > 1 m")
    ax[0].legend()
    bins = np.arange(0, 101, 2.5)
    ax[1].hist(r_sim[r_sim > 1], bins, histtype="step", density=True, label="simulated")
    ax[1].hist(r_real[r_real > 1], bins, histtype="step", density=True, label="nuScenes")
    ax[1].set_xlabel("range (m)")
    ax[1].set_ylabel("density")
    ax[1].set_yscale("log")
    ax[1].legend()
    ax[2].scatter(sim["x"], sim["y"], c=sim["ring"], s=0.2, cmap="turbo")
    ax[2].set_aspect("equal")
    ax[2].set_xlim(-50, 50)
    ax[2].set_ylim(-50, 50)
    ax[2].set_title("simulated scan (lidar frame), coloured by ring")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def plot_birdseye(sim_dir: Path, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import cv2
    import matplotlib.pyplot as plt

    from stages.common.records import Trajectory

    city = json.loads((sim_dir / "truth/city.json").read_text())
    meta = json.loads((sim_dir / "truth/markings.json").read_text())
    img = cv2.imread(str(sim_dir / "truth/markings.png"), cv2.IMREAD_GRAYSCALE)
    small = cv2.resize(img, (img.shape[1] // 4, img.shape[0] // 4), interpolation=cv2.INTER_AREA)
    res = meta["resolution_m"]
    extent = [meta["west_m"], meta["west_m"] + img.shape[1] * res, meta["north_m"] - img.shape[0] * res,
              meta["north_m"]]
    fig, ax = plt.subplots(figsize=(14, 11))
    ax.imshow(np.minimum(small.astype(float) * 3, 255), cmap="gray_r", extent=extent, vmax=255 * 2.5, alpha=0.9)
    for b in city["buildings"]:
        fp = np.array(b["footprint_en"])
        built = np.array(b.get("outline_en", b["footprint_en"]))  # rounded / chamfered corners as built
        ax.fill(built[:, 0], built[:, 1], color="0.75", ec="0.3", lw=0.6)
        for k, g in enumerate(b["glass_walls"]):
            if g:
                seg = fp[[k, (k + 1) % len(fp)]]
                ax.plot(seg[:, 0], seg[:, 1], color="deepskyblue", lw=2.2)
    for item in city.get("furniture", []):
        for e, n, yaw, length, width, *_ in item["boxes_en"]:
            c, s_ = np.cos(yaw), np.sin(yaw)
            loc = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1], [-1, -1]]) * [length / 2, width / 2]
            ax.plot(e + c * loc[:, 0] - s_ * loc[:, 1], n + s_ * loc[:, 0] + c * loc[:, 1], color="darkorange", lw=1.0)
    ax.plot([], [], color="darkorange", lw=1.0, label="street furniture")
    trees = np.array([[t["east_m"], t["north_m"]] for t in city["trees"]])
    ax.scatter(trees[:, 0], trees[:, 1], s=6, color="forestgreen", label="trees")
    T = Trajectory.from_tum(sim_dir / "truth/drive_0_poses_tum.txt").T
    ax.plot(T[:, 0, 3], T[:, 1, 3], color="crimson", lw=1.2, label="drive 0 (truth)")
    ax.plot([], [], color="deepskyblue", lw=2.2, label="glass walls")
    ax.set_aspect("equal")
    ax.legend(loc="upper right")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title(f"simulated city ({len(city['buildings'])} buildings, {len(trees)} trees); markings in black")
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)


def plot_scan_top(sim_dir: Path, drive: str, scan_id: int, out: Path, half_m: float = 35.0) -> dict:
    """One scan from above in the map frame (truth pose, no deskew) over the built outlines and the furniture:
    the lead vehicle ahead, rounded corners, mixed pixels trailing off facade edges. Returns what it shows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from stages.common.records import Trajectory

    city = json.loads((sim_dir / "truth/city.json").read_text())
    pts = read_pcd(sim_dir / drive / "scans" / f"{scan_id:06d}.pcd")
    T = Trajectory.from_tum(sim_dir / "truth" / f"{drive}_poses_tum.txt").T
    xyz = np.column_stack([pts["x"], pts["y"], pts["z"] + 1.9]).astype(float) @ T[scan_id, :3, :3].T + T[scan_id, :3, 3]
    keep = xyz[:, 2] > 0.3  # above the road: walls, vehicles, furniture, trees
    fig, ax = plt.subplots(figsize=(9, 9))
    for b in city["buildings"]:
        fp = np.array(b["footprint_en"])
        built = np.array(b.get("outline_en", b["footprint_en"]))
        ax.fill(built[:, 0], built[:, 1], color="0.88", ec="0.5", lw=0.6)
        ax.plot(*np.vstack([fp, fp[:1]]).T, color="0.5", lw=0.5, ls=":")
    for item in city.get("furniture", []):
        for e, n, yaw, length, width, *_ in item["boxes_en"]:
            c, s_ = np.cos(yaw), np.sin(yaw)
            loc = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1], [-1, -1]]) * [length / 2, width / 2]
            ax.plot(e + c * loc[:, 0] - s_ * loc[:, 1], n + s_ * loc[:, 0] + c * loc[:, 1], color="darkorange", lw=1.2)
    sc = ax.scatter(xyz[keep, 0], xyz[keep, 1], s=0.6, c=np.minimum(xyz[keep, 2], 6.0), cmap="viridis")
    ax.plot(T[:, 0, 3], T[:, 1, 3], color="crimson", lw=0.8)
    ax.scatter([T[scan_id, 0, 3]], [T[scan_id, 1, 3]], marker="^", color="crimson", s=60, zorder=5)
    ax.set_xlim(T[scan_id, 0, 3] - half_m, T[scan_id, 0, 3] + half_m)
    ax.set_ylim(T[scan_id, 1, 3] - half_m, T[scan_id, 1, 3] + half_m)
    ax.set_aspect("equal")
    fig.colorbar(sc, ax=ax, shrink=0.7, label="height above road (m), points above 0.3 m")
    ax.set_title(f"{drive} scan {scan_id}: built outlines (grey; dotted: walls' intersections), furniture (orange)")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return {"points": int(len(xyz)), "above_road": int(keep.sum())}


def plot_gnss(sim_dir: Path, out: Path) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from stages.common.geodesy import EnuOrigin, geodetic_to_enu
    from stages.common.records import Trajectory

    sim = json.loads((sim_dir / "simulation.json").read_text())
    truth = Trajectory.from_tum(sim_dir / "truth/drive_0_poses_tum.txt")
    stamps, T = truth.stamp_s, truth.T
    rows = list(csv.reader(open(sim_dir / "drive_0/gnss_inspva.csv")))[1:]
    g = np.array([[float(v) for v in r[1:12]] for r in rows])
    stamps = stamps - float(rows[0][0]) * 604800.0  # TUM truth is in full GPS seconds; the CSV in week seconds
    enu = geodetic_to_enu(g[:, 1], g[:, 2], g[:, 3], EnuOrigin.from_dict(sim["enu_origin"]))
    inside = (g[:, 0] >= stamps[0]) & (g[:, 0] <= stamps[-1])
    e = enu[inside, 0] - np.interp(g[inside, 0], stamps, T[:, 0, 3])
    n = enu[inside, 1] - np.interp(g[inside, 0], stamps, T[:, 1, 3])
    h = np.hypot(e, n)
    fig, ax = plt.subplots(figsize=(12, 3.8))
    ax.plot(g[inside, 0] - g[0, 0], h, lw=0.7, label="horizontal error vs truth")
    ax.plot(g[inside, 0] - g[0, 0], np.hypot(g[inside, 7], g[inside, 8]), lw=0.7, label="reported std (horizontal)")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("m")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return {"rms_m": float(np.sqrt(np.mean(h ** 2))), "max_m": float(h.max()),
            "seconds_above_1m": float((h > 1).sum() * np.median(np.diff(g[:, 0])))}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--tiny", type=Path, required=True)
    ap.add_argument("--gangnam", type=Path)
    ap.add_argument("--nuscenes", type=Path, required=True)
    ap.add_argument("--out", type=Path, default=Path("docs/figures"))
    ap.add_argument("--scan", default="drive_0/scans/000100.pcd")
    ap.add_argument("--top-scan", type=int, help="also draw this scan of --tiny's drive 0 from above "
                    "(simulator_tiny_scan_top.png)")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.top_scan is not None:
        print(
            "scan from above:",
            plot_scan_top(args.tiny, "drive_0", args.top_scan, args.out / "simulator_tiny_scan_top.png"),
        )
    sim, real = read_pcd(args.tiny / args.scan), read_nuscenes(args.nuscenes)
    plot_rings(sim, real, args.out / "simulator_rings.png")
    a, b = ring_table(sim, real)
    print("| ring | elevation deg | simulated returns (of 2250) | nuScenes returns (of 1084) |\n|---|---|---|---|")
    from stages.simulate.sensor import ELEVATION_DEG

    for k in range(32):
        print(f"| {k} | {ELEVATION_DEG[k]:.2f} | {a[k]} ({a[k] / 2250:.0%}) | {b[k]} ({b[k] / 1084:.0%}) |")
    print(f"| all | | {a.sum()} | {b.sum()} |")
    if args.gangnam:
        plot_birdseye(args.gangnam, args.out / "simulator_gangnam_birdseye.png")
        print("GNSS drive 0 vs truth:", plot_gnss(args.gangnam, args.out / "simulator_gangnam_gnss.png"))


if __name__ == "__main__":
    main()
