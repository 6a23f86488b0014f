"""The generic per-stage sub-app: ``cornermap <stage> run|describe|params``."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from pipeline import cli_options as opts
from pipeline.declare import Params, StageDecl


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
        from pipeline.cli import report_run

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
