"""Integrity check of a published map version: the manifest's digest, every checksum, the file list, the
tile table, and that every path the manifest names stays inside the version directory."""
from __future__ import annotations

from pathlib import Path

from mapformat import layout
from mapformat.loader import check_manifest_format
from pipeline.errors import MapFormatError, PathEscapeError
from pipeline.names import inside
from pipeline.versioned import MANIFEST_NAME, read_manifest, verify_version


def verify_map(version_dir: Path, manifest_sha256: str | None = None) -> list[str]:
    """Every problem of a map version (empty when intact): a manifest whose sha256 differs from
    ``manifest_sha256`` (the digest recorded outside it, see ``trusted_manifest_digests``), unknown format,
    missing/extra/corrupt files, paths leaving the version directory, tile entries whose per-file sha256
    disagrees with the manifest's file table."""
    version_dir = Path(version_dir)
    try:
        manifest, _ = read_manifest(version_dir)
        check_manifest_format(manifest, version_dir / MANIFEST_NAME)
    except MapFormatError as exc:
        return [str(exc)]
    problems = verify_version(version_dir, manifest_sha256)
    files = manifest.get("files") if isinstance(manifest.get("files"), dict) else {}
    tiles = manifest.get("tiles")
    if not isinstance(tiles, list):
        return problems + [f"{version_dir / MANIFEST_NAME}: no 'tiles' list"]
    for n, tile in enumerate(tiles):
        try:
            where, tdir = f"tile ({tile['i']},{tile['j']})", str(tile["dir"])
            inside(version_dir, tdir)
            named = dict(tile.get("files") or {})
            marking = tile.get("marking") or {}
            if marking.get("mask_file"):
                named.setdefault(str(marking["mask_file"]), None)
        except PathEscapeError as exc:
            problems.append(f"{version_dir / MANIFEST_NAME}: tile entry {n}: {exc}")
            continue
        except (KeyError, TypeError, AttributeError, ValueError) as exc:
            problems.append(f"{version_dir / MANIFEST_NAME}: tile entry {n} is malformed ({type(exc).__name__}: {exc})")
            continue
        for name, sha in named.items():
            rel = f"{tdir}/{name}"
            try:
                inside(version_dir, rel)
            except PathEscapeError as exc:
                problems.append(f"{version_dir / MANIFEST_NAME}: {where}: {exc}")
                continue
            if rel not in files:
                problems.append(f"{version_dir / rel}: {where} names a file the file table does not list")
            elif sha is not None and (files[rel].get("sha256") if isinstance(files[rel], dict) else None) != sha:
                problems.append(f"{version_dir / rel}: {where} records a sha256 the file table does not")
        if f"{tdir}/{layout.CORNERS_FILE}" not in files:
            problems.append(f"{version_dir / tdir}: {where} has no {layout.CORNERS_FILE}")
    return problems
