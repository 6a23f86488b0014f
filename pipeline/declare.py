"""Stage declarations: a stage is data (name, summary, code version, inputs, outputs, params, partitioning)
plus a ``compute`` referenced by import path so that declaring a stage imports nothing heavy.

Convention: ``compute(ctx: StageContext) -> Mapping[str, pa.Table | Iterable[pa.Table]]`` keyed by output key.
An iterable of tables is written piece by piece (streaming); each piece must hold one value per partition
column of its dataset.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, ClassVar, Mapping

from pydantic import BaseModel, ConfigDict, model_validator

if TYPE_CHECKING:  # pragma: no cover
    import pyarrow as pa


class Params(BaseModel):
    """Base of every stage's params and of their sections: defaults in code, immutable, unknown keys refused with
    the nearest known name, and a key that moved (``renamed``: old key -> its place now, e.g. ``"loops.radius_m"``)
    refused with the place to write it. Sections are fields whose type is itself a ``Params``."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    renamed: ClassVar[Mapping[str, str]] = {}

    def updated(self, values: Mapping[str, Any]) -> "Params":
        """A copy with ``values`` over this one's values (dotted keys or nested mappings, as ``nested`` reads them:
        ``{"loops.radius_m": 20.0}``), validated as the workflow's keys are."""
        return type(self).model_validate(merged(self.model_dump(), nested(values)))

    @model_validator(mode="before")
    @classmethod
    def _refuse_unknown_keys(cls, data: Any) -> Any:
        if isinstance(data, Mapping):
            problems = [unknown_key_problem(cls, key) for key in data if key not in cls.model_fields]
            if problems:
                raise ValueError("; ".join(problems))
        return data


def unknown_key_problem(params: type[Params], key: Any) -> str:
    """One line for a key ``params`` does not have: where it moved, or the nearest known key."""
    if key in params.renamed:
        return f"{key!r} has moved: write it as {params.renamed[key]!r}"
    from pipeline.names import suggest

    known = sorted(params.model_fields)
    return f"unknown key {key!r}{suggest(str(key), known)}; known: {', '.join(known) or '(none)'}"


def nested(values: Mapping[str, Any]) -> dict[str, Any]:
    """``values`` with each dotted key as nested mappings: ``{"loops.radius_m": 20, "loops": {"stride_m": 4}}`` ->
    ``{"loops": {"radius_m": 20, "stride_m": 4}}`` (merged as ``merged`` does, in the given order; the workflow's
    ``params`` and ``--params`` files may name a section's key either way)."""
    out: dict[str, Any] = {}
    for key, value in values.items():
        if isinstance(key, str) and "." in key:
            head, _, rest = key.partition(".")
            value, key = {rest: value}, head
        out = merged(out, {key: nested(value) if isinstance(value, Mapping) else value})
    return out


def merged(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with ``over``'s values over it, section by section (a mapping in both is merged, any other value of
    ``over`` replaces ``base``'s)."""
    out = dict(base)
    for key, value in over.items():
        out[key] = merged(out[key], value) if isinstance(out.get(key), Mapping) and isinstance(value, Mapping) \
            else value
    return out


class Partitioning(str, Enum):
    SINGLE = "single"
    PER_DRIVE = "per_drive"
    PER_SCAN_CHUNK = "per_scan_chunk"
    PER_TILE = "per_tile"


@dataclass(frozen=True, order=True)
class PartitionKey:
    """Which slice of the work one task does. Fields unused by a partitioning stay None."""

    drive: str | None = None
    chunk: int | None = None
    tile_i: int | None = None
    tile_j: int | None = None

    @property
    def label(self) -> str:
        parts = []
        if self.drive is not None:
            parts.append(self.drive.replace("_", ""))
        if self.chunk is not None:
            parts.append(f"chunk{self.chunk:04d}")
        if self.tile_i is not None:
            parts.append(f"tile{self.tile_i:+05d}{self.tile_j:+05d}")
        return "-".join(parts) or "all"

    def as_dict(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items() if v is not None}


@dataclass(frozen=True)
class StageDecl:
    name: str
    summary: str
    # a string, or a function giving it (a digest of the stage's code: computed at the first read, not at import,
    # so ``--help`` and worker processes that never fingerprint do not pay for it)
    code_version: str | Callable[[], str]
    inputs: Mapping[str, str]  # argument -> dataset name
    outputs: Mapping[str, str]  # output key -> dataset name
    params: type[Params]
    partition: Partitioning
    compute: str  # "module:function", imported only when the stage runs
    # Which input argument's committed partitions define this stage's partitions (per_scan_chunk / per_tile).
    partition_source: str | None = None
    # Per-drive stages read the workflow's drives (drive.yaml paths) rather than a dataset.
    uses_drives: bool = False
    # Optional "module:function" that enumerates partitions: f(ctx: PlanContext) -> list[PartitionKey].
    plan: str | None = None
    # Optional "module" whose register(app) adds stage-specific CLI commands (imports heavy code lazily).
    cli: str | None = None
    optional_inputs: frozenset[str] = field(default_factory=frozenset)
    # Per-drive stages: which drives they run on ("map", "eval" or None for all the workflow's drives).
    drive_role: str | None = None
    # Workflow settings that affect the output (part of the fingerprint); None means all of them.
    settings_keys: frozenset[str] | None = None
    # Optional "module:function" run before any stage of a run starts: f(drives: dict[name, Path], settings: dict)
    # raises a CornermapError when the run cannot succeed on these inputs (a drive nothing places in the map's
    # frame); drives whose files do not exist yet (written by an earlier stage) are not passed.
    preflight: str | None = None

    def load_compute(self) -> Callable[["StageContext"], Mapping[str, Any]]:
        return resolve(self.compute)

    def __getattribute__(self, name: str) -> Any:
        value = object.__getattribute__(self, name)
        if name == "code_version" and callable(value):
            value = str(value())
            object.__setattr__(self, "code_version", value)  # once: the code does not change under a process
        return value


def source_digest(*modules: str, follow: tuple[str, ...] = ()) -> str:
    """The first 12 hex digits of the sha256 of the code of ``modules`` (a package: every ``.py`` file below it),
    found without importing them. ``follow``: module prefixes (``"stages.common"``) whose modules are digested too
    wherever a digested file imports one, and so on through what those import. A stage whose code_version includes
    the digest of its own package with ``follow`` on the shared code re-runs when any code it runs changes, whoever
    changes it, and only then (the reuse of per-drive work across rebuilds, ``pipeline.reuse``, holds while the code
    does). Each file counts by its syntax tree without docstrings: an edit of prose or comments re-runs nothing."""
    import hashlib

    h = hashlib.sha256()
    for name, path in sorted(_code_files(modules, follow).items()):
        h.update(name.encode())
        h.update(_parsed(path)[1])
    return h.hexdigest()[:12]


def _module_files(name: str) -> dict[str, Path]:
    """{qualified name: file} of module ``name`` (a package: every ``.py`` file below it); ImportError if none.
    Found on disk below its top-level package, so no parent package's ``__init__`` is run."""
    import importlib.util

    top, *rest = name.split(".")
    spec = importlib.util.find_spec(top)
    if spec is None or spec.origin is None:
        raise ImportError(f"source_digest: no module {name!r}")
    base = Path(spec.origin).parent if Path(spec.origin).name == "__init__.py" else None
    if base is None:
        if rest:
            raise ImportError(f"source_digest: no module {name!r}")
        return {name: Path(spec.origin)}
    folder = base.joinpath(*rest)
    if (folder / "__init__.py").is_file():
        return {".".join([name, *f.relative_to(folder).with_suffix("").parts]): f for f in sorted(folder.rglob("*.py"))}
    if rest and folder.with_suffix(".py").is_file():
        return {name: folder.with_suffix(".py")}
    raise ImportError(f"source_digest: no module {name!r}")


_PARSED: dict[Path, tuple[set[str], bytes]] = {}  # file -> (absolute modules it imports, code without docstrings)


def _parsed(path: Path) -> tuple[set[str], bytes]:
    """The absolute module names a file imports (``from a.b import c`` gives ``a.b`` and ``a.b.c``) and its syntax
    tree without docstrings (line numbers and comments are not in it); parsed once per process."""
    import ast

    if path not in _PARSED:
        tree = ast.parse(path.read_bytes(), filename=str(path))
        imports: set[str] = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                imports.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                imports.add(node.module)
                imports.update(f"{node.module}.{a.name}" for a in node.names)
            body = getattr(node, "body", None)
            if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and body \
                    and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
                    and isinstance(body[0].value.value, str):
                node.body = body[1:] or [ast.Pass()]
        _PARSED[path] = (imports, ast.dump(tree).encode())
    return _PARSED[path]


def _code_files(modules: tuple[str, ...], follow: tuple[str, ...]) -> dict[str, Path]:
    files: dict[str, Path] = {}
    todo = list(modules)
    seen: set[str] = set()
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        try:
            found = _module_files(name)
        except ImportError:
            if name in modules:
                raise
            continue  # ``from a.b import c`` where c is a function of a.b, not a module
        for qual, path in found.items():
            if qual in files:
                continue
            files[qual] = path
            todo += [m for m in _parsed(path)[0] if any(m == p or m.startswith(p + ".") for p in follow)]
    return files


def resolve(ref: str) -> Any:
    module, _, attr = ref.partition(":")
    obj = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


@dataclass
class StageContext:
    """Everything one partition task sees. Built inside the task; holds only plain data and readers."""

    stage: str
    partition: PartitionKey
    params: Params
    inputs: "InputReader"
    drives: Mapping[str, Path]  # drive name -> drive.yaml path (resolved)
    settings: Mapping[str, Any]  # workflow-level settings (map name, ENU origin, tile size, ...)
    scratch_dir: Path  # private, deleted after the task
    artifact_dirs: Mapping[str, Path]  # output key -> staging dir for non-tabular files of this partition
    # Inner steps of a long partition ("loops verified", n, total; counts None for a step that cannot count) -> the
    # run's progress display, where the partition runs in the process that shows it (no-op elsewhere).
    step_progress: Callable[[str, int | None, int | None], None] | None = None

    def report_step(self, step: str, done: int | None = None, total: int | None = None) -> None:
        if self.step_progress is not None:
            self.step_progress(step, done, total)

    def artifact_dir(self, key: str) -> Path:
        path = self.artifact_dirs[key]
        path.mkdir(parents=True, exist_ok=True)
        return path

    def committed_artifact_dir(self, key: str) -> Path:
        """Where ``artifact_dir(key)`` will be once this partition commits (for messages and manifests)."""
        return self.artifact_dirs[key].parent / self.partition.label


class InputReader:
    """Reads committed input datasets of a stage. Implemented by the store; declared here for typing."""

    def read(self, arg: str, *, partition: PartitionKey | None = None, columns: list[str] | None = None,
             filters: Any = None) -> "pa.Table":  # pragma: no cover - interface
        raise NotImplementedError

    def read_in(self, arg: str, column: str, values: Any, *, partition: PartitionKey | None = None,
                columns: list[str] | None = None) -> "pa.Table":  # pragma: no cover - interface
        """Rows whose ``column`` is one of ``values`` (a key lookup: only the data that can hold them is read)."""
        raise NotImplementedError

    def partitions(self, arg: str) -> list[PartitionKey]:  # pragma: no cover - interface
        raise NotImplementedError

    def metadata(self, arg: str) -> dict[str, Any]:  # pragma: no cover - interface
        raise NotImplementedError

    def artifact_dir(self, arg: str, partition: PartitionKey | None = None) -> Path:  # pragma: no cover
        raise NotImplementedError

    def has(self, arg: str) -> bool:  # pragma: no cover - interface
        raise NotImplementedError
