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


def drive_fingerprint(drive_yaml: Path) -> str:
    """A raw drive on disk: its drive.yaml bytes plus the (relative path, size) of every file beside it.

    File sizes rather than contents keep this cheap for 8000-scan drives; a rewritten file of equal size is
    not detected (documented limit; ingest writes the sha256 of what it read into its report).
    """
    drive_yaml = Path(drive_yaml)
    folder = drive_yaml.parent
    if not drive_yaml.is_file():
        return stable_hash({"missing": str(drive_yaml)})
    listing = sorted((str(p.relative_to(folder)), p.stat().st_size) for p in folder.rglob("*") if p.is_file())
    return stable_hash({"drive_yaml": drive_yaml.read_bytes().hex(), "files": listing})


def stage_fingerprint(*, stage: str, code_version: str, params: dict, inputs: dict[str, str],
                      drives: dict[str, str], settings: dict) -> str:
    return stable_hash({"stage": stage, "code_version": code_version, "params": params, "inputs": inputs,
                        "drives": drives, "settings": settings})
