"""Delta delivery: the files that differ between two versions of a map as a bundle, applied to a vehicle's copy.

    OUT/bundle.json          format cornermap-bundle 1 (schema: mapformat/schemas/bundle.schema.json): map name,
                             base and target (version, sha256 of manifest.json), every file of the target with its
                             sha256, bytes and source ("bundle": in OUT/files/, "base": taken from the base copy),
                             the base files the target drops, bundle and target bytes
    OUT/files/manifest.json  the target's manifest, byte for byte (its sha256 is the target's digest)
    OUT/files/<path>         each target file whose bytes the base does not have at that path

``make_bundle`` writes OUT through a temporary folder renamed into place. ``apply_bundle`` turns a copy of the map
folder (``LATEST`` naming the base, the base's folder) into one whose LATEST names the target: it refuses a bundle
whose base is not the copy's version (number and manifest digest), a bundle.json that disagrees with the target's
manifest, a file whose sha256 differs, a path leaving the folder, a bundle file that is not a regular file; the
target is assembled and checked file by file in a staging folder under the copy, renamed to ``vNNNN`` and only then
named by LATEST (atomic replace), so a copy never shows a half-applied bundle. The base version stays.
"""
from __future__ import annotations

import hashlib
import json
import os
import secrets
import shutil
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from mapformat.schemas import validate
from pipeline.errors import IntegrityError, MapFormatError, PublishConflictError, UnknownNameError
from pipeline.names import inside
from pipeline.storage import VERSION_MANIFEST

BUNDLE_FILE = "bundle.json"
BUNDLE_FORMAT = "cornermap-bundle"
FILES_DIR = "files"
MANIFEST = VERSION_MANIFEST  # files/manifest.json: the target version's manifest
MAX_BUNDLE_JSON_BYTES = 64 << 20


def _sha256_copy(src: Path, dst: Path | None) -> str:
    """sha256 of ``src`` (copied to ``dst`` on the way when given)."""
    h = hashlib.sha256()
    with open(src, "rb") as fi, (open(dst, "wb") if dst is not None else open(os.devnull, "wb")) as fo:
        while chunk := fi.read(1 << 20):
            h.update(chunk)
            fo.write(chunk)
        if dst is not None:
            fo.flush()
            os.fsync(fo.fileno())
    return h.hexdigest()


def _regular(path: Path, what: str) -> Path:
    if path.is_symlink() or not path.is_file():
        raise MapFormatError(f"{path}: {what} is not a regular file (a link or missing); refusing it")
    return path


def make_bundle(map_dir: Path, base: str | int, target: str | int, out: Path) -> dict[str, Any]:
    """Write the bundle turning ``base`` into ``target`` (versions of ``map_dir``) at ``out`` (must not exist or be
    empty); return its bundle.json document. Every file written is checked against the target's manifest."""
    from mapformat.loader import open_map

    a, b = open_map(map_dir, base), open_map(map_dir, target)
    if a.version == b.version:
        raise UnknownNameError(f"{map_dir}: base and target are both v{a.version:04d}; nothing to bundle")
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise PublishConflictError(f"{out}: exists and is not an empty folder; a bundle is written to a new one")
    base_files = a.manifest.get("files", {})
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}"
    (tmp / FILES_DIR).mkdir(parents=True)
    try:
        entries, bundle_bytes = [], 0
        for rel, info in sorted(b.manifest.get("files", {}).items()):
            src = _regular(inside(b.path, rel), "a file of the target")
            same = (base_files.get(rel) or {}).get("sha256") == info["sha256"]
            if not same:
                dst = inside(tmp / FILES_DIR, rel)
                dst.parent.mkdir(parents=True, exist_ok=True)
                if _sha256_copy(src, dst) != info["sha256"]:
                    raise IntegrityError(f"{src}: its sha256 differs from v{b.version:04d}'s manifest; hint: run "
                                         "`cornermap tiles verify`")
                bundle_bytes += int(info["bytes"])
            entries.append({"path": rel, "sha256": info["sha256"], "bytes": int(info["bytes"]),
                            "source": "base" if same else "bundle"})
        raw = (b.path / MANIFEST).read_bytes()
        if hashlib.sha256(raw).hexdigest() != b.manifest_sha256:
            raise IntegrityError(f"{b.path / MANIFEST}: changed while bundling")
        (tmp / FILES_DIR / MANIFEST).write_bytes(raw)
        target_bytes = sum(int(i["bytes"]) for i in b.manifest.get("files", {}).values()) + len(raw)
        doc = {"format": BUNDLE_FORMAT, "format_version": 1, "map_name": str(b.manifest.get("map_name")),
               "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
               "base": {"version": a.version, "manifest_sha256": a.manifest_sha256},
               "target": {"version": b.version, "manifest_sha256": b.manifest_sha256},
               "files": entries, "removed": sorted(set(base_files) - set(b.manifest.get("files", {}))),
               "bytes": {"bundle": bundle_bytes + len(raw), "target": target_bytes}}
        validate(doc, "bundle", str(out / BUNDLE_FILE))
        (tmp / BUNDLE_FILE).write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
        if out.exists():
            out.rmdir()
        os.rename(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return doc


def read_bundle(bundle_dir: Path) -> dict[str, Any]:
    """bundle.json, bounded and checked against its schema."""
    path = _regular(Path(bundle_dir) / BUNDLE_FILE, BUNDLE_FILE)
    if path.stat().st_size > MAX_BUNDLE_JSON_BYTES:
        raise MapFormatError(f"{path}: {path.stat().st_size} bytes, more than {MAX_BUNDLE_JSON_BYTES}")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise MapFormatError(f"{path}: not JSON ({exc})") from exc
    validate(doc, "bundle", str(path))
    return doc


def _check_target(doc: dict[str, Any], bundle_dir: Path) -> tuple[bytes, dict[str, Any]]:
    """The target manifest's bytes and document, after checking its digest and that it lists exactly the bundle's
    files with the same sha256 and sizes."""
    path = _regular(inside(Path(bundle_dir) / FILES_DIR, MANIFEST), "the target's manifest")
    raw = path.read_bytes()
    if hashlib.sha256(raw).hexdigest() != doc["target"]["manifest_sha256"]:
        raise IntegrityError(f"{path}: sha256 differs from the bundle's target digest "
                             f"{doc['target']['manifest_sha256'][:16]}...; the bundle was altered")
    manifest = json.loads(raw)
    if manifest.get("version") != doc["target"]["version"] or manifest.get("map_name") != doc["map_name"]:
        raise IntegrityError(f"{path}: map {manifest.get('map_name')!r} v{manifest.get('version')}, the bundle says "
                             f"{doc['map_name']!r} v{doc['target']['version']}")
    listed = {e["path"]: (e["sha256"], e["bytes"]) for e in doc["files"]}
    table = {rel: (i.get("sha256"), i.get("bytes")) for rel, i in (manifest.get("files") or {}).items()}
    if listed != table:
        odd = sorted(set(listed.items()) ^ set(table.items()))[:3]
        raise IntegrityError(f"{Path(bundle_dir) / BUNDLE_FILE}: its file list disagrees with the target's manifest "
                             f"(e.g. {odd}); the bundle was altered")
    return raw, manifest


def apply_bundle(bundle_dir: Path, map_folder: Path) -> dict[str, Any]:
    """Turn the copy at ``map_folder`` (LATEST naming the bundle's base) into the target; return
    {"base", "target", "written", "from_base"}. See the module doc for every refusal."""
    from pipeline.versioned import publish_lock, read_latest, read_manifest, version_name, write_latest

    bundle_dir, map_folder = Path(bundle_dir), Path(map_folder)
    doc = read_bundle(bundle_dir)
    raw, manifest = _check_target(doc, bundle_dir)
    base_v, target_v = int(doc["base"]["version"]), int(doc["target"]["version"])
    for e in doc["files"]:  # every path inside both folders before anything is written
        inside(map_folder / version_name(target_v), e["path"])
        if e["source"] == "bundle":
            inside(bundle_dir / FILES_DIR, e["path"])
    with publish_lock(map_folder):
        held = read_latest(map_folder)
        if held is None:
            raise UnknownNameError(f"{map_folder}: no LATEST; the copy holds no version to apply the bundle to")
        held_sha = read_manifest(map_folder / version_name(held))[1]
        if held == target_v and held_sha == doc["target"]["manifest_sha256"]:
            return {"base": base_v, "target": target_v, "written": 0, "from_base": 0, "already": True}
        if held != base_v or held_sha != doc["base"]["manifest_sha256"]:
            raise MapFormatError(f"{map_folder}: holds {version_name(held)} (manifest {held_sha[:16]}...); the bundle "
                                 f"applies to {version_name(base_v)} (manifest "
                                 f"{doc['base']['manifest_sha256'][:16]}...) only; refusing it")
        final = map_folder / version_name(target_v)
        if final.exists():
            raise PublishConflictError(f"{final}: exists; a version folder is never overwritten")
        staging = map_folder / f".staging-{version_name(target_v)}-{os.getpid()}-{secrets.token_hex(4)}"
        staging.mkdir()
        written = from_base = 0
        try:
            for e in doc["files"]:
                if e["source"] == "bundle":
                    src = _regular(inside(bundle_dir / FILES_DIR, e["path"]), "a bundle file")
                    written += 1
                else:
                    src = _regular(inside(map_folder / version_name(base_v), e["path"]), "a file of the base copy")
                    from_base += 1
                dst = inside(staging, e["path"])
                dst.parent.mkdir(parents=True, exist_ok=True)
                got = _sha256_copy(src, dst)
                if got != e["sha256"]:
                    raise IntegrityError(f"{src}: sha256 {got[:16]}... differs from the target's "
                                         f"{e['sha256'][:16]}... for {e['path']}; nothing applied")
            with open(staging / MANIFEST, "wb") as fh:
                fh.write(raw)
                fh.flush()
                os.fsync(fh.fileno())
            for d in sorted({p.parent for p in staging.rglob("*")} | {staging}, key=lambda p: -len(p.parts)):
                fd = os.open(d, os.O_RDONLY | os.O_DIRECTORY)
                os.fsync(fd)
                os.close(fd)
            os.rename(staging, final)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
        write_latest(map_folder, target_v, True, doc["target"]["manifest_sha256"])
    return {"base": base_v, "target": target_v, "written": written, "from_base": from_base, "already": False,
            "map_name": manifest.get("map_name")}

