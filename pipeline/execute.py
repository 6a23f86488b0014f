"""The engine's tasks: one per partition (readable keys), then one commit per stage; ``pipeline.flow`` runs them.

Tasks receive and return small JSON-able manifests, never arrays, so the same graph runs on the synchronous,
threaded or multiprocessing scheduler, or on a dask.distributed cluster (``tcp://host:port``).
"""
from __future__ import annotations

import datetime as dt
import logging
import os
import shutil
import time
import uuid
from pathlib import Path, PurePosixPath
from typing import Any, Callable

from pipeline import storage
from pipeline.catalog import resolve_schema
from pipeline.declare import Partitioning, PartitionKey, StageContext
from pipeline.errors import CornermapError, StageError
from pipeline.memory import trim_threshold_mb
from pipeline.plan import Plan, StagePlan
from pipeline.reader import StoreInputReader, merge_part_extras
from pipeline.registry import get_stage
from pipeline.store import commit_artifacts, data_root, write_pieces

log = logging.getLogger(__name__)


def _task_spec(plan: Plan, sp: StagePlan) -> dict[str, Any]:
    catalog = plan.workflow.catalog
    ds_spec = lambda ds: catalog.datasets.get(ds)  # noqa: E731
    return {
        "stage": sp.name,
        "fingerprint": sp.fingerprint,
        "root": plan.uri,  # a local folder or an object-store URI: a task reads and writes through it
        "params": sp.params,
        "inputs": {a: list(v) for a, v in sp.inputs.items()},
        "input_schemas": {a: (ds_spec(ds).schema_ref if ds_spec(ds) else None) for a, (ds, _) in sp.inputs.items()},
        "outputs": {k: {"dataset": ds, "kind": ds_spec(ds).kind, "schema": ds_spec(ds).schema_ref,
                        "partitioning": list(ds_spec(ds).partitioning)} for k, ds in sp.outputs.items()},
        "drives": {k: str(v) for k, v in sp.drives.items()},
        "settings": sp.settings,
        "extra_stages": os.environ.get("CORNERMAP_EXTRA_STAGES", ""),
        "drive_scope": dict(sp.drive_scope),
        "trim_above_mb": trim_threshold_mb(plan.workflow.spec.memory_budget_mb),  # release_memory keeps the heap below
    }


_STEP_PROGRESS: dict[str, Callable[[str, int, int], None]] = {}  # stage -> display (this process only)


def _context(spec: dict[str, Any], partition: PartitionKey, scratch: Path,
             artifact_dirs: dict[str, Path], provisional: dict[str, list[str]] | None = None) -> StageContext:
    decl = get_stage(spec["stage"])
    reader = StoreInputReader(spec["root"], {a: tuple(v) for a, v in spec["inputs"].items()},
                              {a: resolve_schema(r) for a, r in spec["input_schemas"].items()}, provisional,
                              _ledger(spec))
    return StageContext(stage=spec["stage"], partition=partition, params=decl.params.model_validate(spec["params"]),
                        inputs=reader, drives={k: Path(v) for k, v in spec["drives"].items()},
                        settings=spec["settings"], scratch_dir=scratch, artifact_dirs=artifact_dirs,
                        step_progress=_STEP_PROGRESS.get(spec["stage"]))


def _ledger(spec: dict[str, Any]) -> Path | None:
    """The run's verification ledger (``pipeline.store.verify_file``), None outside a run. On an object-store root
    the ledger is named, not placed: each process keeps it in its own local copy of the root (the processes of one
    machine sharing a scratch folder share it; a worker on another machine has its own)."""
    name = spec.get("verified_ledger")
    if not name:
        return None
    droot = data_root(spec["root"])
    return storage.tmp_dir(droot.local, Path(name).name) if droot.remote else Path(name)


def _ensure_extra_stages(spec: dict[str, Any]) -> None:
    if spec.get("extra_stages") and os.environ.get("CORNERMAP_EXTRA_STAGES") != spec["extra_stages"]:
        from pipeline.registry import load_stages

        os.environ["CORNERMAP_EXTRA_STAGES"] = spec["extra_stages"]
        load_stages.cache_clear()


def _parts(spec: dict[str, Any], label: str) -> dict[str, dict[str, Any] | None]:
    """Output key -> partition ``label``'s part marker (None when not committed)."""
    root, fp = data_root(spec["root"]), spec["fingerprint"]
    return {k: root.part(o["dataset"], fp, label) for k, o in spec["outputs"].items()}


def _cpu_s() -> tuple[float, float]:
    """CPU seconds (this thread's, this process's), each with this process's finished children (the pools a task
    starts)."""
    import resource

    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    kids = children.ru_utime + children.ru_stime
    return time.thread_time() + kids, time.process_time() + kids


def run_partition(spec: dict[str, Any], partition: dict[str, Any],
                  provisional: dict[str, list[str]] | None = None) -> dict[str, Any]:
    """One task: compute one partition, write its outputs atomically, then its part markers (commit).
    ``provisional``: input arg -> upstream partition labels to read before that stage commits (pipeline.flow).
    The result records when it ran (``t_start``/``t_end``, epoch s), its CPU seconds (``cpu_s``: its process's,
    helper threads included, when it ran alone in a process of a pool or cluster worker; else its own thread's) and
    its process's peak RSS (``peak_rss_mb``, pipeline.memory)."""
    import multiprocessing as mp

    from pipeline.memory import PeakRss, relax_malloc_trim, task_scope

    relax_malloc_trim()  # a dask worker's allocator trims so eagerly that numpy work takes 1.5x the CPU
    t_start, (thread0, process0) = time.time(), _cpu_s()
    with task_scope(spec.get("trim_above_mb")) as scope, PeakRss() as rss:
        result = _run_partition(spec, partition, provisional)
    thread1, process1 = _cpu_s()
    # a worker process's threads (a stream's reader and writers, a library's own pool) are the task's when it ran
    # alone there; the run's own process also runs the flow and the single-partition stages' threads
    whole_process = scope.alone and mp.parent_process() is not None
    result.update(t_start=t_start, t_end=time.time(),
                  cpu_s=round(process1 - process0 if whole_process else thread1 - thread0, 3),
                  peak_rss_mb=round(rss.peak_mb, 1))
    return result


def _run_partition(spec: dict[str, Any], partition: dict[str, Any],
                   provisional: dict[str, list[str]] | None) -> dict[str, Any]:
    _ensure_extra_stages(spec)
    pk = PartitionKey(**partition)
    label = pk.label
    markers = _parts(spec, label)
    if markers and all(m is not None for m in markers.values()):
        log.info("%s %s: already committed by an earlier run; reused", spec["stage"], label)
        first = next(iter(markers.values()))
        return {"label": label, "partition": partition, "outputs": {k: m["output"] for k, m in markers.items()},
                "extra": first.get("extra", {}), "reused": True}
    scope = spec.get("drive_scope", {}).get(pk.drive) if pk.drive is not None else None
    if scope and markers:
        reused = _reuse_from_sibling(spec, label, partition, scope)
        if reused is not None:
            return reused
    droot = data_root(spec["root"])
    root, fp = droot.local, spec["fingerprint"]  # on an object-store root: this process's local copy
    token = uuid.uuid4().hex[:8]
    scratch = storage.tmp_dir(root, f"{spec['stage']}-{label}-{token}")
    staging = {k: storage.artifacts_dir(droot.dir(o["dataset"], fp), f".staging-{label}-{token}")
               for k, o in spec["outputs"].items() if o["kind"] == "artifacts"}
    scratch.mkdir(parents=True, exist_ok=True)
    try:
        ctx = _context(spec, pk, scratch, staging, provisional)
        compute = get_stage(spec["stage"]).load_compute()
        try:
            result = dict(compute(ctx) or {})
            extra = result.pop("_extra", {}) or {}
            outputs: dict[str, Any] = {}
            for key, out in spec["outputs"].items():
                ds_dir = droot.dir(out["dataset"], fp)
                where = f"stage {spec['stage']!r} partition {label} output {key!r} (dataset {out['dataset']!r})"
                if out["kind"] == "artifacts":
                    files = commit_artifacts(staging[key], storage.artifacts_dir(ds_dir, label))
                    outputs[key] = {"files": [], "artifacts": files}
                else:
                    files = write_pieces(result.get(key), out_dir=ds_dir, label=label,
                                         schema=resolve_schema(out["schema"]),
                                         partitioning=tuple(out["partitioning"]), where=where,
                                         ledger=_ledger(spec))
                    outputs[key] = {"files": files, "artifacts": None}
        except CornermapError:
            raise
        except Exception as exc:  # noqa: BLE001 - wrapped with where it happened, cause kept
            raise StageError(f"stage {spec['stage']!r} partition {label} failed: {type(exc).__name__}: {exc}") \
                from exc
        for key, out in spec["outputs"].items():  # an object store: the files first, then the part marker
            art = storage.artifacts_dir(PurePosixPath(), label)
            droot.upload(out["dataset"], fp, [f["path"] for f in outputs[key]["files"]]
                         + [(art / f["path"]).as_posix() for f in outputs[key]["artifacts"] or []])
        for key, out in spec["outputs"].items():
            droot.put_part(out["dataset"], fp, label, {"label": label, "partition": partition,
                                                       "output": outputs[key], "extra": extra, "scope": scope})
        return {"label": label, "partition": partition, "outputs": outputs, "extra": extra, "reused": False}
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
        for path in staging.values():
            shutil.rmtree(path, ignore_errors=True)


def _reuse_from_sibling(spec: dict[str, Any], label: str, partition: dict[str, Any],
                        scope: str) -> dict[str, Any] | None:
    """The partition linked (a local root) or copied within the store (an object store: server-side) from another
    build's committed copy with the same drive-scope fingerprint (pipeline/reuse.py), or None when no complete copy
    exists."""
    from pipeline.reuse import find_committed, link_partition

    droot, fp = data_root(spec["root"]), spec["fingerprint"]
    found = {}
    for key, out in spec["outputs"].items():
        hit = find_committed(droot, out["dataset"], fp, label, scope)
        if hit is None:
            return None
        found[key] = (out["dataset"], *hit)
    for key, (ds, src, doc) in found.items():
        link_partition(droot, ds, src, fp, label, doc["output"])
    extra = next(iter(found.values()))[2].get("extra", {})
    for key, (ds, src, doc) in found.items():
        droot.put_part(ds, fp, label, {"label": label, "partition": partition, "output": doc["output"],
                                       "extra": doc.get("extra", {}), "scope": scope, "linked_from": src})
    log.info("%s %s: reused the drive's committed work from %s", spec["stage"], label, src)
    return {"label": label, "partition": partition, "outputs": {k: d["output"] for k, (_, _, d) in found.items()},
            "extra": extra, "reused": True}


def commit_stage(spec: dict[str, Any], parts: list[dict[str, Any]]) -> dict[str, Any]:
    """Write each output dataset's manifest last: the commit marker that readers look for."""
    droot = data_root(spec["root"])
    extra = merge_part_extras(parts)
    manifests = {}
    for key, out in spec["outputs"].items():
        files = [f for p in parts for f in p["outputs"][key]["files"]]
        artifacts = {p["label"]: p["outputs"][key]["artifacts"] for p in parts
                     if p["outputs"][key]["artifacts"] is not None}
        manifest = {
            "dataset": out["dataset"], "stage": spec["stage"], "fingerprint": spec["fingerprint"],
            "code_version": get_stage(spec["stage"]).code_version, "params": spec["params"],
            "inputs": {a: {"dataset": ds, "fingerprint": fp} for a, (ds, fp) in spec["inputs"].items()},
            "drives": spec["drives"], "settings": spec["settings"],
            "partitions": sorted(p["label"] for p in parts),
            "rows": sum(f["rows"] for f in files), "files": sorted(files, key=lambda f: f["path"]),
            "artifacts": artifacts, "extra": extra,
            "committed_utc": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        }
        if not droot.commit(out["dataset"], spec["fingerprint"], manifest):
            log.info("%s: committed by another writer first; its manifest stands",
                     droot.where(out["dataset"], spec["fingerprint"]))
        manifests[key] = {"dataset": out["dataset"], "rows": manifest["rows"], "files": len(files)}
    return manifests


def enumerate_partitions(plan: Plan, sp: StagePlan) -> list[PartitionKey]:
    if sp.partitions is not None:
        return sp.partitions
    spec = _task_spec(plan, sp)
    ctx = _context(spec, PartitionKey(), storage.tmp_dir(plan.root, f"plan-{sp.name}"), {})  # plan.root: local
    if sp.decl.plan:
        from pipeline.declare import resolve

        keys = list(resolve(sp.decl.plan)(ctx))
    elif sp.decl.partition == Partitioning.PER_DRIVE:
        keys = [PartitionKey(drive=d) for d in sp.drives]
    else:
        src = sp.decl.partition_source
        if not src:
            raise StageError(f"stage {sp.name!r} is {sp.decl.partition.value} but names no partition_source or plan")
        fields = ("drive", "chunk") if sp.decl.partition == Partitioning.PER_SCAN_CHUNK else ("tile_i", "tile_j")
        keys = sorted({PartitionKey(**{k: v for k, v in pk.as_dict().items() if k in fields})
                       for pk in ctx.inputs.partitions(src)})
    sp.partitions = keys
    return keys


def task_key(sp: StagePlan, pk: PartitionKey) -> str:
    return f"{sp.name}-{pk.label}-{sp.fp8}"


Progress = Callable[[str, int, int], None]


def set_step_progress(stage: str, display: Callable[[str, int, int], None] | None) -> None:
    """Where a stage's inner steps (``StageContext.report_step``) are shown when it runs in this process."""
    if display is None:
        _STEP_PROGRESS.pop(stage, None)
    else:
        _STEP_PROGRESS[stage] = display


class Scheduler:
    """Where a run's tasks go: ``sync``, ``threads``, ``local``/``processes`` (pools of ``pipeline.flow``), or a
    dask.distributed cluster (``distributed`` starts a local one; ``tcp://HOST:PORT`` connects).

    A local cluster listens on ``host`` only (its scheduler, workers and dashboard; default 127.0.0.1: the dashboard
    has no authentication). dask's own log lines (this process's client, and a local cluster's scheduler, nannies
    and workers) go to ``log_dir``/dask-<time>-<pid>.log (default: the system's temporary folder), not to the
    terminal: a task that raises (an expected quality refusal too) reaches the command as its exception, reported
    in one line. ``dashboard_link`` and ``log_file`` say where to look."""

    def __init__(self, address: str = "local", workers: int | None = None, *, host: str = "127.0.0.1",
                 log_dir: Path | None = None):
        self.address = address
        self.workers = workers or os.cpu_count() or 1
        self._client = None
        self._cluster = None
        self._logs = None  # pipeline.dask_logs.DaskLogs while a cluster is in use
        self.dashboard_link: str | None = None
        self.log_file: Path | None = None
        if address.startswith("tcp://") or address == "distributed":
            self._start_cluster(address, host, log_dir)
        elif address not in ("local", "sync", "synchronous", "threads", "processes"):
            raise StageError(f"unknown scheduler {address!r}; use local | sync | threads | processes | "
                             f"distributed | tcp://HOST:PORT")

    def _start_cluster(self, address: str, host: str, log_dir: Path | None) -> None:
        import tempfile
        import warnings

        from distributed import Client, LocalCluster

        from pipeline.dask_logs import DaskLogs, WorkerLogsToFile

        folder = Path(log_dir) if log_dir is not None else Path(tempfile.gettempdir())
        folder.mkdir(parents=True, exist_ok=True)
        self.log_file = folder / f"dask-{time.strftime('%Y%m%dT%H%M%S')}-{os.getpid()}.log"
        self._logs = DaskLogs(self.log_file)  # worker processes log at ERROR until their plugin sends it to the file
        try:
            with warnings.catch_warnings(record=True) as caught:  # "port 8787 is in use, serving on ..." and alike
                warnings.simplefilter("always")
                if address == "distributed":
                    self._cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=True,
                                                 host=host, dashboard_address=f"{host}:8787",
                                                 worker_dashboard_address=None, silence_logs=False)
                    self._client = Client(self._cluster)
                    self._client.register_plugin(WorkerLogsToFile(str(self.log_file)), name="cornermap-logs")
                else:  # a running cluster's workers log where its operator decided
                    self._client = Client(address)
            for w in caught:
                logging.getLogger("distributed").warning("%s: %s", w.category.__name__, w.message)
            self.dashboard_link = self._client.dashboard_link
        except BaseException:
            self.close()
            raise

    @property
    def kind(self) -> str:
        if self._client is not None:
            return "distributed"
        return {"local": "processes", "synchronous": "sync"}.get(self.address, self.address)

    def close(self) -> None:
        try:
            if self._client is not None:
                self._client.close()
            if self._cluster is not None:
                self._cluster.close()
        finally:
            self._client = self._cluster = None
            if self._logs is not None:
                self._logs.restore()
                self._logs = None
