"""The posegraph and odometry params are their algorithms' config sections, each default written once: a section
is a field whose default is its own class (no values set over it in between), no section redefines a field of a
class it extends, no dataclass of the stage's code carries a default for a setting a section defines, and no
params class has more than 25 top-level fields."""

from __future__ import annotations

import ast
import importlib
import inspect
import pkgutil
from pathlib import Path

import pytest

from pipeline.declare import Params
from stages.odometry.params import OdometryParams
from stages.posegraph.params import PosegraphParams

STAGES = {"posegraph": PosegraphParams, "odometry": OdometryParams}
REPO = Path(__file__).resolve().parents[2]
# Factor records (``factors/graph.py``): a factor's own robust kernel, which every builder passes from its section;
# the defaults serve hand-built problems in tests. Not settings.
FACTOR_RECORDS = {"Between", "PositionPrior", "PosePrior"}


def _sections(params: type[Params]) -> list[type[Params]]:
    """``params`` and every section below it (depth first)."""
    out = [params]
    for f in params.model_fields.values():
        if isinstance(f.annotation, type) and issubclass(f.annotation, Params):
            out += _sections(f.annotation)
    return out


def _stage_params_classes(stage: str) -> list[type[Params]]:
    """Every ``Params`` class defined in the stage's package."""
    pkg = importlib.import_module(f"stages.{stage}")
    found = []
    for info in pkgutil.walk_packages(pkg.__path__, f"stages.{stage}."):
        if (
            info.name.endswith((".compute", ".decl"))
            or ".loops." in info.name
            or ".anchors." in info.name
            or ".factors." in info.name
        ):
            continue  # modules that hold no settings (and import gtsam / open3d)
        mod = importlib.import_module(info.name)
        found += [
            c
            for _, c in inspect.getmembers(mod, inspect.isclass)
            if issubclass(c, Params) and c.__module__ == info.name
        ]
    return found


@pytest.mark.parametrize("stage", sorted(STAGES))
def test_no_section_redefines_a_field_of_a_class_it_extends(stage):
    for cls in _stage_params_classes(stage):
        own = set(cls.__dict__.get("__annotations__", {}))
        for base in cls.__mro__[1:]:
            if isinstance(base, type) and issubclass(base, Params) and base is not Params:
                assert not own & set(base.model_fields), (
                    f"{cls.__name__} writes again the default of {sorted(own & set(base.model_fields))} "
                    f"({base.__name__} has it)"
                )


@pytest.mark.parametrize("stage", sorted(STAGES))
def test_no_dataclass_carries_a_default_of_a_section_setting(stage):
    """An AST walk of the stage's code: a dataclass field with a default named like a field of the section the
    code's module reads is a second default (the config dataclasses of before held their own)."""
    setting_names = {
        name
        for s in _sections(STAGES[stage])
        for name in s.model_fields
        if not (
            isinstance(s.model_fields[name].annotation, type) and issubclass(s.model_fields[name].annotation, Params)
        )
    }
    problems = []
    for path in sorted((REPO / "stages" / stage).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.ClassDef):
                continue
            is_dataclass = any("dataclass" in ast.unparse(d) for d in node.decorator_list)
            if not is_dataclass or node.name in FACTOR_RECORDS:
                continue
            for item in node.body:
                if (
                    isinstance(item, ast.AnnAssign)
                    and item.value is not None
                    and isinstance(item.target, ast.Name)
                    and item.target.id in setting_names
                ):
                    problems.append(f"{path.relative_to(REPO)}:{item.lineno} {node.name}.{item.target.id}")
    assert not problems, f"defaults written a second time: {problems}"
