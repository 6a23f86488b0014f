"""Every YAML example in docs/drive-file.md is a valid drive file (schema and semantic checks), and every key
of the drive-file schema is documented there."""
from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from stages.ingest.drive_file import DriveSpec, _semantic_problems

DOC = Path(__file__).resolve().parents[1] / "docs" / "drive-file.md"


def _examples() -> list[dict]:
    return [yaml.safe_load(block) for block in re.findall(r"```yaml\n(.*?)```", DOC.read_text(), re.S)]


def test_every_example_is_a_valid_drive_file():
    examples = _examples()
    assert len(examples) >= 4
    for doc in examples:
        spec = DriveSpec.model_validate(doc)
        assert _semantic_problems(spec) == [], doc["name"]


def _keys(model, prefix: str = "") -> set[str]:
    out = set()
    for name, f in model.model_fields.items():
        if f.exclude:
            continue
        sub = getattr(f.annotation, "__args__", (f.annotation,))
        nested = [a for a in sub if isinstance(a, type) and hasattr(a, "model_fields")]
        if nested:
            out |= _keys(nested[0], f"{prefix}{name}.")
        else:
            out.add(prefix + name)
    return out


def test_every_schema_key_is_documented():
    text = DOC.read_text()
    missing = [k for k in sorted(_keys(DriveSpec)) if f"`{k}`" not in text and f".{k.split('.')[-1]}`" not in text]
    assert missing == [], f"keys missing from docs/drive-file.md: {missing}"


def test_the_scans_format_row_is_the_scan_format_table():
    from stages.ingest.scan_format_table import SCAN_FORMATS

    row = next(line for line in DOC.read_text().splitlines() if line.startswith("| `scans.format` |"))
    cells = [c.strip() for c in re.split(r"(?<!\\)\|", row)[1:-1]]
    assert cells[1] == r" \| ".join(f"`{f.name}`" for f in SCAN_FORMATS)
    assert cells[4] == "; ".join(f.layout for f in SCAN_FORMATS)


def test_every_format_of_the_table_has_its_reader_and_is_a_drive_file_value():
    import pydantic

    from stages.ingest import scan_formats
    from stages.ingest.drive_file import ScansSpec
    from stages.ingest.scan_format_table import SCAN_FORMATS

    for f in SCAN_FORMATS:
        assert callable(getattr(scan_formats, f.reader)), f.reader
        assert ScansSpec(folder="s", format=f.name).format == f.name
    with pytest.raises(pydantic.ValidationError) as exc:
        ScansSpec(folder="s", format="ply")
    assert all(f"'{f.name}'" in str(exc.value) for f in SCAN_FORMATS)
