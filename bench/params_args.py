"""Params overrides written on a bench's command line as dotted keys (``checks.min_layers=4``), turned into the
nested mapping a stage's params take (``{"checks": {"min_layers": 4}}``)."""

from __future__ import annotations

import copy
from typing import Any, Mapping


def nested(dotted: Mapping[str, Any], base: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """``base`` (a params dump, default empty) with each ``"section.key": value`` of ``dotted`` set in place."""
    out: dict[str, Any] = copy.deepcopy(dict(base or {}))
    for key, value in dotted.items():
        *path, last = key.split(".")
        node = out
        for part in path:
            node = node.setdefault(part, {})
        node[last] = value
    return out


def merged(base: Mapping[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with ``override`` laid over it, section by section (a nested mapping merges, a value replaces)."""
    out = copy.deepcopy(dict(base))
    for key, value in override.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = merged(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out
