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
its files are hard-linked (copied across file systems; on an object store copied server-side, no bytes through
the task) into the new directory and a marker is written, in place of computing. Parquet and artifact files are
immutable once committed, so links are safe and the drive's scans are stored once however many versions use them
(on an object store: twice, as copies).
"""
from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING, Any

from pipeline import storage
from pipeline.fingerprint import stable_hash
from pipeline.names import inside

if TYPE_CHECKING:
    from pipeline.store import DataRoot

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


def _files_of(output: dict[str, Any], label: str) -> list[str]:
    """A partition's files (tables and artifacts), relative to its dataset directory."""
    art = storage.artifacts_dir(PurePosixPath(), label)
    return [r["path"] for r in output.get("files", [])] + [(art / r["path"]).as_posix()
                                                           for r in (output.get("artifacts") or [])]


def find_committed(root: "DataRoot", dataset: str, own_fp: str, label: str, scope: str
                   ) -> tuple[str, dict[str, Any]] | None:
    """(fingerprint folder, part marker) of a sibling dataset directory whose part marker ``label`` records
    ``scope`` and whose files exist."""
    own = own_fp[:storage.FP_LEN]
    for fp in root.siblings(dataset):
        if fp == own or fp.startswith("."):
            continue
        doc = root.part(dataset, fp, label)
        if doc is None or doc.get("scope") != scope:
            continue
        rels = _files_of(doc.get("output", {}), label)
        if root.remote:
            have = {rel for rel, _ in root.store.walk_files(root.loc(dataset, fp))}
            present = all(rel in have for rel in rels)
        else:
            base = root.dir(dataset, fp)
            present = all(inside(base, rel).is_file() for rel in rels)
        if present:
            return fp, doc
    return None


def link_partition(root: "DataRoot", dataset: str, src_fp: str, dst_fp: str, label: str,
                   output: dict[str, Any]) -> None:
    """One partition's committed files (tables and artifacts) from fingerprint folder ``src_fp`` into ``dst_fp``:
    hard links on a local root (copies across file systems), server-side copies on an object store (no bytes
    through the task)."""
    for rel in _files_of(output, label):
        if root.remote:
            root.store.copy(root.loc(dataset, src_fp) / rel, root.loc(dataset, dst_fp) / rel)
        else:
            _link(inside(root.dir(dataset, src_fp), rel), inside(root.dir(dataset, dst_fp), rel))
