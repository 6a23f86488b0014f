"""The docs are reference pages: no scratch path (/tmp) anywhere, and every parameter table's default is the code's
default (a page that says 0.15 where the code says 0.25 fails here).

A parameter table is a markdown table with a ``default`` column whose rows start with a name in backticks. Every
such table on every page is checked against the code that owns the names: a stage's pydantic params, the
simulator's presets, or the drive file's model; a page with such a table that names no owner fails.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted((ROOT / "docs").glob("*.md")) + [ROOT / "README.md", ROOT / "CHANGELOG.md"]
# pages with parameter tables -> the owners of their names: stage names (their params model), "presets" (the
# simulator's Preset fields: the record's default) or "drive_file" (the drive file's keys)
PARAM_PAGES = {"corners.md": ("corners",), "posegraph.md": ("odometry", "posegraph"), "evaluation.md": ("evaluate",),
               "cornermap.md": ("cornermap",), "simulator.md": ("presets",), "drive-file.md": ("drive_file",)}
NAME = re.compile(r"`\.?[A-Za-z0-9_.]+`")
UNIT = re.compile(r"\s+(m|deg|mrad|s|Hz|m\^2)$")
TUPLE = re.compile(r"^\(\s*-?[0-9.]+(\s*,\s*-?[0-9.]+)+\s*\)$")
DERIVED = object()  # a default described in words ("the sensor's table"): the code's default is None


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_no_scratch_paths(page):
    hits = [f"{page.name}:{n}" for n, line in enumerate(page.read_text().splitlines(), 1) if "/tmp" in line]
    assert not hits, f"/tmp paths in docs (use runs/... or a bench command): {hits}"


def _cells(line: str) -> list[str]:
    return [c.strip() for c in re.split(r"(?<!\\)\|", line.strip().strip("|"))]


def param_tables(page: Path):
    """(line number, heading above, default column, body rows as cell lists) of every parameter table."""
    lines = page.read_text().splitlines()
    heading = ""
    for n, line in enumerate(lines):
        if line.startswith("#"):
            heading = line
        is_header = line.startswith("|") and n + 1 < len(lines) and re.match(r"^\|\s*:?-{3}", lines[n + 1])
        if not is_header:
            continue
        header = [c.lower() for c in _cells(line)]
        body = []
        for row in lines[n + 2:]:
            if not row.startswith("|"):
                break
            body.append(_cells(row))
        if "default" in header and body and body[0][0].startswith("`"):
            yield n + 1, heading, header.index("default"), body


def _names(cell: str) -> list[str]:
    """`a` / `b`, `a`, `.b` (relative to a's parent): the full names."""
    out = []
    for raw in NAME.findall(cell):
        name = raw.strip("`")
        out.append(out[0].rsplit(".", 1)[0] + name if name.startswith(".") and out else name)
    return out


def _value(text: str):
    text = text.strip().strip("`")
    if text.lower() in ("none", "required"):
        return text.lower() if text.lower() == "required" else None
    text = UNIT.sub("", text)
    if TUPLE.match(text):
        text = "[" + text[1:-1] + "]"
    try:
        v = yaml.safe_load(text)
    except yaml.YAMLError:
        return DERIVED
    if isinstance(v, str):
        return DERIVED if re.search(r"[\s()<>,]", v) else v.lower().strip("'\"")
    return v


def _same(doc_value, code_value) -> bool:
    if doc_value is DERIVED:
        return code_value is None
    if hasattr(code_value, "value"):  # enums
        code_value = code_value.value
    if doc_value is None or code_value is None:
        return doc_value is code_value
    if isinstance(code_value, str):
        return str(doc_value).lower() == code_value.lower()
    if isinstance(code_value, (list, tuple)):
        return isinstance(doc_value, list) and len(doc_value) == len(code_value) and all(
            _same(d, c) for d, c in zip(doc_value, code_value))
    if isinstance(code_value, bool) or isinstance(doc_value, bool):
        return doc_value is code_value
    return isinstance(doc_value, (int, float)) and doc_value == pytest.approx(code_value, rel=1e-12, abs=0.0)


def _rows(page: Path, owners: tuple[str, ...]):
    """(owners of the row, name, default text): the owner named in the nearest heading above the table, else every
    owner of the page."""
    for _, heading, col, body in param_tables(page):
        named = tuple(s for s in owners if re.search(rf"\b{s}\b", heading))
        for cells in body:
            names = _names(cells[0])
            if not names or col >= len(cells):
                continue
            text = cells[col]
            values = [v.strip() for v in re.split(r"\s+/\s+|,\s+(?![^(]*\))", text)] if len(names) > 1 else [text]
            if len(values) == 1:
                values = values * len(names)
            if len(values) == len(names):
                for name, value in zip(names, values):
                    yield named or owners, name, value


def _stage_default(stage: str, name: str):
    """A stage param's default; a dotted name (``ekf.icp.sigma_frac``) is a field of a section."""
    from pipeline.registry import get_stage

    value = get_stage(stage).params()  # a dotted name is a key of a section (``loops.radius_m``)
    for part in name.split("."):
        if not hasattr(type(value), "model_fields") or part not in type(value).model_fields:
            return KeyError
        value = getattr(value, part)
    return value


def _preset_defaults(name: str):
    """The Preset record's default of the field (presets may set their own), else its value in every preset
    (KeyError when not a Preset field; a list when the presets differ)."""
    import dataclasses

    from stages.simulate.presets import PRESETS, Preset

    field = {f.name: f for f in dataclasses.fields(Preset)}.get(name)
    if field is not None and field.default is not dataclasses.MISSING:
        return field.default
    values = {repr(getattr(p, name, KeyError)) for p in PRESETS.values()}
    if len(values) != 1:
        return [getattr(p, name) for p in PRESETS.values()]
    return getattr(next(iter(PRESETS.values())), name, KeyError)


def _drive_file_default(name: str):
    """A dotted drive-file key's default ("required" when it has none; KeyError when not a key)."""
    import typing

    from pydantic import BaseModel

    from stages.ingest.drive_file import DriveSpec

    model, info = DriveSpec, None
    for part in name.split("."):
        if model is None or part not in model.model_fields:
            return KeyError
        info = model.model_fields[part]
        model = next((t for t in (info.annotation, *typing.get_args(info.annotation))
                      if isinstance(t, type) and issubclass(t, BaseModel)), None)
    return "required" if info.is_required() else info.get_default(call_default_factory=True)


def _code_default(owner: str, name: str):
    if owner == "presets":
        return _preset_defaults(name)
    if owner == "drive_file":
        return _drive_file_default(name)
    return _stage_default(owner, name)


@pytest.mark.parametrize("page_name", sorted(PARAM_PAGES))
def test_param_table_defaults_match_the_code(page_name):
    checked, wrong, unknown = 0, [], []
    for owners, name, text in _rows(ROOT / "docs" / page_name, PARAM_PAGES[page_name]):
        found = [(o, d) for o in owners if (d := _code_default(o, name)) is not KeyError]
        if not found:
            unknown.append(name)
            continue
        for owner, default in found:
            checked += 1
            doc = _value(text)
            if not (_same(doc, default) or (default == "required" and doc == "required")):
                wrong.append(f"{name}: docs {text!r}, {owner} {default!r}")
    assert checked >= 8, f"{page_name}: only {checked} parameter rows recognised; did the table format change?"
    assert not wrong, f"{page_name}: parameter defaults differ from the code: {wrong}"
    assert not unknown, f"{page_name}: rows naming no parameter of {PARAM_PAGES[page_name]}: {unknown}"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_parameter_table_is_checked(page):
    tables = [n for n, *_ in param_tables(page)]
    assert not tables or page.name in PARAM_PAGES, (
        f"{page.name}: parameter tables at lines {tables} are not checked; name their owner in PARAM_PAGES")


# Pages that are reference pages (issue 61): what a thing does, its inputs, outputs and params, and its current
# figures with the command; the history of the figures is in CHANGELOG.md and git. Add a page once it is converted.
REFERENCE_PAGES = ["README.md", "docs/architecture.md", "docs/cornermap.md", "docs/corners.md", "docs/drive-file.md",
                   "docs/evaluation.md", "docs/ingest.md", "docs/maintenance.md", "docs/map-format.md",
                   "docs/markings.md", "docs/performance.md", "docs/posegraph.md", "docs/security.md",
                   "docs/simulator.md", "docs/storage.md"]
MAX_DATED_SHARE = 0.15


@pytest.mark.parametrize("name", REFERENCE_PAGES)
def test_reference_pages_hold_no_measurement_history(name):
    from bench.docs_history import page_share, sections

    page = ROOT / name
    share = page_share(page)
    dated = [f"line {s.first_line} {s.heading!r}: {', '.join(s.markers)}"
             for s in sections(page.read_text(encoding="utf-8")) if s.dated]
    assert share.share < MAX_DATED_SHARE, (
        f"{name}: {share.dated_lines} of {share.lines} lines in dated measurement sections "
        f"(python -m bench.docs_history --sections {name}); state the current figure with its command and a "
        f"'last measured' column, and leave the history to CHANGELOG.md and git: {dated}")
