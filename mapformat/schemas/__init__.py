"""JSON Schemas (draft 2020-12) of the map format's JSON documents, shipped with the package.

    validate(doc, "manifest")       # manifest.json of a version
    validate(doc, "changelog")      # changelog.json of a version
    validate(doc, "bundle")         # bundle.json of a delta bundle (mapformat/bundle.py)
    validate(doc, "map-identity")   # ROOT/maps/NAME/map.json

The files (``{name}.schema.json`` beside this module) are the machine-readable twin of docs/map-format.md; a reader
in another language validates against them with any draft 2020-12 validator. ``validate`` raises
``MapFormatError`` naming the document, the failing path and the rule (every problem, sorted by path).
"""
from __future__ import annotations

import json
from functools import lru_cache
from importlib import resources
from typing import Any

from pipeline.errors import MapFormatError

NAMES = ("manifest", "changelog", "bundle", "map-identity")


@lru_cache(maxsize=None)
def schema(name: str) -> dict[str, Any]:
    """The parsed schema ``name`` (one of NAMES)."""
    if name not in NAMES:
        raise KeyError(f"no schema {name!r}; have {', '.join(NAMES)}")
    return json.loads(resources.files(__name__).joinpath(f"{name}.schema.json").read_text(encoding="utf-8"))


@lru_cache(maxsize=None)
def _validator(name: str):
    from jsonschema import Draft202012Validator

    doc = schema(name)
    Draft202012Validator.check_schema(doc)
    return Draft202012Validator(doc)


def problems(doc: Any, name: str) -> list[str]:
    """Every way ``doc`` breaks schema ``name``: 'path: message' lines, sorted; empty when it conforms."""
    out = []
    for err in _validator(name).iter_errors(doc):
        path = "/".join(str(p) for p in err.absolute_path) or "(top)"
        out.append(f"{path}: {err.message}")
    return sorted(out)


def validate(doc: Any, name: str, where: str = "document") -> None:
    """Raise ``MapFormatError`` when ``doc`` does not conform to schema ``name`` (``where`` names the file)."""
    found = problems(doc, name)
    if found:
        shown = "; ".join(found[:5]) + (f"; ... {len(found) - 5} more" if len(found) > 5 else "")
        raise MapFormatError(f"{where}: does not conform to the {name} schema ({len(found)} problem(s)): {shown}")
