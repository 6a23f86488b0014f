"""Issue 22 findings 1, 2 and 5 (loader window, export height): what a localizer loads is what was published.

Each test tampers with a published map the way the issue's attacker did and asserts a named error (or a
verify problem) where the old code served the tampered data."""
from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest

from mapformat.diff import diff_maps
from mapformat.export import export_map
from mapformat.loader import open_map
from mapformat.verify import verify_map
from pipeline.errors import IntegrityError, LimitError, PathEscapeError, PublishConflictError
from pipeline.versioned import LATEST_NAME, read_latest_entry, read_manifest, trusted_manifest_digests
from tests.stages.tiles.tiles_synth import publish_two_versions


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    return publish_two_versions(tmp_path_factory.mktemp("integrity"))


@pytest.fixture
def map_dir(pristine, tmp_path) -> Path:
    shutil.copytree(pristine / "maps", tmp_path / "maps")
    return tmp_path / "maps" / "city"


def _edit_manifest(vdir: Path, edit) -> None:
    m = json.loads((vdir / "manifest.json").read_text())
    edit(m)
    (vdir / "manifest.json").write_text(json.dumps(m))


def _a_corners_file(vdir: Path) -> Path:
    m, _ = read_manifest(vdir)
    tile = next(t for t in m["tiles"] if t["n_corners"])
    return vdir / tile["dir"] / "corners.parquet"


def test_latest_records_the_manifest_digest_and_manifests_chain(map_dir):
    version, sha = read_latest_entry(map_dir)
    m2, sha2 = read_manifest(map_dir / "v0002")
    _, sha1 = read_manifest(map_dir / "v0001")
    assert (version, sha) == (2, sha2) and m2["parent_manifest_sha256"] == sha1
    assert trusted_manifest_digests(map_dir) == {2: sha2, 1: sha1}
    assert verify_map(map_dir / "v0002", sha2) == [] and verify_map(map_dir / "v0001", sha1) == []


def test_finding1_every_bit_flip_in_a_tile_file_is_refused(map_dir):
    """One flipped bit anywhere in corners.parquet: the loader, export and diff raise IntegrityError."""
    path = _a_corners_file(map_dir / "v0002")
    clean = path.read_bytes()
    rng = np.random.default_rng(0)
    for bit in rng.choice(len(clean) * 8, size=40, replace=False):
        raw = bytearray(clean)
        raw[bit // 8] ^= 1 << (bit % 8)
        path.write_bytes(bytes(raw))
        with pytest.raises(IntegrityError, match="sha256"):
            open_map(map_dir).all_corners()
    path.write_bytes(clean)
    assert open_map(map_dir).all_corners().num_rows > 0
    raw = bytearray(clean)
    raw[len(raw) // 2] ^= 0x10
    path.write_bytes(bytes(raw))
    with pytest.raises(IntegrityError):
        export_map(open_map(map_dir), "geojson", map_dir.parent.parent / "out.geojson")
    with pytest.raises(IntegrityError):
        diff_maps(open_map(map_dir, "v0001"), open_map(map_dir, "v0002"))
    assert open_map(map_dir, trust_files=True).path.name == "v0002"  # the opt-out for trusted local use


def test_finding2_an_edited_manifest_fails_verify_and_the_loader(map_dir):
    _edit_manifest(
        map_dir / "v0002", lambda m: m["enu_origin"].__setitem__("lat_deg", m["enu_origin"]["lat_deg"] + 0.01)
    )
    digests = trusted_manifest_digests(map_dir)
    problems = verify_map(map_dir / "v0002", digests.get(2))
    assert any("digest recorded outside" in p for p in problems), problems
    with pytest.raises(IntegrityError, match="digest recorded outside"):
        open_map(map_dir)
    _edit_manifest(map_dir / "v0001", lambda m: m.__setitem__("n_corners", 1))  # an older link of the chain
    latest = read_latest_entry(map_dir)
    (map_dir / LATEST_NAME).write_text(f"v0002 {read_manifest(map_dir / 'v0002')[1]}\n")  # attacker fixes LATEST
    assert any("digest recorded outside" in p for p in verify_map(map_dir / "v0001",
                                                                    trusted_manifest_digests(map_dir).get(1)))
    assert latest is not None


@pytest.mark.parametrize("where", ["tile_dir", "mask_file"])
def test_finding2_manifest_paths_outside_the_version_are_refused(map_dir, where):
    vdir = map_dir / "v0002"
    outside = map_dir.parent.parent / "elsewhere"
    shutil.copytree(vdir / "tiles", outside)

    def edit(m):
        tile = next(t for t in m["tiles"] if t.get("marking"))
        if where == "tile_dir":
            tile["dir"] = "../../../elsewhere/" + tile["dir"].split("/", 1)[1]
        else:
            tile["marking"]["mask_file"] = "../../../../elsewhere/" + tile["dir"].split("/", 1)[1] + "/marking.png"

    _edit_manifest(vdir, edit)
    (map_dir / LATEST_NAME).write_text(f"v0002 {read_manifest(vdir)[1]}\n")  # LATEST vouches: only paths are wrong
    problems = verify_map(vdir, trusted_manifest_digests(map_dir)[2])
    assert any("outside" in p for p in problems), problems
    with pytest.raises((PathEscapeError, IntegrityError)):
        reader = open_map(map_dir)
        reader.all_corners()
        reader.marking_window(0, 0, 100, 300)


def test_finding2_file_entries_outside_the_version_are_not_hashed(map_dir, monkeypatch):
    vdir = map_dir / "v0002"
    _edit_manifest(vdir, lambda m: m["files"].update({"/etc/hostname": {"sha256": "0" * 64, "bytes": 1},
                                                      "../../etc/passwd": {"sha256": "0" * 64, "bytes": 1}}))
    hashed = []
    import pipeline.versioned as versioned

    real = versioned.file_sha256
    monkeypatch.setattr(versioned, "file_sha256", lambda p: hashed.append(str(p)) or real(p))
    problems = verify_map(vdir)
    assert sum("leaves the version directory" in p for p in problems) == 2, problems
    assert not any("etc" in h for h in hashed)


def test_old_latest_without_digest_is_read_with_a_warning(map_dir, caplog):
    (map_dir / LATEST_NAME).write_text("v0002\n")
    with caplog.at_level(logging.WARNING):
        assert read_latest_entry(map_dir) == (2, None)
        reader = open_map(map_dir)
    assert reader.version == 2 and "without its manifest digest" in caplog.text


def test_finding5_marking_window_is_bounded(map_dir, tmp_path):
    """(The autoware export no longer builds corner columns, whose --column-height-m 1e9 tried 104 GiB: it is
    the map drives' point cloud, voxel-downsampled; see mapformat/autoware.py.)"""
    reader = open_map(map_dir)
    with pytest.raises(LimitError, match="cells"):
        reader.marking_window(0.0, 0.0, 200_000.0, 200_000.0)
    with pytest.raises(LimitError, match="finite"):
        reader.marking_window(0.0, 0.0, float("inf"), 10.0)
    assert reader.marking_window(0.0, 0.0, 100.0, 100.0)[0].shape == (200, 200)


def test_finding8_export_never_writes_into_a_published_map(map_dir, tmp_path):
    reader = open_map(map_dir)
    for target in (map_dir / LATEST_NAME, map_dir / "v0002" / "manifest.json", map_dir / "v0002"):
        with pytest.raises(PublishConflictError):
            export_map(reader, "geojson" if target.name != "v0002" else "autoware", target)
    assert verify_map(map_dir / "v0002", trusted_manifest_digests(map_dir)[2]) == []
    bad = tmp_path / "a_file"
    bad.write_text("x")
    with pytest.raises(OSError):
        export_map(reader, "geojson", bad / "out.geojson")
    with pytest.raises(OSError, match="directory"):
        export_map(reader, "geojson", tmp_path)
    assert [p.name for p in tmp_path.iterdir() if ".tmp-" in p.name] == []
