"""An operator's (and an attacker's) deliveries to a maintained map's inbox, run as processes (the installed
``cornermap``) on short simulated drives (tiny preset, 30 scans): the same drive delivered twice, a re-delivered copy
with new modification times, a map drive that gains an unrelated file, links inside and outside the inbox, a link to
a folder named like a map drive, a drive still being copied, a half-copied drive, quarantine reasons that must not
quote foreign files, a drive 70 km away, GNSS in radians declared as degrees; then bounded reading of the published
version (a PNG bomb, the manifest's byte counts: tests/stages/tiles/test_tiles_bounded_reads.py has the rest).
One build (about a minute on 2 cores).
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
import yaml

from fixtures.cli import one_error_line
from mapservice.maps import create_map, read_identity
from pipeline.versioned import list_versions, read_latest, write_latest

REPO = Path(__file__).resolve().parents[1]
CM = Path(sys.executable).with_name("cornermap")
ORIGIN = {"lat_deg": 37.4979, "lon_deg": 127.0276, "h_m": 57.0}
pytestmark = pytest.mark.skipif(not CM.is_file(), reason=f"no installed console script at {CM}")
SECRET = "TOPSECRET-do-not-copy"


def cornermap(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(CM), *args], capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(REPO)})


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "sim"
    res = cornermap("simulate", "--preset", "tiny", "--seed", "41", "--drives", "2", "--max-scans", "30",
                    "--out", str(out))
    assert res.returncode == 0, res.stderr
    return out


@pytest.fixture(scope="module")
def workflow(tmp_path_factory) -> Path:
    """The standard map workflow without the tiles quality gates (30 scans make too short a map for them)."""
    doc = yaml.safe_load((REPO / "workflows" / "map_rebuild.yaml").read_text())
    doc["params"] = {"tiles": {"gates_enabled": False}}
    path = tmp_path_factory.mktemp("wf") / "map_30_scans.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def rebuild(root: Path, inbox: Path, workflow: Path, *more: str) -> subprocess.CompletedProcess:
    return cornermap("rebuild", "--root", str(root), "--map", "city", "--inbox", str(inbox), "--min-free-gib", "0.1",
                     "--no-gate", "--workflow", str(workflow), *more)


def copy_drive(src: Path, dst: Path, new_mtimes: bool = False, rename: bool = False) -> Path:
    shutil.copytree(src, dst, copy_function=shutil.copy if new_mtimes else shutil.copy2)
    if rename:  # the drive file names the drive like its folder
        text = (dst / "drive.yaml").read_text()
        (dst / "drive.yaml").write_text(text.replace(f"name: {src.name}", f"name: {dst.name}"))
    return dst


@pytest.fixture(scope="module")
def city(sim, workflow, tmp_path_factory) -> tuple[Path, Path, subprocess.CompletedProcess]:
    """A map built by one rebuild from an inbox holding drive_0 twice (two folder names), a link to drive_0 inside
    the inbox and a link to a drive folder outside it."""
    base = tmp_path_factory.mktemp("city")
    root, inbox, elsewhere = base / "root", base / "inbox", base / "elsewhere"
    inbox.mkdir()
    shutil.copytree(sim / "survey", inbox / "survey")
    copy_drive(sim / "drive_0", inbox / "drive_0")
    copy_drive(sim / "drive_0", inbox / "drive_0_copy")
    (inbox / "alias").symlink_to(inbox / "drive_0")
    copy_drive(sim / "drive_1", elsewhere / "drive_1")
    (inbox / "drive_1").symlink_to(elsewhere / "drive_1")
    create_map(root, "city", ORIGIN)
    return root, inbox, rebuild(root, inbox, workflow, "--quiet-period-min", "0")


def test_the_same_drive_twice_is_taken_once_and_a_link_out_of_the_inbox_is_refused(city):
    root, inbox, res = city
    assert res.returncode == 0, res.stderr
    mdir = root / "maps" / "city"
    assert [d.name for d in read_identity(mdir).drives] == ["drive_0"] and read_latest(mdir) == 1
    manifest = json.loads((mdir / "v0001" / "manifest.json").read_text())
    assert [d["drive"] for d in manifest["source_drives"]] == ["drive_0"]  # one trajectory, not two
    assert f"duplicate of {inbox / 'drive_0'} (the same content): {inbox / 'drive_0_copy'} left alone" in res.stdout
    assert (inbox / "drive_0_copy" / "drive.yaml").is_file()  # left where it was delivered
    q = inbox / "quarantine"
    assert (q / "drive_1").is_symlink() and (inbox.parent / "elsewhere" / "drive_1" / "drive.yaml").is_file()
    assert "outside the inbox" in (q / "drive_1.reason.txt").read_text()
    assert not (q / "alias").exists() and (inbox / "alias").is_symlink()  # the link to drive_0 added nothing


def test_redeliveries_and_a_map_drive_gaining_a_file_leave_the_map_alone(city, sim, workflow):
    root, inbox, _ = city
    copy_drive(sim / "drive_0", inbox / "drive_0_redelivered", new_mtimes=True)
    (inbox / "drive_0" / "scans" / "README.txt").write_text("delivered by the survey team\n")
    (inbox / "drive_0" / "notes.txt").write_text("an unrelated file\n")
    mdir = root / "maps" / "city"
    before = (list_versions(mdir), (mdir / "LATEST").read_bytes())
    for _ in range(2):  # and again: no rebuild fails because of them
        res = rebuild(root, inbox, workflow, "--quiet-period-min", "0")
        assert res.returncode == 0, res.stderr
        assert f"already in the map as drive_0: {inbox / 'drive_0_redelivered'} (the same content) left alone" \
            in res.stdout, res.stdout
        assert f"already in the map as drive_0: {inbox / 'drive_0_copy'}" in res.stdout
        assert res.stdout.splitlines()[-1].startswith("nothing to do")
    assert "quarantined" not in res.stdout and (inbox / "drive_0_redelivered").is_dir()
    assert (list_versions(mdir), (mdir / "LATEST").read_bytes()) == before
    assert [d.name for d in read_identity(mdir).drives] == ["drive_0"]


def test_a_link_to_a_folder_named_like_a_map_drive_is_quarantined_once(city, sim, workflow):
    root, inbox, _ = city
    copy_drive(sim / "drive_1", inbox / "deliveries" / "drive_0")  # another drive, in a folder named drive_0
    (inbox / "newcomer").symlink_to(inbox / "deliveries" / "drive_0")
    res = rebuild(root, inbox, workflow, "--quiet-period-min", "0")
    assert res.returncode == 0 and "quarantined newcomer" in res.stdout, res.stdout + res.stderr
    assert "drive name 'drive_0' is taken" in (inbox / "quarantine" / "newcomer.reason.txt").read_text()
    assert (inbox / "deliveries" / "drive_0" / "drive.yaml").is_file()  # the link moved, not its target
    again = rebuild(root, inbox, workflow, "--quiet-period-min", "0")
    assert again.returncode == 0 and again.stdout.splitlines()[-1].startswith("nothing to do"), again.stdout


def test_a_drive_still_being_copied_waits_and_is_never_quarantined(city, sim, workflow):
    root, inbox, _ = city
    copy_drive(sim / "drive_1", inbox / "drive_1_arriving")
    (inbox / "drive_1_arriving" / "wheel_gyro.csv").write_text("gps_week,gps_seconds\n")  # half written right now
    res = rebuild(root, inbox, workflow)  # the default quiet period (10 min)
    assert res.returncode == 0, res.stderr
    assert f"waiting: {inbox / 'drive_1_arriving'} changed" in res.stdout and "quarantined" not in res.stdout
    assert (inbox / "drive_1_arriving" / "drive.yaml").is_file()
    shutil.rmtree(inbox / "drive_1_arriving")


def _gnss_rows(path: Path) -> tuple[str, list[list[str]]]:
    lines = path.read_text().splitlines()
    return lines[0], [line.split(",") for line in lines[1:] if line]


def _write_gnss(path: Path, header: str, rows: list[list[str]]) -> None:
    path.write_text(header + "\n" + "\n".join(",".join(r) for r in rows) + "\n")


def test_quarantine_reasons_never_quote_a_drives_files(city, sim, workflow, tmp_path):
    root, inbox, _ = city
    secret = tmp_path / "root_only.txt"
    secret.write_text(f"{SECRET}\n")
    secret.chmod(0o600)
    linked = copy_drive(sim / "drive_1", inbox / "drive_linked")
    (linked / "gnss_inspva.csv").unlink()
    (linked / "gnss_inspva.csv").symlink_to(secret)
    headed = copy_drive(sim / "drive_1", inbox / "drive_headed")
    _, rows = _gnss_rows(headed / "gnss_inspva.csv")
    _write_gnss(headed / "gnss_inspva.csv", f"{SECRET},b,c,d,e,f,g,h,i,j,k,l,m", rows)
    assert SECRET in cornermap("drive", "check", str(headed / "drive.yaml")).stderr  # the check quotes it...
    res = rebuild(root, inbox, workflow, "--quiet-period-min", "0")
    assert res.returncode == 0, res.stderr
    q = inbox / "quarantine"
    reasons = {n: (q / f"{n}.reason.txt").read_text() for n in ("drive_linked", "drive_headed")}
    assert "outside the inbox" in reasons["drive_linked"] and "gnss_inspva.csv" in reasons["drive_linked"]
    assert "`cornermap drive check` refused it" in reasons["drive_headed"] and "gnss" in reasons["drive_headed"]
    for text in list(reasons.values()) + [res.stdout, res.stderr]:  # ...the reasons and the log do not
        assert SECRET not in text


def test_a_half_copied_drive_fails_drive_check_and_is_quarantined(city, sim, workflow):
    root, inbox, _ = city
    half = copy_drive(sim / "drive_1", inbox / "drive_half")
    for scan in sorted((half / "scans").glob("*.pcd"))[10:]:
        scan.unlink()
    res = cornermap("drive", "check", str(half / "drive.yaml"))
    assert res.returncode == 1 and "incomplete: 20 of the 30 scans listed in stamps.csv have no file" in res.stderr
    assert cornermap("drive", "check", str(sim / "drive_1" / "drive.yaml")).returncode == 0  # the whole drive passes
    out = rebuild(root, inbox, workflow, "--quiet-period-min", "0")
    assert out.returncode == 0 and "quarantined drive_half" in out.stdout, out.stdout + out.stderr
    assert "about scans" in (inbox / "quarantine" / "drive_half.reason.txt").read_text()
    assert read_identity(root / "maps" / "city").drives[-1].name == "drive_0"


def test_a_drive_nothing_places_is_quarantined_with_the_reason(city, sim, workflow):
    root, inbox, _ = city
    lost = copy_drive(sim / "drive_1", inbox / "drive_lost")
    doc = yaml.safe_load((lost / "drive.yaml").read_text())
    del doc["gnss"]  # no GNSS, no prior trajectory, no start heading: a valid drive file nothing places
    (lost / "drive.yaml").write_text(yaml.safe_dump(doc))
    assert cornermap("drive", "check", str(lost / "drive.yaml")).returncode == 0  # a warning there
    placed = cornermap("drive", "check", "--placed", str(lost / "drive.yaml"))
    assert placed.returncode == 3 and "its frame cannot be fixed" in one_error_line(placed)
    out = rebuild(root, inbox, workflow, "--quiet-period-min", "0")
    assert out.returncode == 0 and "quarantined drive_lost" in out.stdout, out.stdout + out.stderr
    reason = (inbox / "quarantine" / "drive_lost.reason.txt").read_text()
    assert "its frame cannot be fixed" in reason and "start:" in reason, reason
    assert all(d.name != "drive_lost" for d in read_identity(root / "maps" / "city").drives)


def test_a_drive_with_a_sha256sums_file_is_checked_against_it(sim, tmp_path):
    drive = copy_drive(sim / "drive_1", tmp_path / "summed" / "drive_1")
    shutil.copytree(sim / "survey", tmp_path / "summed" / "survey")
    files = sorted(p for p in drive.rglob("*") if p.is_file())
    (drive / "SHA256SUMS").write_text("".join(f"{hashlib.sha256(p.read_bytes()).hexdigest()}  "
                                              f"{p.relative_to(drive)}\n" for p in files))
    res = cornermap("drive", "check", str(drive / "drive.yaml"))
    assert res.returncode == 0 and f"SHA256SUMS: {len(files)} files present and intact" in res.stdout, res.stderr
    [p for p in files if p.suffix == ".pcd"][-1].unlink()  # one scan short: a gap by the stamps file alone (3 %)
    res = cornermap("drive", "check", str(drive / "drive.yaml"))
    assert res.returncode == 1 and "SHA256SUMS: incomplete" in res.stderr and "1 missing" in res.stderr


def _shifted_drive(sim: Path, dst: Path, dlat: float, dlon: float) -> Path:
    drive = copy_drive(sim / "drive_1", dst, rename=True)
    header, rows = _gnss_rows(drive / "gnss_inspva.csv")
    names = header.split(",")
    ilat, ilon = names.index("latitude_deg"), names.index("longitude_deg")
    for r in rows:
        r[ilat], r[ilon] = f"{float(r[ilat]) + dlat:.10f}", f"{float(r[ilon]) + dlon:.10f}"
    _write_gnss(drive / "gnss_inspva.csv", header, rows)
    return drive


def test_a_drive_70_km_away_is_refused_with_exit_3_naming_it_and_the_distance(city, sim, tmp_path):
    root, _, _ = city
    far = _shifted_drive(sim, tmp_path / "far" / "drive_far", 0.5, -0.7)
    shutil.copytree(sim / "survey", tmp_path / "far" / "survey")
    mdir = root / "maps" / "city"
    before = (list_versions(mdir), (mdir / "LATEST").read_bytes())
    res = cornermap("build", "--drive", str(far / "drive.yaml"), "--map", "city", "--root", str(root), "--quiet")
    assert res.returncode == 3, res.stderr
    line = one_error_line(res)
    assert "drive drive_far" in line and " km from the map's origin" in line and "area of 10 km" in line, line
    distance_km = float(line.split(" lies ")[1].split(" km")[0])
    assert 60.0 < distance_km < 90.0, line
    assert (list_versions(mdir), (mdir / "LATEST").read_bytes()) == before


def test_gnss_in_radians_declared_as_degrees_is_a_named_error(sim, tmp_path):
    drive = copy_drive(sim / "drive_1", tmp_path / "rad" / "drive_rad")
    shutil.copytree(sim / "survey", tmp_path / "rad" / "survey")
    header, rows = _gnss_rows(drive / "gnss_inspva.csv")
    names = header.split(",")
    for col in ("latitude_deg", "longitude_deg"):
        i = names.index(col)
        for r in rows:
            r[i] = f"{np.radians(float(r[i])):.12f}"
    _write_gnss(drive / "gnss_inspva.csv", header, rows)
    res = cornermap("drive", "check", str(drive / "drive.yaml"))
    assert res.returncode == 1, res.stdout
    line = one_error_line(res)
    assert "gnss_inspva.csv" in line and "radians" in line and "expected degrees" in line, line


# -- bounded reading of what a version holds -----------------------------------------------------------------
def _png_bomb(width: int, height: int) -> bytes:
    """A valid 8-bit grey PNG of width x height zeros: a few MB that decode to width * height bytes."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return (len(data).to_bytes(4, "big") + kind + data
                + (zlib.crc32(kind + data) & 0xFFFFFFFF).to_bytes(4, "big"))

    z = zlib.compressobj(1)
    block = (b"\0" * (width + 1)) * 100
    idat = b"".join([z.compress(block) for _ in range(height // 100)] + [z.flush()])
    ihdr = width.to_bytes(4, "big") + height.to_bytes(4, "big") + bytes([8, 0, 0, 0, 0])
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def _tampered_copy(root: Path, name: str, edit) -> Path:
    """A copy of map city's v0001 as map ``name``, edited by ``edit(version_dir, manifest)``; the manifest's file
    table and LATEST's digest rewritten to match (someone who can write the whole map)."""
    mdir = root / "maps" / name
    shutil.copytree(root / "maps" / "city" / "v0001", mdir / "v0001")
    manifest = json.loads((mdir / "v0001" / "manifest.json").read_text())
    edit(mdir / "v0001", manifest)
    (mdir / "v0001" / "manifest.json").write_text(json.dumps(manifest, indent=1))
    write_latest(mdir, 1, durable=False)
    return mdir


def test_a_png_bomb_in_a_version_is_refused_before_decoding(city, tmp_path):
    from mapformat.loader import open_map
    from pipeline.errors import MapFormatError

    root, _, _ = city
    tile = {}

    def bomb(vdir: Path, manifest: dict) -> None:
        t = next(t for t in manifest["tiles"] if t.get("marking"))
        tile.update(t)
        rel = f"{t['dir']}/{t['marking']['mask_file']}"
        data = _png_bomb(30000, 30000)
        (vdir / rel).write_bytes(data)
        manifest["files"][rel] = {"sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}

    mdir = _tampered_copy(root, "bombed", bomb)
    with pytest.raises(MapFormatError, match="PNG of 30000 x 30000 pixels"):
        open_map(mdir).tile_marking(tile["i"], tile["j"])
    res = cornermap("tiles", "export", "-f", "geotiff", "-o", str(tmp_path / "rasters"), "--map", "bombed",
                    "--root", str(root))
    assert res.returncode == 1 and "30000 x 30000" in one_error_line(res), res.stderr


def test_tiles_verify_checks_the_manifests_byte_counts(city):
    root, _, _ = city

    def wrong_bytes(vdir: Path, manifest: dict) -> None:
        rel = next(r for r in manifest["files"] if r.endswith("corners.parquet"))
        manifest["files"][rel]["bytes"] += 1

    _tampered_copy(root, "resized", wrong_bytes)
    res = cornermap("tiles", "verify", "--map", "resized", "--root", str(root))
    assert res.returncode == 1 and "bytes, the manifest records" in res.stdout, res.stdout
    assert cornermap("tiles", "verify", "--map", "city", "--root", str(root)).returncode == 0
