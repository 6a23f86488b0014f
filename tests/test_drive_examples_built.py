"""The drive-file examples of docs/drive-file.md (a drive without GNSS with a prior trajectory, a keyframe drive, an
Ouster drive) built into maps on simulated data: the simulator writes a drive of each kind, its files are laid out
and named as the example names them, the drive file is the example's text (read from the doc, so the two cannot
drift; only a measured value of the drive itself is put in: the start heading), and ``cornermap build`` runs as a
user runs it, from a folder outside the checkout. The optimised poses are compared with the simulator's truth in the
map's frame."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from stages.common.geodesy import EnuOrigin, enu_to_geodetic
from stages.common.geometry import write_kitti, write_tum
from stages.common.records import Trajectory
from stages.common.trajectory_frame import move_poses

DOC = Path(__file__).resolve().parents[1] / "docs" / "drive-file.md"
CORNERMAP = [sys.executable, "-m", "mapservice"]
SIM_ORIGIN = EnuOrigin(37.4979, 127.0276, 57.0)  # the tiny preset's


def _example(title: str) -> str:
    text = DOC.read_text()
    section = text[text.index(f"### {title}"):]
    return re.search(r"```yaml\n(.*?)```", section, re.S).group(1)


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    out = subprocess.run(CORNERMAP + args, cwd=cwd, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, (args, out.stdout[-2000:], out.stderr[-3000:])
    return out


def _simulate(tmp: Path, seed: int, max_scans: int, *sets: str) -> Path:
    sim = tmp / "sim"
    args = ["simulate", "--preset", "tiny", "--seed", str(seed), "--drives", "1", "--max-scans", str(max_scans),
            "--out", str(sim), "-q", "--set", "survey=0"]
    for s in sets:
        args += ["--set", s]
    _run(args, tmp)
    return sim


def _stamps_s(drive: Path) -> np.ndarray:
    rows = np.loadtxt(drive / "scans" / "stamps.csv", delimiter=",", skiprows=1)
    return rows[:, 1] * 604800.0 + rows[:, 2]


def _truth(sim: Path) -> np.ndarray:
    return Trajectory.from_tum(sim / "truth" / "drive_0_poses_tum.txt").T


def _map_poses(root: Path) -> tuple[np.ndarray, EnuOrigin]:
    from bench.roots import read

    opt = read(root, "poses_optimized").sort_by("scan_id")
    info = read(root, "drive_info").to_pylist()[0]
    return Trajectory.from_table(opt, "drive_0").T, EnuOrigin(info["origin_lat_deg"], info["origin_lon_deg"],
                                                              info["origin_h_m"])


def _horizontal_rms(root: Path, sim: Path) -> float:
    est, origin = _map_poses(root)
    truth = move_poses(_truth(sim), SIM_ORIGIN, origin)
    assert len(est) == len(truth)
    return float(np.sqrt(np.mean(np.sum((est[:, :2, 3] - truth[:, :2, 3]) ** 2, axis=1))))


def _build(tmp: Path, drive_yaml: Path, *extra: str) -> Path:
    root = tmp / "root"
    outside = tmp / "elsewhere"
    outside.mkdir(exist_ok=True)
    out = _run(["build", "--drive", str(drive_yaml), "--map", "m", "--root", str(root), "--quiet", "--workers", "1",
                *extra], outside)
    assert "published map 'm' version v0001" in out.stdout, out.stdout
    return root


def test_the_gnss_free_example_with_a_local_prior_builds(tmp_path):
    sim = _simulate(tmp_path, 331, 120, "gnss=0", "prior=local", "sensor=os1-64", "lidar_z_m=1.8")
    d = sim / "drive_0"
    t = _stamps_s(d)
    (d / "scans" / "times.txt").write_text("".join(f"{v:.6f}\n" for v in t))
    doc = yaml.safe_load(_example("A drive without GNSS, with a prior trajectory"))
    T_vl = np.asarray(doc["T_vehicle_lidar"], float)
    prior = Trajectory.from_tum(d / "prior.txt")  # the simulator's: the vehicle in the frame of its first pose
    write_tum(d / "slam_poses_tum.txt", prior.stamp_s, prior.T @ T_vl)  # the example's body: lidar
    truth = _truth(sim)
    yaw0 = np.arctan2(truth[0, 1, 0], truth[0, 0, 0])
    doc["start"]["heading_deg"] = round(float((90.0 - np.degrees(yaw0)) % 360.0), 3)  # the drive's own heading
    (d / "drive.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    lat, lon, h = enu_to_geodetic(truth[:1, :3, 3], SIM_ORIGIN)[0]
    root = _build(tmp_path, d / "drive.yaml", "--origin", f"{lat:.9f},{lon:.9f},{h:.3f}")
    rms = _horizontal_rms(root, sim)
    assert rms < 0.25, rms  # the stated start heading is exact here: what is left is the prior's and odometry's


def test_the_keyframe_example_builds(tmp_path):
    sim = _simulate(tmp_path, 332, 60, "gnss=0", "prior=enu", "keyframe_spacing_m=5")
    d = sim / "drive_0"
    t = _stamps_s(d)
    gaps = np.diff(t)
    assert gaps.min() > 0.25 and gaps.max() / gaps.min() > 1.5  # metres apart, irregular
    shutil.move(d / "scans", d / "keyframes")
    (d / "keyframes" / "times.txt").write_text("".join(f"{v:.6f}\n" for v in t))
    prior = Trajectory.from_tum(d / "prior.txt")  # ENU about the simulator's origin, one row per keyframe
    write_kitti(d / "keyframe_poses_kitti.txt", prior.T)
    (d / "drive.yaml").write_text(_example("A keyframe drive"))
    root = _build(tmp_path, d / "drive.yaml")
    truth = _truth(sim)
    prior_rms = float(np.sqrt(np.mean(np.sum((prior.T[:, :2, 3] - truth[:, :2, 3]) ** 2, axis=1))))
    rms = _horizontal_rms(root, sim)
    assert rms < 0.3 and rms < prior_rms + 0.05, (rms, prior_rms)


@pytest.mark.slow  # 70 s: a full tiny drive (250 scans); fewer leave 2 of 3 tiles without a corner (the gate)
def test_the_ouster_example_builds(tmp_path):
    from stages.common.beam_tables import OS1_64_GEN1

    sim = _simulate(tmp_path, 333, 250, "sensor=os1-64", "lidar_x_m=0.3")
    d = sim / "drive_0"
    t = _stamps_s(d)
    shutil.move(d / "scans", d / "points")
    (d / "points" / "stamps.txt").write_text("".join(f"{v:.6f}\n" for v in t))
    (d / "os1_metadata.json").write_text(json.dumps({"beam_intrinsics": {"beam_altitude_angles": list(OS1_64_GEN1)},
                                                     "sensor_info": {"prod_line": "OS-1-64"}}))
    g = np.genfromtxt(d / "gnss_inspva.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    stamp_ns = np.round((g["gps_week"] * 604800.0 + g["gps_seconds"]) * 1e9).astype(np.int64)
    yaw = np.radians(90.0 - g["azimuth_deg"])
    header = ["%time", "field.header.stamp", "field.latitude", "field.longitude", "field.altitude", "yaw_enu_rad"] + \
        [f"field.position_covariance{i}" for i in range(9)]
    lines = [",".join(header)]
    for k in range(len(stamp_ns)):
        cov = np.zeros(9)
        cov[[0, 4, 8]] = np.array([g["std_lon_m"][k], g["std_lat_m"][k], g["std_height_m"][k]]) ** 2
        lines.append(",".join([str(stamp_ns[k] + 1000), str(stamp_ns[k]), f"{g['latitude_deg'][k]:.10f}",
                               f"{g['longitude_deg'][k]:.10f}", f"{g['height_m'][k]:.4f}", f"{yaw[k]:.8f}",
                               *(f"{v:.6f}" for v in cov)]))
    (d / "ins_fix.csv").write_text("\n".join(lines) + "\n")
    (d / "drive.yaml").write_text(_example("An Ouster drive with its metadata"))
    root = _build(tmp_path, d / "drive.yaml")
    rms = _horizontal_rms(root, sim)
    assert rms < 1.0, rms  # the GNSS's own error (tiny: 0.5 m RMS bias) is the frame's
