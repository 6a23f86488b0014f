"""Workflows: what to build (drives, stages, params, root, map name, scheduler), validated at load time.

Every problem in a workflow is collected and raised once, with "did you mean" for unknown names.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from pipeline.catalog import Catalog, load_catalog
from pipeline.declare import Params, StageDecl, merged, nested, unknown_key_problem
from pipeline.errors import ConfigError
from pipeline.names import name_problem, suggest
from pipeline.registry import load_stages, unknown_stage_problem
from pipeline.safe_yaml import load_yaml_file

TEMPLATE = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)\}")


class DriveEntry(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str
    path: str  # drive.yaml; may reference a dataset's artifacts as ${dataset}/...
    role: Literal["map", "eval"] = "map"
    reference: str | None = None  # truth trajectory (TUM) for evaluation


class WorkflowSpec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str
    description: str = ""
    catalog: list[str] | None = None  # default: the catalog shipped with the package
    root: str | None = None  # default: runs/<name> under the current directory
    map_name: str = "map"
    scheduler: str = "local"
    # the map's frame ({lat_deg, lon_deg, h_m}): carried, not interpreted; the stages that read it validate it
    # (``stages.common.geodesy.EnuOrigin.validate``); null: the stages choose it (ingest: the first GNSS fix)
    enu_origin: dict[str, float] | None = None
    tile_size_m: float | None = Field(None, gt=0)  # null: the stages' default (stages.common.tiling)
    # the map's area: a map drive with a GNSS fix farther from enu_origin is refused (exit 3); null: unbounded
    max_radius_m: float | None = Field(10_000.0, gt=0)
    hold_latest: bool = False  # publish the new map version without moving LATEST (a later gate moves it)
    # incremental pose graph (``cornermap rebuild``'s default): {fingerprint, version} of the published
    # poses_optimized dataset whose map drives keep their poses; null: every map drive solved jointly
    held_poses: dict[str, Any] | None = None
    # peak RSS a task may reach (MB): a stage over it is named after the run (summary and one line each);
    # null: no budget. 1536 MB is the design target of every stage (docs/performance.md).
    memory_budget_mb: float | None = Field(1536.0, gt=0)
    drives: list[DriveEntry] = []
    stages: list[str]
    params: dict[str, dict[str, Any]] = {}


@dataclass
class Workflow:
    spec: WorkflowSpec
    path: Path
    base_dir: Path  # the workflow file's folder: relative paths in the workflow resolve against it
    catalog: Catalog
    stages: dict[str, StageDecl]  # in execution order
    params: dict[str, Params]
    producers: dict[str, str] = field(default_factory=dict)  # dataset -> stage
    deps: dict[str, set[str]] = field(default_factory=dict)  # stage -> upstream stages

    @property
    def name(self) -> str:
        return self.spec.name

    def resolve(self, relative: str | Path) -> Path:
        """A path written in the workflow: absolute as is, relative against the workflow file's folder."""
        p = Path(relative).expanduser()
        return p if p.is_absolute() else self.base_dir / p

    def root_dir(self, override: str | Path | None = None) -> Path | str:
        """The output root: ``override`` (a command-line path, relative to the current directory, or an object-store
        URI ``s3://BUCKET/PREFIX``, returned as a str), else the workflow's ``root`` (relative to the workflow file),
        else ``runs/<workflow name>`` in the current directory."""
        if override is not None:
            from pipeline.storage import normalise_uri, uri_scheme

            if uri_scheme(override) is not None:
                return normalise_uri(override)
            return Path(override).expanduser().resolve()
        if self.spec.root:
            from pipeline.storage import uri_scheme

            if uri_scheme(self.spec.root) is not None:
                raise ConfigError(str(self.path), [f"root: {self.spec.root} is a URI; a workflow's root is a local "
                                                   "folder (object-store roots: docs/storage.md)"])
            return self.resolve(self.spec.root).resolve()
        return (Path.cwd() / "runs" / self.spec.name).resolve()

    def settings(self, root: Path) -> dict[str, Any]:
        s = self.spec
        return {
            "map_name": s.map_name,
            "enu_origin": dict(s.enu_origin) if s.enu_origin else None,
            "tile_size_m": s.tile_size_m,
            "map_drives": [d.name for d in s.drives if d.role == "map"],
            "eval_drives": [d.name for d in s.drives if d.role == "eval"],
            "root": str(root),
            "references": {d.name: d.reference for d in s.drives},
            "hold_latest": s.hold_latest,
            "max_radius_m": s.max_radius_m,
        } | ({"held_poses": dict(s.held_poses)} if s.held_poses else {})


def _pydantic_problems(where: str, exc: ValidationError) -> list[str]:
    out = []
    for err in exc.errors():
        loc = ".".join(str(x) for x in err["loc"])
        if err["type"] == "extra_forbidden":
            out.append(f"{where}: unknown key {loc!r}")
        else:
            msg = err["msg"].removeprefix("Value error, ")
            out.append(f"{where}: {loc}: {msg}" if loc else f"{where}: {msg}")
    return out


def validate_params(stage: StageDecl, overrides: dict[str, Any], where: str) -> tuple[Params | None, list[str]]:
    problems = [f"{where}: params of {stage.name!r}: {unknown_key_problem(stage.params, key)}"
                for key in overrides if key not in stage.params.model_fields]
    if problems:
        return None, problems
    try:
        return stage.params.model_validate(overrides), []
    except ValidationError as exc:
        return None, _pydantic_problems(f"{where}: params of {stage.name!r}", exc)


def load_workflow(path: Path | str, *, param_overrides: dict[str, dict[str, Any]] | None = None) -> Workflow:
    """Load a workflow file, or a packaged workflow by name (``demo``, ``map_rebuild``, ...), and validate it."""
    from pipeline.resources import packaged_catalog_dir, resolve_workflow

    path = resolve_workflow(path)
    where = str(path)
    raw = load_yaml_file(path)
    try:
        spec = WorkflowSpec.model_validate(raw or {})
    except ValidationError as exc:
        raise ConfigError(where, _pydantic_problems(where, exc)) from exc
    base_dir = path.resolve().parent
    problems: list[str] = []

    catalog_paths = [packaged_catalog_dir()] if spec.catalog is None else \
        [(base_dir / c) if not Path(c).is_absolute() else Path(c) for c in spec.catalog]
    try:
        catalog = load_catalog(catalog_paths)
    except ConfigError as exc:
        problems += exc.problems
        catalog = Catalog({}, ())

    registry = load_stages()
    stages: dict[str, StageDecl] = {}
    for name in spec.stages:
        if name not in registry:
            problems.append(unknown_stage_problem(name, registry))
        elif name in stages:
            problems.append(f"stage {name!r} is listed twice")
        else:
            stages[name] = registry[name]

    overrides = {k: nested(v) for k, v in spec.params.items()}
    for stage_name, extra in (param_overrides or {}).items():
        overrides[stage_name] = merged(overrides.get(stage_name, {}), nested(extra))
    params: dict[str, Params] = {}
    for stage_name, values in overrides.items():
        if stage_name not in stages:
            problems.append(f"params given for {stage_name!r}, which is not a stage of this workflow"
                            f"{suggest(stage_name, stages)}")
    for name, decl in stages.items():
        p, probs = validate_params(decl, overrides.get(name, {}), where)
        problems += probs
        if p is not None:
            params[name] = p

    producers: dict[str, str] = {}
    for name, decl in stages.items():
        for key, ds in decl.outputs.items():
            if catalog.datasets and ds not in catalog.datasets:
                problems.append(f"stage {name!r} output {key!r} writes dataset {ds!r}, which the catalog does not "
                                f"declare{suggest(ds, catalog.datasets)}")
            if ds in producers:
                problems.append(f"dataset {ds!r} is written by both {producers[ds]!r} and {name!r}")
            producers[ds] = name
    deps: dict[str, set[str]] = {name: set() for name in stages}
    for name, decl in stages.items():
        for arg, ds in decl.inputs.items():
            if catalog.datasets and ds not in catalog.datasets:
                problems.append(f"stage {name!r} input {arg!r} reads dataset {ds!r}, which the catalog does not "
                                f"declare{suggest(ds, catalog.datasets)}")
            elif ds in producers:
                deps[name].add(producers[ds])
            elif arg not in decl.optional_inputs:
                problems.append(f"stage {name!r} input {arg!r} needs dataset {ds!r}, which no stage of this "
                                f"workflow produces (add its producer to 'stages')")
    # Templated drive paths and references make the drive readers depend on the producing stage.
    for d in spec.drives:
        for text in (d.path, d.reference or ""):
            for ds in TEMPLATE.findall(text):
                if ds not in producers:
                    problems.append(f"drive {d.name!r}: ${{{ds}}} names no dataset produced by this workflow"
                                    f"{suggest(ds, producers)}")
                    continue
                for name, decl in stages.items():
                    if name != producers[ds]:
                        deps[name].add(producers[ds])
    names = [d.name for d in spec.drives]
    problems += [p for p in [name_problem(n, "drive") for n in names] + [name_problem(spec.map_name, "map")] if p]
    if len(set(names)) != len(names):
        problems.append(f"drive names must be unique; got {names}")
    if problems:
        raise ConfigError(f"workflow {path.name}", problems)
    order = _topological(deps, list(stages), where)
    return Workflow(spec, path, base_dir, catalog, {n: stages[n] for n in order}, params, producers, deps)


def _topological(deps: dict[str, set[str]], listed: list[str], where: str) -> list[str]:
    order: list[str] = []
    pending = {n: set(d) for n, d in deps.items()}
    while pending:
        ready = [n for n in listed if n in pending and not (pending[n] - set(order))]
        if not ready:
            raise ConfigError(where, [f"stages form a cycle: {sorted(pending)}"])
        for n in ready:
            order.append(n)
            del pending[n]
    return order
