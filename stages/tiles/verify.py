"""Integrity check of a published map version: every checksum, the file list, and the tile table."""
from __future__ import annotations

from pathlib import Path

from pipeline.errors import MapFormatError
from pipeline.versioned import MANIFEST_NAME, read_manifest, verify_version
from stages.tiles import layout
from stages.tiles.loader import check_manifest_format


def verify_map(version_dir: Path) -> list[str]:
    """Every problem of a map version (empty when intact): unknown format, missing/extra/corrupt files,
    tile entries whose per-file sha256 disagrees with the manifest's file table."""
    version_dir = Path(version_dir)
    try:
        manifest, _ = read_manifest(version_dir)
        check_manifest_format(manifest, version_dir / MANIFEST_NAME)
    except MapFormatError as exc:
        return [str(exc)]
    problems = verify_version(version_dir)
    files = manifest.get("files", {})
    for tile in manifest.get("tiles", []):
        for name, sha in tile.get("files", {}).items():
            rel = f"{tile['dir']}/{name}"
            if files.get(rel, {}).get("sha256") != sha:
                problems.append(f"{version_dir / rel}: tile ({tile['i']},{tile['j']}) records a sha256 the file "
                                "table does not")
        if f"{tile['dir']}/{layout.CORNERS_FILE}" not in files:
            problems.append(f"{version_dir / tile['dir']}: tile ({tile['i']},{tile['j']}) has no {layout.CORNERS_FILE}")
    return problems
