"""End to end on a changed city: `simulate --changes` (tiny, 3 drives, drive 2 after the change), version 1 built
from drives 0 + 1, version 2 from drive 2; version 2's changelog against truth/changes.json.

Slow (two tiny builds: ~3-8 min on the shared 2-core machine); the same run as `bench/bench_changed_city.py`.
"""
from __future__ import annotations

import pytest


@pytest.mark.slow
def test_changelog_finds_the_demolished_corners_and_keeps_the_other_ids(tmp_path):
    from bench.bench_changed_city import run_seed

    r = run_seed("tiny", 7, tmp_path, "sync")
    assert r["removed_mapped"] >= 2  # the demolished building was mapped before the change
    assert r["removed_recall"] >= 0.9 and r["removed_precision"] >= 0.9, r
    assert r["unchanged_in_both"] >= 2 and r["id_kept"] >= 0.99, r
    assert r["marking_px_changed_log"] > 0, r  # the moved crosswalk shows in the marking rasters


@pytest.mark.slow
def test_change_detection_with_statistics_against_the_truth_and_an_unchanged_redrive(tmp_path):
    """bench/bench_change_detection.py on tiny calibration seed 221: map 'chg' (drive 0, then drive 2 after the
    change) lists the demolished and built corners and the moved crosswalk's regions; map 'same' (drive 0, then
    drive 1 of the same city) lists no marking region and no moved corner (its corners missing from one re-drive are
    the measured false alarms of absence: docs/map-format.md)."""
    import subprocess
    import sys

    from bench.bench_change_detection import build_maps, score
    from bench.bench_localizability import workflow_for
    from bench.roots import simulator_dir

    root = tmp_path / "tiny-221"
    subprocess.run([sys.executable, "-m", "mapservice", "run", str(workflow_for("tiny", 221, root)), "-q", "--only",
                    "simulate"], check=True)
    build_maps(root, simulator_dir(root))
    r = score(root, simulator_dir(root))
    chg, same = r["chg"], r["same"]
    assert chg["found"] >= 0.8 * (chg["truth_removed_mapped"] + chg["truth_added_mapped"]) and chg["listed_true"] \
        >= 0.8 * chg["listed"], chg
    assert chg["truth_cells"] >= 1 and chg["cells_found"] == chg["truth_cells"] == chg["cells_listed"], chg
    assert same["moved"] == 0 and same["marking_cells"] == 0 and same["added"] == 0, same
