"""The pose graph's inputs on a built tiny root, solved to pass 1 (odometry + GNSS), for tests of its inner steps."""
from __future__ import annotations

from pathlib import Path


def pass1_on_tiny(root: Path, workflow: Path, scratch: str, param_updates: dict | None = None):
    """(context, map drives, params with ``param_updates`` (dotted keys), drive offsets, pass-1 poses) of the
    posegraph stage on ``root`` (a run of ``workflow``)."""
    from pipeline.declare import PartitionKey
    from pipeline.execute import _context, _task_spec
    from pipeline.plan import make_plan
    from pipeline.workflow import load_workflow
    from stages.posegraph.compute import read_drive_inputs
    from stages.posegraph.factors.base import base_problem
    from stages.posegraph.factors.graph import optimize

    plan = make_plan(load_workflow(workflow), root)
    ctx = _context(_task_spec(plan, plan.stages["posegraph"]), PartitionKey(), root / "tmp" / scratch, {})
    drives, _ = read_drive_inputs(ctx)
    cfg = ctx.params.updated(param_updates or {})
    problem, offsets = base_problem(drives, cfg.factors, cfg.gnss)
    return ctx, drives, cfg, offsets, optimize(problem)
