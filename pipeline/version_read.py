"""Read side of versioned collections: version names, LATEST, manifests, the digest chain, verification.

Knows nothing about LiDAR; ``pipeline.versioned`` (the publisher) re-exports every name defined here.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import re
from pathlib import Path
from typing import Any

from pipeline import storage
from pipeline.errors import ChecksumError, DatasetIOError, MapFormatError, PathEscapeError, UnknownNameError
from pipeline.fingerprint import file_sha256
from pipeline.names import inside

log = logging.getLogger("pipeline.versioned")

MANIFEST_NAME = storage.VERSION_MANIFEST
LATEST_NAME = storage.LATEST
_VERSION_RE = storage.VERSION_RE
_SHA_RE = re.compile(r"^[0-9a-f]{64}$")
MAX_MANIFEST_BYTES = 64 << 20


version_name = storage.version_name


def parse_version(text: str | int) -> int:
    """``3``, ``"3"``, ``"v3"`` or ``"v0003"`` -> 3."""
    if isinstance(text, int):
        return text
    s = str(text).strip()
    m = _VERSION_RE.match(s) or re.match(r"^v?(\d+)$", s)
    if not m:
        raise UnknownNameError(f"{text!r} is not a version; expected vNNNN (e.g. v0003), a number, or LATEST")
    return int(m.group(1))


def list_versions(collection_dir: Path) -> list[int]:
    """Complete version numbers present, ascending (staging and trash directories are ignored)."""
    collection_dir = Path(collection_dir)
    if not collection_dir.is_dir():
        return []
    out = []
    for entry in os.scandir(collection_dir):
        m = _VERSION_RE.match(entry.name)
        if m and entry.is_dir():
            out.append(int(m.group(1)))
    return sorted(out)


def read_latest_entry(collection_dir: Path) -> tuple[int, str | None] | None:
    """(version, manifest sha256 or None for an old one-field LATEST) that ``LATEST`` names; None before the
    first publish."""
    path = Path(collection_dir) / LATEST_NAME
    try:
        with open(path, "rb") as fh:
            raw = fh.read(256)
        text = raw.decode("utf-8")
    except FileNotFoundError:
        return None
    except (IsADirectoryError, UnicodeDecodeError) as exc:
        raise MapFormatError(f"{path}: not a one-line text file ({exc}); hint: rewrite it as 'vNNNN SHA256'") from exc
    except OSError as exc:
        raise DatasetIOError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    fields = text.split()
    ok = len(fields) in (1, 2) and _VERSION_RE.match(fields[0]) and (len(fields) == 1 or _SHA_RE.match(fields[1]))
    if not ok:
        raise MapFormatError(f"{path}: expected one line 'vNNNN SHA256'; got {text[:40]!r}. "
                             "hint: rewrite it with the name of a complete version directory")
    if len(fields) == 1:
        log.warning("%s names %s without its manifest digest (written by an older cornermap); the manifest of "
                    "that version cannot be checked against it", path, fields[0])
    return int(fields[0][1:]), (fields[1] if len(fields) == 2 else None)


def read_latest(collection_dir: Path) -> int | None:
    """The version ``LATEST`` names, or None before the first publish."""
    entry = read_latest_entry(collection_dir)
    return None if entry is None else entry[0]


def resolve_version(collection_dir: Path, version: str | int = "LATEST") -> Path:
    """Directory of ``version`` ("LATEST", "v0003", 3); raises UnknownNameError when absent."""
    collection_dir = Path(collection_dir)
    if isinstance(version, str) and version.upper() == "LATEST":
        number = read_latest(collection_dir)
        if number is None:
            raise UnknownNameError(f"{collection_dir}: nothing published yet (no {LATEST_NAME} file)")
    else:
        number = parse_version(version)
    path = collection_dir / version_name(number)
    if not path.is_dir():
        have = ", ".join(version_name(v) for v in list_versions(collection_dir)) or "none"
        raise UnknownNameError(f"{collection_dir}: no version {version_name(number)}; have {have}")
    return path


def read_manifest(version_dir: Path) -> tuple[dict[str, Any], str]:
    """(manifest dict, sha256 of manifest.json)."""
    path = Path(version_dir) / MANIFEST_NAME
    try:
        with open(path, "rb") as fh:  # read(n) would preallocate n bytes: check the size first
            if os.fstat(fh.fileno()).st_size > MAX_MANIFEST_BYTES:
                raise MapFormatError(f"{path}: larger than the {MAX_MANIFEST_BYTES}-byte limit for a manifest")
            raw = fh.read()
    except FileNotFoundError as exc:
        raise MapFormatError(f"{path}: missing; a complete version always has one") from exc
    except OSError as exc:
        raise MapFormatError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    if len(raw) > MAX_MANIFEST_BYTES:
        raise MapFormatError(f"{path}: larger than the {MAX_MANIFEST_BYTES}-byte limit for a manifest")
    try:
        manifest = json.loads(raw)
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
        raise MapFormatError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(manifest, dict):
        raise MapFormatError(f"{path}: expected a JSON object; got {type(manifest).__name__}")
    return manifest, hashlib.sha256(raw).hexdigest()


def trusted_manifest_digests(collection_dir: Path) -> dict[int, str]:
    """Manifest sha256 of each version vouched for from outside its own manifest: LATEST's digest for the
    version it names, then each manifest's ``parent_manifest_sha256`` for its parent, down the chain.

    The chain stops at a version whose manifest does not match the digest vouching for it (that version's
    verification then fails) or that records no parent digest (older maps)."""
    collection_dir = Path(collection_dir)
    entry = read_latest_entry(collection_dir)
    out: dict[int, str] = {}
    if entry is None or entry[1] is None:
        return out
    version, sha = entry
    while version is not None and sha is not None and version not in out:
        out[version] = sha
        try:
            manifest, got = read_manifest(collection_dir / version_name(version))
        except MapFormatError:
            break
        if got != sha:
            break
        parent, sha = manifest.get("parent_version"), manifest.get("parent_manifest_sha256")
        version = parent if isinstance(parent, int) else None
    return out


def verify_version(version_dir: Path, manifest_sha256: str | None = None) -> list[str]:
    """Every problem of a version directory (manifest digest when ``manifest_sha256`` is given, paths leaving
    the directory, missing, extra or corrupted files: a size other than the manifest's ``bytes``, or another
    sha256); empty when intact."""
    version_dir = Path(version_dir)
    manifest, got_sha = read_manifest(version_dir)
    problems = []
    if manifest_sha256 is not None and got_sha != manifest_sha256:
        problems.append(f"{version_dir / MANIFEST_NAME}: sha256 {got_sha[:16]}... differs from the digest recorded "
                        f"outside it ({manifest_sha256[:16]}...); the manifest was edited or replaced")
    listed = manifest.get("files")
    if not isinstance(listed, dict):
        return problems + [f"{version_dir / MANIFEST_NAME}: no 'files' table"]
    for rel, entry in sorted(listed.items()):
        try:
            path = inside(version_dir, rel)
        except PathEscapeError as exc:
            problems.append(f"{version_dir / MANIFEST_NAME}: file entry {rel!r} leaves the version directory ({exc})")
            continue
        if not isinstance(entry, dict):
            problems.append(f"{version_dir / MANIFEST_NAME}: file entry {rel!r} is not an object")
            continue
        if not path.is_file():
            problems.append(f"{path}: missing (manifest lists it)")
            continue
        size, recorded = path.stat().st_size, entry.get("bytes")
        if recorded is not None and (not isinstance(recorded, int) or isinstance(recorded, bool) or recorded < 0):
            problems.append(f"{version_dir / MANIFEST_NAME}: file entry {rel!r} records bytes {recorded!r}; expected a "
                            "whole number >= 0")
        elif recorded is not None and size != recorded:
            problems.append(f"{path}: {size} bytes, the manifest records {recorded}")
            continue
        got = file_sha256(path)
        if got != entry.get("sha256"):
            problems.append(f"{path}: sha256 {got[:16]}... differs from manifest {str(entry.get('sha256'))[:16]}...")
    present = {p.relative_to(version_dir).as_posix() for p in version_dir.rglob("*") if p.is_file()}
    for rel in sorted(present - set(listed) - {MANIFEST_NAME}):
        problems.append(f"{version_dir / rel}: not listed in the manifest")
    return problems


def check_version(version_dir: Path) -> None:
    """Raise ChecksumError listing every problem, or return when the version is intact."""
    problems = verify_version(version_dir)
    if problems:
        raise ChecksumError(f"{version_dir}: {len(problems)} problem(s):\n" + "\n".join(f"  - {p}" for p in problems)
                            + "\nhint: the version is corrupt; republish it or restore it from backup")


def version_states(mdir: Path) -> dict[int, str]:
    """Each version's standing: ``LATEST``; ``refused`` when the regression gate refused it (``gate/vNNNN.json`` with
    ``ok`` false: ``cornermap rebuild`` left LATEST on its parent); ``candidate`` when it is newer than LATEST and was
    never gated (a rebuild stopped before its gate); ``""`` otherwise (an older version LATEST once named)."""
    latest = read_latest(mdir) if storage.latest_file(Path(mdir)).exists() else None
    out = {}
    for v in list_versions(mdir):
        gate = storage.gate_file(Path(mdir), v)
        try:
            ok = json.loads(gate.read_text(encoding="utf-8")).get("ok") if gate.is_file() else None
        except (OSError, ValueError, AttributeError):
            ok = None
        if v == latest:
            out[v] = "LATEST"
        elif ok is False:
            out[v] = "refused"
        elif latest is not None and v > latest and ok is None:
            out[v] = "candidate"
        else:
            out[v] = ""
    return out


def state_note(mdir: Path, version: int, state: str) -> str:
    """The words ``tiles ls`` and ``maps show`` print after a version in that standing."""

    if state == "refused":
        return f"REFUSED by the regression gate ({storage.gate_file(Path(mdir), version)}); never LATEST"
    if state == "candidate":
        return "candidate, not gated (a rebuild stopped before its gate); never LATEST"
    return ""
