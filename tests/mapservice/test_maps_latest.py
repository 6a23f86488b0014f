"""What a build says when its drive set's version is not LATEST (fast: no build)."""
from __future__ import annotations

from pipeline.versioned import rollback_latest as rollback
from tests.mapservice.test_maps import _publish


def test_a_drive_set_published_earlier_is_named_when_latest_is_another(tmp_path):
    """Re-running an already-built drive set skips publishing; the build then says its version is not LATEST
    (the issue: 'published map version v0002' printed while LATEST stayed at v0004)."""
    from types import SimpleNamespace

    import pyarrow as pa
    import pyarrow.parquet as pq

    from mapservice.maps import stale_latest_note
    from pipeline.store import atomic_write_json, dataset_dir

    mdir = tmp_path / "maps" / "city"
    for payload in (b"a", b"b", b"c"):
        _publish(mdir, payload)
    fp = "f" * 64
    ddir = dataset_dir(tmp_path, "map_tiles", fp)
    ddir.mkdir(parents=True)
    pq.write_table(pa.table({"map_name": ["city"], "version": pa.array([2], pa.int32())}), ddir / "part.parquet")
    atomic_write_json(ddir / "_manifest.json", {"files": [{"path": "part.parquet"}]})
    plan = SimpleNamespace(root=tmp_path, stages={"tiles": SimpleNamespace(outputs={"published": "map_tiles"},
                                                                           fingerprint=fp)})
    note = stale_latest_note(plan, "city")
    assert note is not None and "v0002" in note and "LATEST is v0003" in note and "rollback --to v0002" in note
    rollback(mdir, "v0002")
    assert stale_latest_note(plan, "city") is None
