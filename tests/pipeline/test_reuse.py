"""Drive-scoped reuse (pipeline/reuse.py) on the toy stages: adding a drive to a pinned-frame workflow links the
old drives' per-drive partitions instead of computing them; the joint stage runs on all drives."""
from __future__ import annotations

import json
from pathlib import Path

import pyarrow as pa
import yaml

from tests.pipeline.test_engine import run, toy_stages, write_toy  # noqa: F401  (fixture)

ORIGIN = {"lat_deg": 37.4979, "lon_deg": 127.0276, "h_m": 57.0}


def _workflow(tmp: Path, drives: list[str], pinned: bool = True) -> Path:
    path = write_toy(tmp)
    wf = yaml.safe_load(path.read_text())
    for d in drives:
        (tmp / d).mkdir(exist_ok=True)
        (tmp / d / "drive.yaml").write_text(f"name: {d}\n")
    wf["drives"] = [{"name": d, "path": str(tmp / d / "drive.yaml")} for d in drives]
    if pinned:
        wf["enu_origin"] = ORIGIN
    path.write_text(yaml.safe_dump(wf))
    return path


def _markers(root: Path, dataset: str, fp16: str) -> dict[str, dict]:
    return {m.stem: json.loads(m.read_text()) for m in (root / "datasets" / dataset / fp16 / "_parts").glob("*.json")}


def test_adding_a_drive_links_old_partitions_and_equals_a_fresh_build(tmp_path):
    root = tmp_path / "root"
    first = run(_workflow(tmp_path, ["d0", "d1"]))["summary"]
    assert first["numbers"]["partitions_reused"] == 0
    second = run(_workflow(tmp_path, ["d0", "d1", "d2"]))["summary"]
    assert (second["numbers"]["partitions"], second["numbers"]["partitions_reused"]) == (3, 2)
    assert (second["squares"]["partitions"], second["squares"]["partitions_reused"]) == (12, 8)
    assert second["total"]["decision"] == "ran" and second["total"]["partitions_reused"] == 0
    squares = _markers(root, "toy_squares", second["squares"]["fingerprint"])
    assert {k for k, m in squares.items() if m.get("linked_from")} == {f"d{i}-chunk{c:04d}" for i in (0, 1)
                                                                         for c in range(4)}
    notes = root / "datasets" / "toy_notes" / second["squares"]["fingerprint"] / "artifacts" / "d0-chunk0000"
    old_notes = root / "datasets" / "toy_notes" / first["squares"]["fingerprint"] / "artifacts" / "d0-chunk0000"
    assert (notes / "note.txt").stat().st_ino == (old_notes / "note.txt").stat().st_ino  # hard-linked, stored once

    fresh = tmp_path / "fresh"
    fresh.mkdir()
    for d in ("d0", "d1", "d2"):
        (fresh / d).mkdir()
        (fresh / d / "drive.yaml").write_text(f"name: {d}\n")
    fresh_total = run(_workflow(fresh, ["d0", "d1", "d2"]))["summary"]["total"]["fingerprint"]
    assert fresh_total == second["total"]["fingerprint"]  # no location in a fingerprint
    assert _only(fresh / "root", "toy_total", fresh_total).equals(_only(root, "toy_total", fresh_total))


def _only(root: Path, dataset: str, fp16: str) -> pa.Table:
    import pyarrow.parquet as pq

    d = root / "datasets" / dataset / fp16
    m = json.loads((d / "_manifest.json").read_text())
    return pa.concat_tables([pq.read_table(d / f["path"]) for f in m["files"]])


def test_no_pinned_frame_no_reuse_and_a_changed_drive_is_recomputed(tmp_path):
    run(_workflow(tmp_path, ["d0", "d1"], pinned=False))
    second = run(_workflow(tmp_path, ["d0", "d1", "d2"], pinned=False))["summary"]
    assert second["numbers"]["partitions_reused"] == 0  # the origin could come from another first drive
    run(_workflow(tmp_path, ["d0", "d1"]))
    wf = _workflow(tmp_path, ["d0", "d1", "d2"])
    (tmp_path / "d1" / "drive.yaml").write_text("name: d1\n# re-recorded\n")
    third = run(wf)["summary"]
    assert third["numbers"]["partitions_reused"] == 1  # d0 only: d1's content changed, d2 is new
