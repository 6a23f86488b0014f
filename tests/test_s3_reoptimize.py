"""``cornermap maps reoptimize`` with its root in a bucket, against a real S3 API (moto's server, started by the test
session: ``tests/conftest.py::s3_env``), run as processes: the re-optimization publishes through the rebuild's own
gate-and-publish flow (``mapservice.rebuild.gate_and_publish``) on an object store.

- ``test_reoptimize_on_a_bucket`` (slow): two nights of ``rebuild`` (v0001 drive_0, v0002 drive_1 added
  incrementally), then ``maps reoptimize --region-max-poses 30`` with the gate on -> v0003: LATEST in the bucket names
  it, the gate's record is the bucket's (previous 2, candidate 3), every version verifies from the bucket, the old
  drive's published trajectory changed (it was re-solved; the incremental night had kept it byte for byte), the
  identity's drive set is unchanged; a second run has nothing new to publish (exit 0, LATEST stays v0003); no local
  folder named after the root.
- ``test_a_lease_held_on_the_bucket_stops_reoptimize_with_75``: another holder of the map's lease -> exit 75, one line,
  nothing written to the bucket.
"""

from __future__ import annotations

import json

import pytest

from tests.test_cli_process import cornermap
from tests.test_s3_rebuild import ORIGIN, deliver, keys, rebuild_args, sim  # noqa: F401 - sim: the module fixture


@pytest.mark.slow
def test_reoptimize_on_a_bucket(s3_env, s3_root, sim, tmp_path):  # noqa: F811 - the imported fixture
    from pipeline.storage import Store

    bucket = s3_root.rsplit("/", 1)[0]
    inbox = f"{bucket}/inbox"
    env = {**s3_env, "CORNERMAP_SCRATCH": str(tmp_path / "scratch")}
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    assert (
        cornermap("maps", "create", "--root", s3_root, "--map", "city", "--origin", ORIGIN, cwd=cwd, **env).returncode
        == 0
    )
    deliver(inbox, sim / "survey", "survey", ready=False)
    for k in (0, 1):
        deliver(inbox, sim / f"drive_{k}", f"drive_{k}")
        night = cornermap(*rebuild_args(s3_root, inbox, sim, "--no-gate"), cwd=cwd, timeout=900, **env)
        assert night.returncode == 0 and f"v000{k + 1}" in night.stdout, night.stdout + night.stderr
    root = Store.open(s3_root)
    ident_before = json.loads(root.read_bytes(root.root / "maps/city/map.json"))

    args = (
        "maps",
        "reoptimize",
        "--root",
        s3_root,
        "--map",
        "city",
        "--region-max-poses",
        "30",
        "--min-free-gib",
        "0.1",
        "--params",
        str(sim / "no_gates.yaml"),
    )
    res = cornermap(*args, cwd=cwd, timeout=900, **env)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "published map 'city' v0003 (LATEST): 2 drive(s) re-optimized region by region" in res.stdout, res.stdout
    assert "gate: ekf.rms_2d_m" in res.stdout  # the regression gate ran, on a local snapshot of both versions
    assert root.read_bytes(root.root / "maps/city/LATEST").decode().startswith("v0003 ")
    gate = json.loads(root.read_bytes(root.root / "maps/city/gate/v0003.json"))
    assert gate["ok"] and gate["previous"] == 2 and gate["candidate"] == 3
    assert json.loads(root.read_bytes(root.root / "maps/city/map.json")) == ident_before  # no drive added
    t1, t2, t3 = (root.read_bytes(root.root / f"maps/city/v000{k}/trajectories/drive_0.tum") for k in (1, 2, 3))
    assert t1 == t2 and t3 != t2  # held by the incremental night, re-solved by the re-optimization
    manifest = json.loads(root.read_bytes(root.root / "maps/city/v0003/manifest.json"))
    assert sorted(d["drive"] for d in manifest["source_drives"]) == ["drive_0", "drive_1"]
    ver = cornermap("tiles", "verify", "--root", s3_root, "--map", "city", "--all", "--json", cwd=cwd, **env)
    assert ver.returncode == 0 and [r["ok"] for r in json.loads(ver.stdout)["versions"]] == [True] * 3, ver.stdout

    again = cornermap(*args, "--json", cwd=cwd, timeout=900, **env)
    assert again.returncode == 0, again.stdout + again.stderr
    doc = json.loads(again.stdout)
    assert doc["status"] == "published" and doc["version"] == "v0003", doc["lines"]
    assert any("already this re-optimization" in line for line in doc["lines"]), doc["lines"]
    assert root.read_bytes(root.root / "maps/city/LATEST").decode().startswith("v0003 ")
    assert not (cwd / "s3:").exists() and not list(cwd.glob("**/s3:*")), "a local folder named after the root"


def test_a_lease_held_on_the_bucket_stops_reoptimize_with_75(s3_env, s3_root, tmp_path):
    from mapservice.maps import create_map
    from pipeline.leases import LeaseLocks
    from pipeline.locks import map_key
    from pipeline.storage import Store

    bucket = s3_root.rsplit("/", 1)[0]
    create_map(s3_root, "city", {"lat_deg": 37.4979, "lon_deg": 127.0276, "h_m": 57.0})
    before = sorted(keys(bucket))
    store = Store.open(s3_root)
    with LeaseLocks(store, holder="another-rebuild").hold(map_key("city"), exclusive=True, what="another rebuild"):
        res = cornermap(
            "maps",
            "reoptimize",
            "--root",
            s3_root,
            "--map",
            "city",
            "--min-free-gib",
            "0",
            cwd=tmp_path,
            **s3_env,
            CORNERMAP_SCRATCH=str(tmp_path / "scratch"),
        )
        assert res.returncode == 75, res.stdout + res.stderr
        assert res.stdout == "" and len(res.stderr.strip().splitlines()) == 1 and "another rebuild" in res.stderr
    lock_free = [k for k in keys(bucket) if "/locks/" not in f"/{k}"]
    assert lock_free == [k for k in before if "/locks/" not in f"/{k}"], "the refused reoptimize wrote to the bucket"
