"""Drive-scoped reuse: a drive's per-drive work is committed once and reused by every later build of its map.

A stage's fingerprint covers all of its drives, so adding a drive to a map gives every stage a new fingerprint
(a new dataset directory). For per-drive and per-scan-chunk stages whose inputs are themselves drive-scoped,
a partition of drive D depends on D alone once the map's frame is pinned (``enu_origin`` set: the drive lists
only choose an origin otherwise). Such a partition gets a *drive-scope fingerprint*::

    scope(stage, D) = hash(stage, code_version, params, settings without the drive lists (D's entry of
                           per-drive settings such as references),
                           D's name, role and content fingerprint, scope(producer of each input, D))

recorded in its part marker. When a new dataset directory needs partition ``label`` of drive D, a sibling
directory of the same dataset holding a committed part marker with the same scope fingerprint is reused:
its files are hard-linked (copied across file systems) into the new directory and a marker is written, in
place of computing. Parquet and artifact files are immutable once committed, so links are safe and the
drive's scans are stored once however many versions use them.
"""
from __future__ import annotations

import json
import logging
import os
import shutil
from pathlib import Path
from typing import Any

from pipeline import storage
from pipeline.fingerprint import stable_hash
from pipeline.names import inside

log = logging.getLogger(__name__)

DRIVE_LIST_SETTINGS = ("map_drives", "eval_drives")
PER_DRIVE_SETTINGS = ("references",)  # {drive: value}: a partition of drive D sees D's entry only


def drive_scope_fingerprints(*, frame_pinned: bool, stage: str, code_version: str, params: dict,
                             settings: dict[str, Any],
                             drive_fps: dict[str, str], roles: dict[str, str],
                             input_scopes: dict[str, dict[str, str] | None]) -> dict[str, str]:
    """Per-drive scope fingerprints of one stage, or {} when its partitions are not a function of their drive
    alone (the workflow pins no ``enu_origin``, or an input that is not drive-scoped). ``input_scopes``: arg -> the
    producer's scope fingerprints ({} for an absent optional input, None for an input that is not drive-scoped)."""
    if not frame_pinned or any(v is None for v in input_scopes.values()):
        return {}
    fixed = {k: v for k, v in settings.items() if k not in DRIVE_LIST_SETTINGS + PER_DRIVE_SETTINGS}
    out = {}
    for drive, dfp in drive_fps.items():
        own = {k: (settings[k] or {}).get(drive) for k in PER_DRIVE_SETTINGS if k in settings}
        ins = {}
        for arg, scopes in input_scopes.items():
            if scopes and drive not in scopes:
                break
            ins[arg] = scopes.get(drive, "absent") if scopes else "absent"
        else:
            out[drive] = stable_hash({"stage": stage, "code_version": code_version, "params": params,
                                      "settings": {**fixed, **own}, "drive": drive, "role": roles.get(drive),
                                      "drive_fingerprint": dfp, "inputs": ins})
    return out


def _link(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    if dst.exists():
        dst.unlink()
    try:
        os.link(src, dst)
    except OSError:  # another file system, or links not supported
        shutil.copy2(src, dst)


def find_committed(datasets_root: Path, dataset: str, own_dir: Path, label: str, scope: str
                   ) -> tuple[Path, dict[str, Any]] | None:
    """A sibling dataset directory whose part marker ``label`` records ``scope`` and whose files exist."""
    base = datasets_root / dataset
    if not base.is_dir():
        return None
    for d in sorted(base.iterdir()):
        if d == own_dir or not d.is_dir():
            continue
        marker = storage.part_marker(d, label)
        try:
            doc = json.loads(marker.read_text())
        except (OSError, ValueError):
            continue
        if doc.get("scope") != scope:
            continue
        out = doc.get("output", {})
        files = [d / r["path"] for r in out.get("files", [])]
        files += [storage.artifacts_dir(d, label) / r["path"] for r in (out.get("artifacts") or [])]
        if all(f.is_file() for f in files):
            return d, doc
    return None


def link_partition(src_dir: Path, dst_dir: Path, label: str, output: dict[str, Any]) -> None:
    """Hard-link one partition's committed files (tables and artifacts) from src_dir into dst_dir."""
    for rec in output.get("files", []):
        _link(inside(src_dir, rec["path"]), inside(dst_dir, rec["path"]))
    for rec in output.get("artifacts") or []:
        _link(inside(storage.artifacts_dir(src_dir, label), rec["path"]),
              inside(storage.artifacts_dir(dst_dir, label), rec["path"]))
