"""``stages.evaluate.map_access.open_published_map`` reads the version its ``map`` input names through the run's store:
a root-relative path on a local root is a path under it, on an ``s3://`` root the version's URI (which the loader
reads from the bucket); an absolute path is taken as it is."""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pyarrow as pa
import pytest

import mapformat.loader
from stages.evaluate.map_access import open_published_map


class _Inputs:
    def __init__(self, path: str):
        self.path = path

    def read(self, arg: str) -> pa.Table:
        assert arg == "map"
        return pa.table({"map_name": ["city"], "version": [2], "path": [self.path]})


@pytest.mark.parametrize("root, path, expected", [
    ("s3://bucket/root", "maps/city/v0002", "s3://bucket/root/maps/city/v0002"),
    ("/data/root", "maps/city/v0002", Path("/data/root/maps/city/v0002")),
    ("s3://bucket/root", "/elsewhere/maps/city/v0002", "/elsewhere/maps/city/v0002"),
])
def test_the_version_is_resolved_on_the_runs_store(monkeypatch, root, path, expected):
    opened = []
    monkeypatch.setattr(mapformat.loader, "open_map", lambda p, *a, **k: opened.append(p) or "reader")
    ctx = SimpleNamespace(inputs=_Inputs(path), settings={"root": root})
    assert open_published_map(ctx) == "reader"
    assert opened == [expected]
