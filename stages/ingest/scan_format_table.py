"""The scan file formats ingest reads, in one table: the drive file's ``scans.format`` values, the file suffixes
``drive init`` searches and ``cornermap inspect`` guesses from, the reader of each (a function of
``stages/ingest/scan_formats.py``) and the record layout docs/drive-file.md states (tests/test_docs_drive_file.py
checks the page against this table). No numpy here: the CLI imports this module to build its help.

Adding a format: a row here and its reader in ``scan_formats.py``.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ScanFormat:
    name: str  # the drive file's scans.format
    suffixes: tuple[str, ...]  # lower-case file name endings
    reader: str  # the function of stages.ingest.scan_formats reading one file (path -> ScanPoints)
    layout: str  # what a file holds (docs/drive-file.md, the CLI help)


SCAN_FORMATS: tuple[ScanFormat, ...] = (
    ScanFormat("pcd", (".pcd",), "read_pcd_points", "PCD v0.7 (ascii/binary/binary_compressed)"),
    ScanFormat("kitti_bin", (".bin",), "read_kitti_bin", "KITTI `.bin` (x y z reflectance float32)"),
    ScanFormat("nuscenes_bin", (".bin",), "read_nuscenes_bin", "nuScenes `.bin` (x y z intensity ring float32)"),
    ScanFormat("las", (".las", ".laz"), "read_las_points", "LAS/LAZ"),
)
SCAN_FORMAT_NAMES: tuple[str, ...] = tuple(f.name for f in SCAN_FORMATS)
SCAN_SUFFIXES: dict[str, tuple[str, ...]] = {f.name: f.suffixes for f in SCAN_FORMATS}
DEFAULT_FORMAT_OF_UNKNOWN_SUFFIX = "kitti_bin"  # a .bin is KITTI's unless said otherwise


def scan_format(name: str) -> ScanFormat:
    """The table's row of ``name``; KeyError for a name it does not hold."""
    for f in SCAN_FORMATS:
        if f.name == name:
            return f
    raise KeyError(name)


def format_of_file(file_name: str) -> str:
    """The first format whose suffix ends ``file_name`` (``.bin``: kitti_bin), else kitti_bin."""
    low = file_name.lower()
    return next((f.name for f in SCAN_FORMATS if low.endswith(f.suffixes)), DEFAULT_FORMAT_OF_UNKNOWN_SUFFIX)


def suffix_groups() -> list[tuple[tuple[str, ...], tuple[str, ...]]]:
    """(suffixes, the formats sharing them) in table order: files are told apart by suffix within a group only by
    their content (``.bin``: kitti_bin or nuscenes_bin)."""
    groups: dict[tuple[str, ...], tuple[str, ...]] = {}
    for f in SCAN_FORMATS:
        groups[f.suffixes] = (*groups.get(f.suffixes, ()), f.name)
    return list(groups.items())


def formats_help() -> str:
    """``pcd | kitti_bin | nuscenes_bin | las``."""
    return " | ".join(SCAN_FORMAT_NAMES)


def suffixes_help() -> str:
    """``.pcd/.bin/.las/.laz``."""
    return "/".join(dict.fromkeys(s for f in SCAN_FORMATS for s in f.suffixes))
