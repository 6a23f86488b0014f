"""The evaluation's TUM files state their frame and are planar on both sides: the real evo (``evo_ape``, run as a
process with its defaults) on an estimate and a reference file gives the metrics of metrics.json."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fixtures.evaluate import synthetic_drive
from stages.common.geodesy import EnuOrigin
from stages.common.trajectory_frame import read_trajectory_origin
from stages.evaluate.outputs import write_report
from stages.evaluate.params import EvaluateParams
from stages.evaluate.run import evaluate_drive

ORIGIN = EnuOrigin(37.4979, 127.0276, 57.0)


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    rng = np.random.default_rng(37)
    d, cmap, fetch, truth, stamps = synthetic_drive(300, rng)
    # a reference with a heading offset and lateral noise, so that both errors are far from 0
    ref_map = truth + np.column_stack([rng.normal(0, 0.03, len(truth)), rng.normal(0, 0.03, len(truth)),
                                       np.full(len(truth), np.radians(0.3))])
    ev = evaluate_drive(d, cmap, fetch, {"truth": (stamps, truth), "map": (stamps, ref_map)},
                        EvaluateParams(mcl={"n_particles": 300}))
    out = tmp_path_factory.mktemp("eval")
    doc = write_report(out, ev, cmap, None, drive="drive_1", map_info={"version": 1, "enu_origin": ORIGIN.as_dict()})
    return out, doc


def _evo_ape(ref: Path, est: Path, *extra: str) -> float:
    exe = shutil.which("evo_ape") or str(Path(sys.executable).with_name("evo_ape"))
    out = subprocess.run([exe, "tum", str(ref), str(est), "--no_warnings", *extra], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    return float(re.search(r"^\s*rmse\s+([-0-9.e]+)", out.stdout, re.M).group(1))


def test_every_file_states_frame_origin_and_planar_attitude(report):
    out, _ = report
    files = sorted(out.glob("*_tum.txt"))
    assert {p.name for p in files} >= {"ekf_tum.txt", "mcl_tum.txt", "rtk_ins_tum.txt", "icp_dr_tum.txt",
                                       "reference_map_tum.txt", "reference_truth_tum.txt"}
    for path in files:
        head = [ln for ln in path.read_text().splitlines() if ln.startswith("#")]
        assert any(ln.startswith("# attitude: planar") for ln in head), head
        assert read_trajectory_origin(path) is not None
        origin = read_trajectory_origin(path)
        assert (origin.lat_deg, origin.lon_deg, origin.h_m) == pytest.approx((ORIGIN.lat_deg, ORIGIN.lon_deg,
                                                                               ORIGIN.h_m))
        rows = np.loadtxt(path)  # numpy skips the '#' lines too
        assert np.all(rows[:, 3] == 0) and np.all(rows[:, 4:6] == 0)  # z, qx, qy: planar, as said


@pytest.mark.skipif(shutil.which("evo_ape") is None and not Path(sys.executable).with_name("evo_ape").exists(),
                    reason="evo is not installed (pip install evo; it is in the test extra)")
@pytest.mark.parametrize("method", ["ekf", "mcl", "icp_dr"])
def test_evo_ape_with_its_defaults_gives_the_metrics(report, method):
    out, doc = report
    entry = doc["methods"][method]["map_relative"]
    summary = entry.get("all_epochs") or entry  # the EKF file holds its start-up epochs too
    ref, est = out / "reference_map_tum.txt", out / f"{method}_tum.txt"
    assert _evo_ape(ref, est) == pytest.approx(summary["rms_2d_m"], abs=2e-6)
    assert _evo_ape(ref, est, "--pose_relation", "angle_deg") == pytest.approx(summary["heading_rms_deg"], abs=2e-5)
    assert summary["heading_rms_deg"] > 0.1  # the reference's 0.3 deg heading offset is in it
    assert json.loads((out / "metrics.json").read_text())["methods"][method]["map_relative"] is not None
