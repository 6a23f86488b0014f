"""The data catalog: what datasets exist, with schema, kind, partitioning and versioning.

``data_catalog/*.yaml`` holds ``datasets: {name: {schema, kind, partitioning, versioning, doc}}``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from pipeline.errors import ConfigError
from pipeline.safe_yaml import load_yaml_file

PARTITION_COLUMNS = ("drive", "chunk", "tile_i", "tile_j")


class DatasetSpec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    schema_ref: str | None = Field(default=None, alias="schema")  # registry name or "module:ATTR"
    kind: Literal["table", "artifacts"] = "table"
    partitioning: tuple[str, ...] = ()
    versioning: Literal["fingerprint", "published"] = "fingerprint"
    doc: str = ""


@dataclass(frozen=True)
class Catalog:
    datasets: dict[str, DatasetSpec]
    sources: tuple[str, ...]

    def schema(self, name: str):
        return resolve_schema(self.datasets[name].schema_ref)


def resolve_schema(ref: str | None):
    """A schema reference: a name in ``schemas.SCHEMAS`` or ``module:ATTR`` (None for artifact datasets)."""
    import pyarrow as pa

    from pipeline.declare import resolve
    from schemas import schema_of

    if ref is None:
        return None
    if ":" in ref and ref.partition(":")[0] not in _trusted_schema_modules():
        raise ValueError(f"schema reference {ref!r}: 'module:ATTR' may only name a module of the schemas package "
                         "(e.g. schemas.registry:SCANS_RAW) or of a registered stage; use a registry name otherwise")
    obj = resolve(ref) if ":" in ref else schema_of(ref)
    if not isinstance(obj, pa.Schema):
        raise TypeError(f"schema reference {ref!r} is a {type(obj).__name__}, expected a pyarrow.Schema")
    return obj


def _trusted_schema_modules() -> set[str]:
    """Modules a catalog may import a schema from: ``schemas`` and its submodules, and the modules that
    declare registered stages (already trusted code). Any other ``module:ATTR`` would let a YAML file
    import arbitrary code."""
    import pkgutil

    import schemas
    from pipeline.registry import load_stages

    mods = {"schemas"} | {f"schemas.{m.name}" for m in pkgutil.iter_modules(schemas.__path__)}
    for decl in load_stages().values():
        for ref in (decl.compute, getattr(decl, "cli", None)):
            if isinstance(ref, str) and ref:
                mods.add(ref.partition(":")[0])
    return mods


def _yaml_files(paths: list[Path]) -> list[Path]:
    files: list[Path] = []
    for p in paths:
        files += sorted(p.glob("*.yaml")) if p.is_dir() else [p]
    return files


def load_catalog(paths: list[Path]) -> Catalog:
    """Load and validate every catalog file; every problem is reported in one ConfigError."""
    problems: list[str] = []
    datasets: dict[str, DatasetSpec] = {}
    files = _yaml_files(paths)
    for file in files:
        try:
            doc = load_yaml_file(file) or {}
        except ConfigError as exc:
            problems += [f"{file}: {p}" for p in exc.problems]
            continue
        if not isinstance(doc, dict):
            problems.append(f"{file}: expected a mapping with a 'datasets' key; got {type(doc).__name__}")
            continue
        unknown = set(doc) - {"datasets"}
        if unknown:
            problems.append(f"{file}: unknown top-level keys {sorted(unknown)}; expected only 'datasets'")
        for name, raw in (doc.get("datasets") or {}).items():
            try:
                spec = DatasetSpec.model_validate(raw or {})
            except ValidationError as exc:
                for err in exc.errors():
                    loc = ".".join(str(x) for x in err["loc"])
                    problems.append(f"{file}: dataset {name!r}: {loc}: {err['msg']}")
                continue
            if name in datasets:
                problems.append(f"{file}: dataset {name!r} is declared twice")
            bad = [c for c in spec.partitioning if c not in PARTITION_COLUMNS]
            if bad:
                problems.append(f"{file}: dataset {name!r}: partition columns {bad} not among {PARTITION_COLUMNS}")
            datasets[name] = spec
    if not files:
        problems.append(f"no catalog files found in {[str(p) for p in paths]}")
    catalog = Catalog(datasets, tuple(str(f) for f in files))
    for name, spec in datasets.items():
        if spec.kind == "table":
            try:
                schema = catalog.schema(name)
            except Exception as exc:  # noqa: BLE001 - reported as a config problem
                problems.append(f"dataset {name!r}: schema {spec.schema_ref!r} cannot be loaded: {exc}")
                continue
            if schema is None:
                problems.append(f"dataset {name!r}: a table dataset needs a schema")
            elif any(c not in schema.names for c in spec.partitioning):
                problems.append(f"dataset {name!r}: partition columns {list(spec.partitioning)} "
                                f"must be fields of its schema {spec.schema_ref!r}")
    if problems:
        raise ConfigError(f"data catalog ({', '.join(str(p) for p in paths)})", problems)
    return catalog
