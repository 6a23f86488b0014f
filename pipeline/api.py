"""The engine's public API for code that drives workflows or stages in process (CLIs, benches, notebooks).

- ``execute_workflow``: load a workflow, plan it and run it (or print the plan with ``dry_run``).
- ``stage_context``: the ``StageContext`` a stage's task would receive for a planned stage (params resolved, inputs
  reading the committed fingerprints), so a bench can call the stage's own functions on a committed root.
- ``load_param_file``: a ``--params`` YAML file ``{stage: {param: value}}``.

Heavy imports happen inside the functions so ``cornermap --help`` stays instant.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Optional

from pipeline import storage

if TYPE_CHECKING:
    from pipeline.declare import PartitionKey, StageContext
    from pipeline.plan import Plan

__all__ = ["execute_workflow", "load_param_file", "stage_context"]


def load_param_file(path: Optional[Path]) -> dict:
    """``{stage: {param: value}}`` from a YAML file; {} for None. ConfigError on any other shape."""
    if path is None:
        return {}
    from pipeline.errors import ConfigError
    from pipeline.safe_yaml import load_yaml_file

    data = load_yaml_file(path) or {}
    if not isinstance(data, dict) or not all(isinstance(v, dict) for v in data.values()):
        raise ConfigError(str(path), ["expected a mapping {stage: {param: value}}"])
    from pipeline.declare import nested
    from pipeline.registry import load_stages, unknown_stage_problem
    from pipeline.workflow import validate_params

    stages, problems = load_stages(), []
    for name, values in data.items():  # checked alone, so that a problem names this file, not the workflow
        if name not in stages:
            problems.append(unknown_stage_problem(name, stages))
        else:
            found = validate_params(stages[name], nested(values), str(path))[1]
            problems += [p.removeprefix(f"{path}: ") for p in found]
    if problems:
        raise ConfigError(str(path), problems)
    return data


def execute_workflow(workflow_path: Path | str, *, root: Optional[Path] = None, scheduler: Optional[str] = None,
                     only: list[str] | None = None, dry_run: bool = False, quiet: bool = True,
                     params_file: Optional[Path] = None, workers: Optional[int] = None,
                     dask_host: str = "127.0.0.1", quiet_plan: bool = False) -> dict:
    """Run a workflow (a file or a packaged name): ``{"plan": Plan, "summary": ..., "wall_s", "cpu_s",
    "dashboard", "dask_log"}``, or with ``dry_run`` ``{"dry_run": True, "root", "stages": rows}`` (the plan, also
    printed unless ``quiet_plan``).

    ``only`` restricts the run to these stages (their inputs must be committed); ``scheduler`` overrides the
    workflow's (local | sync | threads | processes | distributed | tcp://HOST:PORT); ``workers`` sizes a local pool;
    ``dask_host`` is where a local dask cluster listens. Progress goes to the display a command opened
    (``pipeline.progress``), else to one of its own unless ``quiet``. ``cpu_s``: this process's CPU seconds and
    its finished children's (the pools) during the run.
    """
    from pipeline.execute import Scheduler
    from pipeline.flow import run_plan
    from pipeline.memory import over_budget
    from pipeline.plan import describe_plan, make_plan
    from pipeline.progress import StageProgress, print_plan
    from pipeline.workflow import load_workflow

    wf = load_workflow(workflow_path, param_overrides=load_param_file(params_file))
    if only:
        from pipeline.errors import UnknownNameError
        from pipeline.names import suggest

        for name in only:
            if name not in wf.stages:
                raise UnknownNameError(f"--only {name!r}: not a stage of {workflow_path}{suggest(name, wf.stages)}")
    from pipeline.locks import workflow_locks

    root = wf.root_dir(root)
    with workflow_locks(wf, root, only, dry_run=dry_run):  # from planning on: gc keeps what it finds
        plan = make_plan(wf, root, only=only)
        if not dry_run:
            run_preflights(plan)
        if dry_run:
            rows = describe_plan(plan)
            if not quiet_plan:
                print_plan(rows, plan.uri)
            return {"dry_run": True, "root": plan.uri, "stages": rows}
        t0, cpu0 = time.perf_counter(), _cpu_s()
        with StageProgress(enabled=not quiet) as progress:
            skipped = [n for n, sp in plan.stages.items() if sp.selected and sp.committed]
            if skipped:
                progress.event(f"committed by an earlier run, skipped: {', '.join(skipped)}")
            sched = Scheduler(scheduler or wf.spec.scheduler, workers=workers, host=dask_host,
                              log_dir=storage.tmp_dir(Path(plan.root)))
            try:
                if sched.dashboard_link:
                    line = f"dask dashboard: {sched.dashboard_link} (log: {sched.log_file})"
                    progress.event(line) if progress.enabled else print(line, file=sys.stderr)
                summary = run_plan(plan, sched, progress if progress.enabled else None)
            finally:
                sched.close()
    for line in over_budget(summary, wf.spec.memory_budget_mb):
        print(line, file=sys.stderr)
    return {"plan": plan, "summary": summary, "wall_s": round(time.perf_counter() - t0, 3),
            "cpu_s": round(_cpu_s() - cpu0, 3), "dashboard": sched.dashboard_link,
            "dask_log": str(sched.log_file) if sched.log_file else None}


def run_preflights(plan: "Plan") -> None:
    """Each selected stage's ``preflight`` on its drives that exist and its settings, before any stage runs: a run
    that cannot succeed on its inputs stops here, in one line, with nothing computed."""
    import tempfile

    from pipeline.declare import resolve
    from pipeline.errors import CornermapError

    for sp in plan.stages.values():
        if sp.selected and not sp.committed and sp.decl.preflight:
            from pipeline.drive_store import preflight_path

            # a drive named only by URI: checked on its check copy (the drive file and its small files, the names
            # of its scans) in a temporary folder, as a local drive is on its own files
            with tempfile.TemporaryDirectory(prefix="cornermap-check-") as tmp:
                copies = str(Path(tmp).resolve())
                drives = {n: preflight_path(p, Path(copies)) for n, p in sp.drives.items()}
                try:
                    resolve(sp.decl.preflight)({n: p for n, p in drives.items() if p is not None and p.is_file()},
                                               dict(sp.settings))
                except CornermapError as exc:  # a check copy's file is named by the drive's URI
                    raise _renamed(exc, {str(drives[n]): storage.normalise_uri(p) for n, p in sp.drives.items()
                                         if drives[n] is not None and str(drives[n]).startswith(copies)}) from None


def _renamed(exc: Exception, names: dict[str, str]) -> Exception:
    """``exc`` with each local path of ``names`` in its message replaced by what it stands for (a drive's URI)."""
    from pipeline.errors import ConfigError

    if not names:
        return exc

    def sub(text: str) -> str:
        for old, new in names.items():
            text = text.replace(old, new)
        return text

    try:
        if isinstance(exc, ConfigError):
            return type(exc)(sub(exc.where), [sub(p) for p in exc.problems])
        return type(exc)(sub(str(exc)))
    except TypeError:  # an error of another shape: as it is
        return exc


def _cpu_s() -> float:
    import resource

    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def stage_context(plan: "Plan", stage: str, scratch_dir: Path, *, partition: "PartitionKey | None" = None,
                  artifact_dirs: dict[str, Path] | None = None) -> "StageContext":
    """The context a task of ``stage`` gets in ``plan``: validated params, a reader of the committed inputs (the
    plan's fingerprints), the drives and settings. Nothing is written; ``scratch_dir`` must exist for stages that
    use scratch space. Raises ``UnknownNameError`` for a stage not in the plan."""
    from pipeline.declare import PartitionKey
    from pipeline.execute import _context, _task_spec

    if stage not in plan.stages:
        from pipeline.errors import UnknownNameError
        from pipeline.names import suggest

        raise UnknownNameError(f"stage {stage!r} is not in the plan of {plan.root}{suggest(stage, plan.stages)}")
    return _context(_task_spec(plan, plan.stages[stage]), partition or PartitionKey(), Path(scratch_dir),
                    dict(artifact_dirs or {}))
