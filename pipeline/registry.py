"""Discovers stage declarations through the ``cornermap.stages`` entry points (plus, for tests, the
``CORNERMAP_EXTRA_STAGES`` environment variable: comma-separated ``module:ATTR`` references).

Only declarations are imported here (they import nothing heavy), so ``cornermap --help`` stays fast.
"""
from __future__ import annotations

import logging
import os
from functools import lru_cache
from importlib.metadata import entry_points

from pipeline.declare import StageDecl, resolve
from pipeline.errors import ConfigError, UnknownNameError
from pipeline.names import name_problem, suggest

log = logging.getLogger(__name__)


@lru_cache(maxsize=1)
def load_stages() -> dict[str, StageDecl]:
    refs: list[tuple[str, str]] = [(ep.name, ep.value) for ep in entry_points(group="cornermap.stages")]
    extra = os.environ.get("CORNERMAP_EXTRA_STAGES", "")
    refs += [(ref.split(":")[-1], ref) for ref in extra.split(",") if ref.strip()]
    stages: dict[str, StageDecl] = {}
    problems: list[str] = []
    for name, ref in refs:
        try:
            decl = resolve(ref)
        except (ImportError, AttributeError) as exc:
            log.debug("stage %s (%s) is not available: %s", name, ref, exc)
            continue
        if not isinstance(decl, StageDecl):
            problems.append(f"entry point {ref} is a {type(decl).__name__}, expected a StageDecl")
            continue
        if decl.name in stages:
            problems.append(f"two stages are named {decl.name!r}")
        bad_name = name_problem(decl.name, "stage")
        if bad_name:
            problems.append(f"entry point {ref}: {bad_name}")
        stages[decl.name] = decl
    if problems:
        raise ConfigError("stage declarations", problems)
    return dict(sorted(stages.items()))  # by name; the app lists them in its own order (``register_stages``)


def unknown_stage_problem(name: str, stages) -> str:
    """One line for a stage name that is not among ``stages``: the nearest one and the known ones."""
    return f"unknown stage {name!r}{suggest(name, stages)}; known: {', '.join(stages)}"


def get_stage(name: str) -> StageDecl:
    stages = load_stages()
    if name not in stages:
        raise UnknownNameError(unknown_stage_problem(name, stages))
    return stages[name]
