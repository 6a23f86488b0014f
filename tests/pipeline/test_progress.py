"""The progress facility (pipeline/progress.py): what a log file gets when stderr is not a terminal, the time left
at the pace so far, displays joining the command's, library reports without a display, and a child command's
progress shown as a step of its parent's row."""
from __future__ import annotations

import io
import re

import pytest

from pipeline import progress as pg
from pipeline.progress import StageProgress, eta_s, hms

STAMP = r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d "


def lines(stream: io.StringIO) -> list[str]:
    out = stream.getvalue().splitlines()
    assert all(re.match(STAMP, ln) for ln in out), out  # every line is timestamped
    return [ln[20:] for ln in out]


def test_eta_is_elapsed_times_remaining_over_done():
    assert eta_s(30.0, 1, 4) == pytest.approx(90.0)  # a quarter in 30 s: three quarters left, 90 s
    assert eta_s(30.0, 1, 4, since_s=10.0) == pytest.approx(80.0)  # ... and 10 s gone by since: 80 s
    assert eta_s(30.0, 1, 4, since_s=200.0) == 0.0
    assert eta_s(30.0, 0, 4) is None and eta_s(30.0, 4, 4) is None and eta_s(30.0, 2, None) is None
    assert hms(3725.4) == "1:02:05" and hms(-1) == "0:00:00"
    assert pg.count(950) == "950" and pg.count(12_345) == "12k" and pg.count(4_500_000) == "4.5M"


def test_plain_lines_start_steps_throttled_counts_and_end(monkeypatch):
    clock = [100.0]
    monkeypatch.setattr(pg.time, "monotonic", lambda: clock[0])
    out = io.StringIO()
    with StageProgress(stream=out, mode="plain", every_s=30.0) as p:
        p.update("odometry", 0, 4)
        clock[0] += 10
        p.update("odometry", 1, 4)  # 10 s after the start line: not yet a line of its own
        clock[0] += 25
        p.update("odometry", 2, 4)  # 35 s: a line, with the time left at that pace (35 s for 2 -> 35 s)
        p.step("posegraph", "loops verified", 3, 12)
        clock[0] += 3
        p.step("posegraph", "loops verified", 6, 12)  # the same step: throttled
        p.step("posegraph", "survey anchors")  # a new step: a line at once
        clock[0] += 5
        p.update("odometry", 4, 4)
        p.finish("odometry")
        p.finish("odometry")  # once
        p.event("dask dashboard: http://127.0.0.1:8787/status")
    assert lines(out) == [
        "odometry: started, 0/4",
        "odometry: 2/4, 0:00:35 elapsed, ~0:00:35 left",
        "posegraph: started, loops verified 3/12",
        "posegraph: survey anchors, 0:00:03 elapsed",
        "odometry: done 4/4 in 0:00:43",
        "dask dashboard: http://127.0.0.1:8787/status",
    ]


def test_an_inner_display_joins_the_commands_and_library_reports_need_one(monkeypatch):
    out = io.StringIO()
    pg.report("inbox", 0, 3)  # no display open: nothing happens, nothing fails
    pg.finish("inbox")
    with StageProgress(stream=out, mode="plain") as outer:
        with StageProgress(enabled=False) as inner:  # e.g. a rebuild's build, run "quiet"
            assert inner.enabled and pg.active() is inner
            inner.update("ingest", 0, 1)
            pg.report("gate", step="drive_1 on v0002")
        assert pg.active() is outer
    assert pg.active() is None
    assert lines(out) == ["ingest: started, 0/1", "gate: started, drive_1 on v0002"]


def test_off_writes_nothing(monkeypatch):
    out = io.StringIO()
    monkeypatch.setenv("CORNERMAP_PROGRESS", "off")
    with StageProgress(stream=out) as p:
        p.update("x", 1, 2)
        p.event("y")
    assert out.getvalue() == "" and not p.enabled


def test_a_child_commands_progress_is_a_step_of_the_parents_row(tmp_path):
    """``run_child`` (here through ``mapservice.child.run_cornermap``, ``python -m mapservice``) relays the plain lines
    of the child's stderr to the row; its other lines are its stderr."""
    from mapservice.child import run_cornermap

    out = io.StringIO()
    args = ["simulate", "--preset", "tiny", "--seed", "1", "--drives", "1", "--max-scans", "20", "--out"]
    with StageProgress(stream=out, mode="plain", every_s=0.0):
        res = run_cornermap(args + [str(tmp_path / "a")], label="sim", step="drive_0")
        failed = run_cornermap(["tiles", "ls", "--root", str(tmp_path / "nothing")], label="ls")
    assert res.returncode == 0 and res.stdout.startswith("drive_0: 20 scans") and res.stderr == "", res.stderr
    got = lines(out)
    assert got[0] == "sim: started, drive_0: drive_0 scans: started, 10/20", got
    assert any(ln.startswith("sim: drive_0: drive_0 scans: done 20/20 in ") for ln in got), got
    assert failed.returncode == 1 and failed.stderr.startswith("error: ") and len(failed.stderr.splitlines()) == 1
    quiet = run_cornermap(args + [str(tmp_path / "b")], label="sim")  # no display: the child shows none
    assert quiet.returncode == 0 and quiet.stderr == ""
