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
