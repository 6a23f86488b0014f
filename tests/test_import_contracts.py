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
