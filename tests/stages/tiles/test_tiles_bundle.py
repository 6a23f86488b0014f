"""Delta bundles (mapformat/bundle.py, `cornermap tiles bundle|apply`): only the files that differ travel, a copy
holding the base becomes the target file for file, and every way a bundle can be wrong is refused with the copy
left as it was."""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from mapformat.bundle import apply_bundle, make_bundle, read_bundle
from mapformat.schemas import problems
from mapformat.verify import verify_map
from pipeline.errors import IntegrityError, MapFormatError, PathEscapeError
from pipeline.versioned import read_latest, write_latest
from tests.stages.tiles.tiles_synth import publish_two_versions


@pytest.fixture(scope="module")
def two(tmp_path_factory):
    return publish_two_versions(tmp_path_factory.mktemp("bundle")) / "maps" / "city"


def _shas(vdir: Path) -> dict[str, str]:
    return {p.relative_to(vdir).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(vdir.rglob("*")) if p.is_file()}


def _vehicle(src_map: Path, dest: Path, version: str = "v0001") -> Path:
    """A vehicle's copy: the base version's folder and a LATEST naming it."""
    dest.mkdir(parents=True)
    shutil.copytree(src_map / version, dest / version)
    write_latest(dest, int(version[1:]))
    return dest


def test_a_bundle_carries_only_what_differs_and_applies_file_for_file(two, tmp_path):
    doc = make_bundle(two, "v0001", "v0002", tmp_path / "delta")
    assert problems(json.loads((tmp_path / "delta" / "bundle.json").read_text()), "bundle") == []
    v1, v2 = _shas(two / "v0001"), _shas(two / "v0002")
    carried = {e["path"] for e in doc["files"] if e["source"] == "bundle"}
    assert carried == {p for p, s in v2.items() if p != "manifest.json" and v1.get(p) != s}
    assert 0 < len(carried) < len(v2) - 1  # the unchanged rasters and trajectories stay home
    in_dir = {p.relative_to(tmp_path / "delta" / "files").as_posix() for p in (tmp_path / "delta" / "files").rglob("*")
              if p.is_file()}
    assert in_dir == carried | {"manifest.json"}
    assert doc["bytes"]["target"] == sum(p.stat().st_size for p in (two / "v0002").rglob("*") if p.is_file())
    assert doc["bytes"]["bundle"] < doc["bytes"]["target"]
    car = _vehicle(two, tmp_path / "car")
    res = apply_bundle(tmp_path / "delta", car)
    assert (res["base"], res["target"], res["written"]) == (1, 2, len(carried))
    assert _shas(car / "v0002") == v2 and read_latest(car) == 2 and verify_map(car / "v0002") == []
    assert sorted(p.name for p in car.iterdir()) == [".publish.lock", "LATEST", "v0001", "v0002"]
    assert apply_bundle(tmp_path / "delta", car)["already"] is True  # applying twice is a no-op


def _other_v1(src_map: Path, dest: Path) -> Path:
    """A copy whose LATEST names a v0001 that is not the map's (its manifest edited, LATEST vouching for it)."""
    car = _vehicle(src_map, dest)
    m = car / "v0001" / "manifest.json"
    m.write_bytes(m.read_bytes() + b"\n")
    write_latest(car, 1)
    return car


def _refused(bundle: Path, car: Path, error, match: str) -> None:
    def names() -> list[str]:
        return sorted(p.name for p in car.iterdir() if p.name != ".publish.lock")

    before = names()
    with pytest.raises(error, match=match):
        apply_bundle(bundle, car)
    assert names() == before and read_latest(car) == 1  # nothing half-applied


def test_refusals_leave_the_copy_untouched(two, tmp_path):
    make_bundle(two, "v0001", "v0002", tmp_path / "delta")
    car = _vehicle(two, tmp_path / "car")
    # the copy holds another v0001 than the bundle's base (another map's, or an edited one): its digest decides
    _refused(tmp_path / "delta", _other_v1(two, tmp_path / "x1"), MapFormatError,
             r"holds v0001 \(manifest .*\); the bundle applies to v0001 \(manifest .*\) only; refusing it")
    # a tampered file of the bundle
    t1 = tmp_path / "t1"
    shutil.copytree(tmp_path / "delta", t1)
    victim = next(p for p in (t1 / "files").rglob("*.parquet"))
    victim.write_bytes(victim.read_bytes()[:-1] + b"\0")
    _refused(t1, car, IntegrityError, "sha256 .* differs from the target's")
    # a tampered base file of the copy
    t2_car = _vehicle(two, tmp_path / "car2")
    base_file = next(e["path"] for e in read_bundle(tmp_path / "delta")["files"] if e["source"] == "base")
    (t2_car / "v0001" / base_file).write_bytes(b"not the base's bytes")
    _refused(tmp_path / "delta", t2_car, IntegrityError, "differs from the target's")
    # bundle.json edited to drop a file, or to name a path leaving the folder
    t3 = tmp_path / "t3"
    shutil.copytree(tmp_path / "delta", t3)
    doc = json.loads((t3 / "bundle.json").read_text())
    doc["files"] = doc["files"][1:]
    (t3 / "bundle.json").write_text(json.dumps(doc))
    _refused(t3, car, IntegrityError, "disagrees with the target's manifest")
    doc["files"].append({"path": "../../escape.txt", "sha256": "0" * 64, "bytes": 1, "source": "bundle"})
    (t3 / "bundle.json").write_text(json.dumps(doc))
    _refused(t3, car, MapFormatError, "does not conform to the bundle schema")
    # the target manifest replaced
    t4 = tmp_path / "t4"
    shutil.copytree(tmp_path / "delta", t4)
    (t4 / "files" / "manifest.json").write_text("{}")
    _refused(t4, car, IntegrityError, "sha256 differs from the bundle's target digest")
    # a bundle file that is a link out of the bundle
    t5 = tmp_path / "t5"
    shutil.copytree(tmp_path / "delta", t5)
    victim = next(p for p in (t5 / "files").rglob("*.parquet"))
    victim.unlink()
    os.symlink("/etc/hostname", victim)
    _refused(t5, car, PathEscapeError, "resolves to /etc/hostname, outside")


def test_a_path_escaping_the_folder_is_refused_before_anything_is_written(two, tmp_path, monkeypatch):
    import mapformat.bundle as mb

    make_bundle(two, "v0001", "v0002", tmp_path / "delta")
    car = _vehicle(two, tmp_path / "car")
    doc = read_bundle(tmp_path / "delta")
    doc["files"][0]["path"] = "tiles/../../../outside.parquet"
    monkeypatch.setattr(mb, "read_bundle", lambda d: doc)  # past the schema: the path check itself refuses
    monkeypatch.setattr(mb, "_check_target", lambda d, b: (b"{}", {}))
    _refused(tmp_path / "delta", car, PathEscapeError, "outside")


def test_a_failure_mid_apply_leaves_no_staging_and_latest_on_the_base(two, tmp_path, monkeypatch):
    import mapformat.bundle as mb

    make_bundle(two, "v0001", "v0002", tmp_path / "delta")
    car = _vehicle(two, tmp_path / "car")
    calls = {"n": 0}
    real = mb._sha256_copy

    def flaky(src, dst):
        calls["n"] += 1
        if calls["n"] == 5:
            raise OSError(28, "No space left on device")
        return real(src, dst)

    monkeypatch.setattr(mb, "_sha256_copy", flaky)
    _refused(tmp_path / "delta", car, OSError, "No space left")
    assert not any(p.name.startswith(".staging") for p in car.iterdir())


def test_the_cli_bundles_applies_and_refuses_in_one_line(two, tmp_path):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    cli = [sys.executable, "-m", "mapservice", "tiles"]
    root = two.parent.parent
    res = subprocess.run(cli + ["bundle", "--root", str(root), "--map", "city", "--from", "v0001", "--to", "LATEST",
                                "--out", str(tmp_path / "d")], capture_output=True, text=True, env=env)
    assert res.returncode == 0 and "v0001 -> v0002" in res.stdout, res.stderr
    _vehicle(two, tmp_path / "car" / "maps" / "city")  # the vehicle's root holds maps/city like any root
    res = subprocess.run(cli + ["apply", str(tmp_path / "d"), "--root", str(tmp_path / "car"), "--map", "city"],
                         capture_output=True, text=True, env=env)
    assert res.returncode == 0 and "LATEST = v0002" in res.stdout, res.stderr
    again = subprocess.run(cli + ["bundle", "--root", str(root), "--map", "city", "--from", "v0001", "--to", "v0002",
                                  "--out", str(tmp_path / "d")], capture_output=True, text=True, env=env)
    _other_v1(two, tmp_path / "c3" / "maps" / "city")
    wrong = subprocess.run(cli + ["apply", str(tmp_path / "d"), "--root", str(tmp_path / "c3"), "--map", "city"],
                           capture_output=True, text=True, env=env)
    # a vehicle's copy kept outside any root is named by its folder (the issue's `--map MAP_FOLDER`)
    loose = _vehicle(two, tmp_path / "loose")
    res = subprocess.run(cli + ["apply", str(tmp_path / "d"), "--map", str(loose)], capture_output=True, text=True,
                         env=env)
    assert res.returncode == 0 and "LATEST = v0002" in res.stdout and read_latest(loose) == 2, res.stderr
    bad = subprocess.run(cli + ["apply", str(tmp_path / "d"), "--map", str(tmp_path)], capture_output=True,
                         text=True, env=env)
    assert bad.returncode == 2 and "holds no LATEST" in bad.stderr, bad.stderr
    for r, want in ((again, "not an empty folder"), (wrong, "refusing it")):
        assert r.returncode == 1 and want in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
