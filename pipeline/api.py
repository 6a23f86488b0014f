"""The engine's public API for code that drives workflows or stages in process (CLIs, benches, notebooks).

- ``execute_workflow``: load a workflow, plan it and run it (or print the plan with ``dry_run``).
- ``stage_context``: the ``StageContext`` a stage's task would receive for a planned stage (params resolved, inputs
  reading the committed fingerprints), so a bench can call the stage's own functions on a committed root.
- ``load_param_file``: a ``--params`` YAML file ``{stage: {param: value}}``.

Heavy imports happen inside the functions so ``cornermap --help`` stays instant.
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING, Optional

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
    return data


def execute_workflow(workflow_path: Path | str, *, root: Optional[Path] = None, scheduler: Optional[str] = None,
                     only: list[str] | None = None, dry_run: bool = False, quiet: bool = True,
                     params_file: Optional[Path] = None, workers: Optional[int] = None) -> dict:
    """Run a workflow (a file or a packaged name): ``{"plan": Plan, "summary": ...}``, or ``{"dry_run": True}``.

    ``only`` restricts the run to these stages (their inputs must be committed); ``scheduler`` overrides the
    workflow's (local | sync | threads | processes | distributed | tcp://HOST:PORT); ``workers`` sizes a local pool.
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
        from pipeline.registry import suggest

        for name in only:
            if name not in wf.stages:
                raise UnknownNameError(f"--only {name!r}: not a stage of {workflow_path}{suggest(name, wf.stages)}")
    from pipeline.locks import workflow_locks

    with workflow_locks(wf, wf.root_dir(root), only, dry_run=dry_run):  # from planning on: gc keeps what it finds
        plan = make_plan(wf, wf.root_dir(root), only=only)
        if dry_run:
            print_plan(describe_plan(plan), plan.root)
            return {"dry_run": True}
        sched = Scheduler(scheduler or wf.spec.scheduler, workers=workers)
        try:
            with StageProgress(enabled=not quiet) as progress:
                summary = run_plan(plan, sched, progress.update)
        finally:
            sched.close()
    if not quiet:
        print_plan(describe_plan(plan), plan.root, summary)
    for line in over_budget(summary, wf.spec.memory_budget_mb):
        print(line, file=sys.stderr)
    return {"plan": plan, "summary": summary}


def stage_context(plan: "Plan", stage: str, scratch_dir: Path, *, partition: "PartitionKey | None" = None,
                  artifact_dirs: dict[str, Path] | None = None) -> "StageContext":
    """The context a task of ``stage`` gets in ``plan``: validated params, a reader of the committed inputs (the
    plan's fingerprints), the drives and settings. Nothing is written; ``scratch_dir`` must exist for stages that
    use scratch space. Raises ``UnknownNameError`` for a stage not in the plan."""
    from pipeline.declare import PartitionKey
    from pipeline.execute import _context, _task_spec

    if stage not in plan.stages:
        from pipeline.errors import UnknownNameError
        from pipeline.registry import suggest

        raise UnknownNameError(f"stage {stage!r} is not in the plan of {plan.root}{suggest(stage, plan.stages)}")
    return _context(_task_spec(plan, plan.stages[stage]), partition or PartitionKey(), Path(scratch_dir),
                    dict(artifact_dirs or {}))
