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
