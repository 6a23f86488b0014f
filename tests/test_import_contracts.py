"""The import contracts in pyproject.toml name every stage package, so a new stage cannot slip past them."""
from __future__ import annotations

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _stage_packages() -> set[str]:
    return {f"stages.{p.name}" for p in (ROOT / "stages").iterdir()
            if (p / "__init__.py").is_file() and p.name != "common"}


def _contracts() -> dict[str, dict]:
    doc = tomllib.loads((ROOT / "pyproject.toml").read_text())
    return {c["name"]: c for c in doc["tool"]["importlinter"]["contracts"]}


def test_every_stage_package_is_in_the_independence_contract():
    independence = [c for c in _contracts().values() if c["type"] == "independence"]
    assert len(independence) == 1
    assert set(independence[0]["modules"]) == _stage_packages()


def test_stages_common_and_mapformat_are_forbidden_every_stage_package():
    by_source = {tuple(c["source_modules"]): c for c in _contracts().values() if c["type"] == "forbidden"}
    for source in ("stages.common", "mapformat"):
        assert set(by_source[(source,)]["forbidden_modules"]) == _stage_packages(), source
    assert {"stages", "mapformat"} <= set(by_source[("pipeline",)]["forbidden_modules"])


def _product_packages() -> set[str]:
    """The installed top-level packages (pyproject's setuptools include) that hold Python modules."""
    doc = tomllib.loads((ROOT / "pyproject.toml").read_text())
    include = {p.rstrip("*") for p in doc["tool"]["setuptools"]["packages"]["find"]["include"]}
    return {p for p in include if (ROOT / p / "__init__.py").is_file() and any((ROOT / p).glob("*.py"))} - {
        "data_catalog", "workflows"}


def test_every_product_package_is_checked_by_the_linter():
    doc = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert _product_packages() <= set(doc["tool"]["importlinter"]["root_packages"])


def test_the_map_service_is_the_top():
    """The engine imports no map-service module (nor a stage, nor the map format); every other package of the
    product is forbidden the service, so the service can import them all without a circle."""
    by_source = {tuple(c["source_modules"]): c for c in _contracts().values() if c["type"] == "forbidden"}
    assert {"stages", "mapformat", "mapservice"} <= set(by_source[("pipeline",)]["forbidden_modules"])
    below = [c for c in _contracts().values() if c["type"] == "forbidden" and c["forbidden_modules"] == ["mapservice"]]
    assert len(below) == 1
    assert set(below[0]["source_modules"]) | {"pipeline"} == _product_packages() - {"mapservice"}
