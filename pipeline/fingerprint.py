"""Fingerprints: hash(stage, code_version, resolved params, input fingerprints, drives, settings).

A stage whose fingerprint already has a committed manifest is skipped, which makes rebuilds incremental.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any


def stable_hash(obj: Any) -> str:
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def file_sha256(path: Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


HASH_MAX_BYTES = 64 << 20  # files up to this size are fingerprinted by content, larger ones by size + mtime


def file_key(path: Path) -> dict:
    """A file's identity without its location: sha256 when small, else size + modification time (ns)."""
    st = path.stat()
    if st.st_size <= HASH_MAX_BYTES:
        return {"size": st.st_size, "sha256": file_sha256(path)}
    return {"size": st.st_size, "mtime_ns": st.st_mtime_ns}


def folder_key(folder: Path) -> list:
    """A folder's files by relative name, size and modification time (cheap for 8000-scan folders)."""
    out = []
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            st = p.stat()
            out.append((str(p.relative_to(folder)), st.st_size, st.st_mtime_ns))
    return out


def relative_strings(doc: Any) -> list[str]:
    """Every string value of a YAML document that could name a path relative to its folder: not absolute, not a
    URI, shorter than 4096 characters; sorted, once each (a drive file's inputs: ``pipeline.drive_store`` resolves
    them in a bucket, ``_referenced_paths`` in a folder)."""
    out: set[str] = set()

    def walk(node: Any) -> None:
        if isinstance(node, dict):
            for v in node.values():
                walk(v)
        elif isinstance(node, (list, tuple)):
            for v in node:
                walk(v)
        elif isinstance(node, str) and node and len(node) < 4096 and not node.startswith("/") and "://" not in node:
            out.add(node)

    walk(doc)
    return sorted(out)


def _referenced_paths(doc: Any, folder: Path) -> dict[str, Path]:
    """Every string value of a YAML document that names an existing file or folder relative to ``folder``."""
    found: dict[str, Path] = {}
    for node in relative_strings(doc):
        candidate = folder / node
        try:
            if candidate.exists():
                found[node] = candidate
        except OSError:  # a string that is not a usable path (too long, bad characters)
            pass
    return found


def drive_fingerprint(drive_yaml: Path) -> str:
    """A raw drive by content, never by location: the drive file's text, and every file or folder it names
    (relative paths, e.g. the scan folder, the GNSS CSV, a survey cloud in ``../survey/``): small files by sha256,
    large files by size + mtime, folders by each file's relative name, size and mtime. Moving or copying the
    drive keeps its fingerprint (a copy that does not keep modification times re-fingerprints its large files);
    a replaced input changes it.
    """
    from pipeline.errors import ConfigError
    from pipeline.safe_yaml import MAX_YAML_BYTES, load_yaml

    drive_yaml = Path(drive_yaml)
    if not drive_yaml.is_file():
        return stable_hash({"missing": drive_yaml.name})
    if drive_yaml.stat().st_size > MAX_YAML_BYTES:  # ingest refuses it by name; never read a huge file here
        return stable_hash({"oversized": drive_yaml.stat().st_size})
    text = drive_yaml.read_bytes()
    try:
        doc = load_yaml(text, str(drive_yaml))
    except ConfigError:  # ingest reports the problem; the fingerprint still changes with the text
        doc = None
    refs = {}
    for name, path in sorted(_referenced_paths(doc, drive_yaml.parent).items()):
        refs[name] = folder_key(path) if path.is_dir() else file_key(path)
    return stable_hash({"drive_yaml": hashlib.sha256(text).hexdigest(), "referenced": refs})


def stage_fingerprint(*, stage: str, code_version: str, params: dict, inputs: dict[str, str],
                      drives: dict[str, str], settings: dict) -> str:
    return stable_hash({"stage": stage, "code_version": code_version, "params": params, "inputs": inputs,
                        "drives": drives, "settings": settings})
