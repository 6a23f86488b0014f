"""Planning: fingerprints, resolved drive paths and run/skip decisions for every stage of a workflow."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline import storage
from pipeline.declare import Partitioning, PartitionKey, StageDecl
from pipeline.fingerprint import drive_fingerprint, file_key, stable_hash, stage_fingerprint
from pipeline.store import data_root, dataset_dir
from pipeline.workflow import TEMPLATE, Workflow


@dataclass
class StagePlan:
    name: str
    decl: StageDecl
    fingerprint: str
    params: dict[str, Any]
    inputs: dict[str, tuple[str, str]]  # arg -> (dataset, fingerprint or "" when absent)
    outputs: dict[str, str]  # key -> dataset
    drives: dict[str, Path]  # drives this stage sees
    settings: dict[str, Any]
    committed: bool = False
    partitions: list[PartitionKey] | None = None  # None until known (dynamic partitioning)
    selected: bool = True
    # (dataset, fingerprint) of datasets this stage reads through templated paths (``${raw_drives}/...`` drives
    # and references) rather than declared inputs: it starts after their stages commit.
    path_inputs: set[tuple[str, str]] = field(default_factory=set)
    drive_scope: dict[str, str] = field(default_factory=dict)  # drive -> scope fingerprint (pipeline/reuse.py)
    ran: bool = False  # set when this run computed the stage (false: skipped as committed, or not selected)
    reused_partitions: int = 0  # partitions linked from committed work instead of computed (set by the run)

    @property
    def fp8(self) -> str:
        return self.fingerprint[:8]

    @property
    def decision(self) -> str:
        if not self.selected:
            return "not selected"
        return "skip (committed)" if self.committed else "run"


@dataclass
class Plan:
    workflow: Workflow
    root: Path  # a local folder: the root itself, or an object-store root's local copy in this process's scratch
    stages: dict[str, StagePlan] = field(default_factory=dict)
    uri: str = ""  # the root as named: the folder, or s3://BUCKET/PREFIX

    def __post_init__(self) -> None:
        self.uri = self.uri or str(self.root)


def _resolve_template(text: str, root: Path, producer_fp: dict[str, str], base_dir: Path
                      ) -> tuple[Path, str | None]:
    """Expand ${dataset} to that dataset's committed artifact directory; returns (path, fingerprint basis).
    A path without a template that is relative resolves against ``base_dir`` (the workflow file's folder)."""
    basis = None
    for ds in TEMPLATE.findall(text):
        if ds not in producer_fp:  # a stage upstream of the producer: the path is not available to it
            continue
        fp = producer_fp[ds]
        artifacts = storage.artifacts_dir(dataset_dir(root, ds, fp), PartitionKey().label)
        text = text.replace("${" + ds + "}", str(artifacts))
        basis = f"{ds}:{fp}"
    path = Path(text).expanduser()
    return (path if path.is_absolute() else base_dir / path), basis


def _local_templates_only(droot, text: str) -> None:
    """A drive or reference path into a committed dataset (``${dataset}``) is a local path: refused on an
    object-store root, whose datasets a task reads through the store (ConfigError naming the template)."""
    if droot.remote:
        from pipeline.errors import ConfigError

        raise ConfigError(droot.uri, [f"{text}: a drive or reference path into a dataset (${{dataset}}) is not "
                                      "supported on an object-store root; build into a local root, or name the "
                                      "drive's own files"])


def _reference_key(text: str | None, path: Path | None, basis: str | None) -> Any:
    """A reference trajectory in a fingerprint, without its location: the template and the fingerprint of the
    dataset it points into, else the file's content."""
    if text is None:
        return None
    if basis is not None:
        return {"template": text, "basis": basis}
    return file_key(path) if path is not None and path.is_file() else {"missing": Path(text).name}


def make_plan(workflow: Workflow, root: Path, only: list[str] | None = None) -> Plan:
    """Fingerprints and decisions. Nothing that names a location enters a fingerprint (the root, absolute drive
    or reference paths): a moved root or drive folder keeps its committed work."""
    droot = data_root(root if storage.uri_scheme(root) else Path(root).resolve())
    root = droot.local
    plan = Plan(workflow, root, uri=droot.uri)
    dataset_fp: dict[str, str] = {}
    dataset_scope: dict[str, dict[str, str]] = {}  # dataset -> drive -> scope fingerprint (drive-scoped work)
    base_settings = workflow.settings(droot.uri)
    drive_fp_cache: dict[Path, str] = {}
    for name, decl in workflow.stages.items():
        # Resolve drives and references with the fingerprints of upstream producers known so far.
        drives: dict[str, Path] = {}
        drive_fps: dict[str, str] = {}
        bases: set[str] = set()
        for d in workflow.spec.drives:
            if decl.drive_role and d.role != decl.drive_role:
                continue
            if TEMPLATE.search(d.path):
                _local_templates_only(droot, d.path)
                path, basis = _resolve_template(d.path, root, dataset_fp, workflow.base_dir)
                drive_fps[d.name] = stable_hash({"template": d.path, "basis": basis})
                bases.add(basis)
            elif storage.uri_scheme(d.path) is not None:  # a drive in a bucket: tasks fetch it (pipeline.drive_store)
                from pipeline.drive_store import remote_drive_fingerprint

                path = Path(storage.normalise_uri(d.path))
                if path not in drive_fp_cache:
                    drive_fp_cache[path] = remote_drive_fingerprint(d.path)
                drive_fps[d.name] = drive_fp_cache[path]
                drives[d.name] = path
                continue
            else:
                path = workflow.resolve(d.path)
                if path not in drive_fp_cache:
                    drive_fp_cache[path] = drive_fingerprint(path)
                drive_fps[d.name] = drive_fp_cache[path]
            drives[d.name] = path.resolve()
        settings = dict(base_settings)
        for d in workflow.spec.drives:
            if d.reference and TEMPLATE.search(d.reference):
                _local_templates_only(droot, d.reference)
        refs = {d.name: _resolve_template(d.reference, root, dataset_fp, workflow.base_dir) if d.reference else
                (None, None) for d in workflow.spec.drives}
        settings["references"] = {n: (str(p) if p is not None else None) for n, (p, _) in refs.items()}
        bases.update(b for _, b in refs.values())
        keys = decl.settings_keys if decl.settings_keys is not None else set(settings) - {"root"}
        fp_settings = {k: settings[k] for k in sorted(keys) if k in settings}
        if "references" in fp_settings:
            fp_settings["references"] = {d.name: _reference_key(d.reference, *refs[d.name])
                                         for d in workflow.spec.drives}
        inputs = {arg: (ds, dataset_fp.get(ds, "")) for arg, ds in decl.inputs.items()}
        params = workflow.params[name].model_dump(mode="json")
        fp = stage_fingerprint(stage=name, code_version=decl.code_version, params=params,
                               inputs={a: f for a, (_, f) in inputs.items()},
                               drives=drive_fps if decl.uses_drives or decl.partition == Partitioning.PER_DRIVE
                               else {}, settings=fp_settings)
        scope: dict[str, str] = {}  # with a pinned frame, per-drive partitions are reused across drive sets
        if decl.partition in (Partitioning.PER_DRIVE, Partitioning.PER_SCAN_CHUNK) and not decl.plan:
            from pipeline.reuse import drive_scope_fingerprints

            scope = drive_scope_fingerprints(
                frame_pinned=bool(base_settings.get("enu_origin")), stage=name, code_version=decl.code_version,
                params=params, settings=fp_settings,
                drive_fps=drive_fps, roles={d.name: d.role for d in workflow.spec.drives},
                input_scopes={a: (dataset_scope.get(ds) if f else {}) for a, (ds, f) in inputs.items()})
        for ds in decl.outputs.values():
            dataset_fp[ds] = fp
            dataset_scope[ds] = scope if scope else None
        committed = all(droot.manifest(ds, fp) is not None for ds in decl.outputs.values())
        sp = StagePlan(name, decl, fp, params, inputs, dict(decl.outputs), drives, settings, committed,
                       selected=(only is None or name in only), drive_scope=scope,
                       path_inputs={tuple(b.split(":", 1)) for b in bases if b})
        if decl.partition == Partitioning.SINGLE:
            sp.partitions = [PartitionKey()]
        elif decl.partition == Partitioning.PER_DRIVE and not decl.plan:
            sp.partitions = [PartitionKey(drive=n) for n in drives]
        plan.stages[name] = sp
    return plan


def describe_plan(plan: Plan) -> list[dict[str, Any]]:
    rows = []
    for sp in plan.stages.values():
        if sp.partitions is not None:
            parts = f"{len(sp.partitions)} ({sp.decl.partition.value})"
        else:
            src = sp.decl.partition_source
            parts = f"dynamic ({sp.decl.partition.value}" + (f" of {sp.inputs[src][0]})" if src else ")")
        rows.append({"stage": sp.name, "fingerprint": sp.fingerprint[:16], "partitions": parts,
                     "decision": sp.decision, "outputs": ", ".join(sp.outputs.values())})
    return rows
