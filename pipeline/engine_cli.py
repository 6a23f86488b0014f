"""The engine's commands, offered to the top-level app (``mapservice.cli``, which adds the map service's): ``run``,
``catalog ls|validate``, and every registered stage's ``cornermap <stage> run|describe|params`` (plus the commands a
stage's own CLI module adds, ``register_stages``); ``report_run``, the closing summary of a run.

Heavy imports happen inside commands so ``--help`` is instant. Shared options: ``pipeline.cli_options``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import typer

from pipeline import cli_options as opts
from pipeline.declare import Params, StageDecl

catalog_app = typer.Typer(no_args_is_help=True, help="Inspect and validate the data catalog.")


def report_run(result: dict, as_json: bool, *, extra: dict | None = None, notes: list[str] = ()) -> None:
    """The closing summary of a run (``execute_workflow``'s result): what the stages published, then per stage its
    decision, partitions, wall and CPU seconds and peak memory, and the run's totals; with ``as_json`` all of it as
    one JSON document on stdout. ``notes`` go to stderr."""
    from pipeline.progress import outcome_lines, summary_lines

    plan = result["plan"]
    outcomes = outcome_lines(plan)
    if as_json:
        opts.echo_json({"root": plan.uri, "workflow": plan.workflow.spec.name, **(extra or {}),
                        "outcomes": outcomes, "wall_s": result["wall_s"], "cpu_s": result["cpu_s"],
                        "stages": result["summary"], "dask_dashboard": result.get("dashboard"),
                        "dask_log": result.get("dask_log")})
    else:
        for line in outcomes + summary_lines(result["summary"], plan.uri, result["wall_s"], result["cpu_s"]):
            typer.echo(line)
    for line in notes:
        typer.echo(line, err=True)


def run_cmd(workflow: Path = typer.Argument(..., help="Workflow YAML file, or a packaged workflow's name "
                                                     "(demo, tiny, gangnam, map_rebuild)"),
            root: Optional[Path] = opts.ROOT_OF_WORKFLOW_OR_URI, scheduler: Optional[str] = opts.SCHEDULER,
            only: Optional[list[str]] = typer.Option(None, "--only", help="Run only these stages (repeatable)."),
            dry_run: bool = typer.Option(False, "--dry-run", help="Print order, partitions, fingerprints, decisions."),
            quiet: bool = opts.QUIET, params: Optional[Path] = opts.PARAMS,
            workers: Optional[int] = opts.WORKERS, dask_host: str = opts.DASK_HOST,
            as_json: bool = opts.JSON) -> None:
    """Run a workflow: stages in dependency order; unchanged stages are skipped.

    Relative paths inside a workflow file resolve against the file's folder; the output root is --root, else the
    workflow's root, else runs/NAME in the current directory.

    Examples: [b]cornermap run tiny --root runs/tiny[/b]; [b]cornermap run tiny --root runs/tiny --only corners[/b];
    [b]cornermap run tiny --root runs/tiny --scheduler tcp://127.0.0.1:8786[/b] (a dask.distributed scheduler)
    """
    from pipeline.api import execute_workflow

    result = execute_workflow(workflow, root=root, scheduler=scheduler, only=only, dry_run=dry_run, quiet=quiet,
                              params_file=params, workers=workers, dask_host=dask_host, quiet_plan=as_json)
    if dry_run and as_json:
        opts.echo_json({"root": result["root"], "dry_run": True, "stages": result["stages"]})
    elif not dry_run:
        report_run(result, as_json)


@catalog_app.command("ls")
def catalog_ls(catalog: Optional[Path] = typer.Argument(None, help="Catalog folder or file (default: the packaged "
                                                                  "catalog).")) -> None:
    """List every dataset with kind, schema, partitioning and versioning.

    Example: [b]cornermap catalog ls[/b]
    """
    from pipeline.catalog import load_catalog
    from pipeline.resources import packaged_catalog_dir

    cat = load_catalog([catalog or packaged_catalog_dir()])
    for name, spec in cat.datasets.items():
        typer.echo(f"{name:22s} {spec.kind:9s} schema={spec.schema_ref or '-':22s} "
                   f"partitioning={','.join(spec.partitioning) or '-':14s} {spec.versioning}")


@catalog_app.command("validate")
def catalog_validate(
    catalog: Optional[Path] = typer.Argument(None, help="default: the packaged catalog"),
    workflows: list[Path] = typer.Option([], "--workflow", help="Also validate these workflows."),
) -> None:
    """Validate the catalog (and workflows): every problem is listed at once.

    Example: [b]cornermap catalog validate --workflow tiny[/b]
    """
    from pipeline.catalog import load_catalog
    from pipeline.resources import packaged_catalog_dir
    from pipeline.workflow import load_workflow

    cat = load_catalog([catalog or packaged_catalog_dir()])
    for wf in workflows:
        load_workflow(wf)
    typer.echo(f"ok: {len(cat.datasets)} datasets" + (f", {len(workflows)} workflow(s)" if workflows else ""))


def register_stages(app: typer.Typer, order: Sequence[str] = ()) -> None:
    """Every registered stage's sub-app on ``app``, those named in ``order`` first in that order, the others by name;
    a stage with a CLI module (``StageDecl.cli``) also adds its own commands through that module's ``register``."""
    import importlib
    import inspect

    from pipeline.registry import load_stages

    rank = {n: i for i, n in enumerate(order)}
    for name, decl in sorted(load_stages().items(), key=lambda kv: (rank.get(kv[0], len(rank)), kv[0])):
        sub = stage_app(decl)
        if decl.cli:
            register = importlib.import_module(decl.cli).register
            # register(app) adds top-level commands; register(app, stage_app) may also extend the stage's group.
            register(app, sub) if len(inspect.signature(register).parameters) >= 2 else register(app)
        # A stage whose CLI module adds a top-level command of its own name (simulate, evaluate) is used that way.
        if not any(c.name == name for c in app.registered_commands):
            app.add_typer(sub, name=name, help=sub.info.help or decl.summary)


def format_params(decl: StageDecl) -> str:
    lines = [f"# {decl.name} params (defaults); override in a workflow's params.{decl.name} or --params FILE"]

    def walk(params: type[Params], indent: str) -> None:
        for name, f in params.model_fields.items():
            doc = f" # {f.description}" if f.description else ""
            if isinstance(f.annotation, type) and issubclass(f.annotation, Params):  # a section: its keys below
                lines.append(f"{indent}{name}:{doc}")
                walk(f.annotation, indent + "  ")
            else:
                lines.append(f"{indent}{name}: {f.get_default(call_default_factory=True)!r}{doc}")

    walk(decl.params, "")
    return "\n".join(lines)


def format_describe(decl: StageDecl) -> str:
    ins = "\n".join(f"  {a} <- {ds}" + (" (optional)" if a in decl.optional_inputs else "")
                    for a, ds in decl.inputs.items()) or "  (none)"
    outs = "\n".join(f"  {k} -> {ds}" for k, ds in decl.outputs.items())
    return (f"{decl.name}: {decl.summary}\ncode_version: {decl.code_version}\npartition: {decl.partition.value}"
            + (f" (from {decl.partition_source})" if decl.partition_source else "")
            + f"\ninputs:\n{ins}\noutputs:\n{outs}\ncompute: {decl.compute}\n\n{format_params(decl)}")


def stage_app(decl: StageDecl) -> typer.Typer:
    sub = typer.Typer(no_args_is_help=True, help=decl.summary)

    @sub.command("run")
    def run(workflow: str = typer.Option("map_rebuild", "--workflow", "-w",
                                         help="Workflow whose inputs this stage reads (a file or a packaged name)."),
            root: Optional[Path] = opts.ROOT_OF_WORKFLOW, scheduler: Optional[str] = opts.SCHEDULER,
            workers: Optional[int] = opts.WORKERS, dask_host: str = opts.DASK_HOST,
            params: Optional[Path] = opts.PARAMS, dry_run: bool = typer.Option(False, "--dry-run"),
            quiet: bool = opts.QUIET, as_json: bool = opts.JSON):
        """Run this stage alone on committed inputs of a workflow."""
        from pipeline.api import execute_workflow

        result = execute_workflow(workflow, root=root, scheduler=scheduler, only=[decl.name], dry_run=dry_run,
                                  quiet=quiet, params_file=params, workers=workers, dask_host=dask_host,
                                  quiet_plan=as_json)
        if dry_run and as_json:
            opts.echo_json({"root": result["root"], "dry_run": True, "stages": result["stages"]})
        elif not dry_run:
            report_run(result, as_json)

    @sub.command("describe")
    def describe():
        """Inputs, outputs, partitioning, code version and params of this stage."""
        typer.echo(format_describe(decl))

    @sub.command("params")
    def params_cmd():
        """Print this stage's params with their defaults and units."""
        typer.echo(format_params(decl))

    run.__doc__ = f"Run the {decl.name} stage alone on committed inputs.\n\nExample: cornermap {decl.name} run " \
                  f"--workflow tiny --root runs/tiny"
    return sub
