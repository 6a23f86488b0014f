"""The docs are reference pages: no scratch path (/tmp) anywhere, and every parameter table's default is the code's
default (a page that says 0.15 where the code says 0.25 fails here)."""
from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted((ROOT / "docs").glob("*.md")) + [ROOT / "README.md", ROOT / "CHANGELOG.md"]
# pages with parameter tables (| `name` | default | ...) -> the stages whose params they document
PARAM_PAGES = {"corners.md": ("corners",), "posegraph.md": ("odometry", "posegraph"), "evaluation.md": ("evaluate",)}
ROW = re.compile(r"^\|\s*(`[a-z0-9_]+`(?:\s*/\s*`[a-z0-9_]+`)*)\s*\|\s*([^|]+?)\s*\|")


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_no_scratch_paths(page):
    hits = [f"{page.name}:{n}" for n, line in enumerate(page.read_text().splitlines(), 1) if "/tmp" in line]
    assert not hits, f"/tmp paths in docs (use runs/... or a bench command): {hits}"


def _value(text: str):
    v = yaml.safe_load(text)
    return v.lower() if isinstance(v, str) else v


def _same(doc_value, code_value) -> bool:
    if hasattr(code_value, "value"):  # enums
        code_value = code_value.value
    if isinstance(code_value, str):
        return str(doc_value).lower() == code_value.lower()
    if isinstance(code_value, (list, tuple)):
        return list(doc_value or []) == list(code_value)
    if isinstance(code_value, bool) or isinstance(doc_value, bool):
        return doc_value is code_value
    return doc_value == pytest.approx(code_value, rel=1e-12, abs=0.0)


def _rows(page: Path, stages: tuple[str, ...]):
    """(stages the row belongs to, name, default text): the stage named in the nearest heading above the table,
    else every stage of the page."""
    owners = stages
    for line in page.read_text().splitlines():
        if line.startswith("#"):
            named = tuple(s for s in stages if re.search(rf"\b{s}\b", line))
            owners = named or stages
        m = ROW.match(line)
        if m:
            names = [n.strip(" `") for n in m.group(1).split("/")]
            values = [v.strip() for v in m.group(2).split(" / ")] if len(names) > 1 else [m.group(2).strip()]
            if len(values) == len(names):
                for name, value in zip(names, values):
                    yield owners, name, value


@pytest.mark.parametrize("page_name", sorted(PARAM_PAGES))
def test_param_table_defaults_match_the_code(page_name):
    from pipeline.registry import get_stage

    checked, wrong = 0, []
    for stages, name, text in _rows(ROOT / "docs" / page_name, PARAM_PAGES[page_name]):
        owners = [m for m in (get_stage(s).params for s in stages) if name in m.model_fields]
        if not owners:
            continue
        for model in owners:
            default = model.model_fields[name].get_default(call_default_factory=True)
            checked += 1
            if not _same(_value(text), default):
                wrong.append(f"{name}: docs {text!r}, {model.__name__} {default!r}")
    assert checked >= 10, f"{page_name}: only {checked} parameter rows recognised; did the table format change?"
    assert not wrong, f"{page_name}: parameter defaults differ from the code: {wrong}"
