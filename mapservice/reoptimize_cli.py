"""``cornermap maps reoptimize``: the map's drives re-solved region by region (mapservice/reoptimize.py). Heavy imports
inside."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from pipeline import cli_options as opts


def reoptimize_cmd(root: Path = opts.ROOT_OR_URI, map_name: str = opts.MAP,
                   region_max_poses: int = typer.Option(600, "--region-max-poses", min=0, help="Most poses of one "
                                                        "region (the cost of one region's solve); 0: one joint "
                                                        "solve, as rebuild --full."),
                   min_free_gib: float = typer.Option(2.0, "--min-free-gib", help="Free space required to start."),
                   gate_tol_m: float = typer.Option(0.05, "--gate-tol-m", help="Gate: a localization figure may "
                                                    "grow by max(this, --gate-tol-rel x previous) metres."),
                   gate_tol_rel: float = typer.Option(0.2, "--gate-tol-rel", help="Gate: relative tolerance."),
                   no_gate: bool = typer.Option(False, "--no-gate", help="Publish without the regression gate."),
                   scheduler: Optional[str] = opts.SCHEDULER, workers: Optional[int] = opts.WORKERS,
                   dask_host: str = opts.DASK_HOST, params: Optional[Path] = opts.PARAMS,
                   workflow: str = typer.Option("map_rebuild", "--workflow", help="The map workflow."),
                   quiet: bool = opts.QUIET, as_json: bool = opts.JSON) -> None:
    """Re-solve every drive of map NAME together, region by region, and publish the result as its next version.

    What `rebuild --full` solves (every pass, every loop), each pose-graph solve split into regions of at most
    --region-max-poses poses that run side by side on the dask workers (--workers, --scheduler tcp://...), with the
    borders between them solved exactly (a condensed separator); then the regression gate and LATEST as a rebuild.
    Run it when `cornermap maps show` advises it, or on a schedule (docs/maintenance.md). --root may be an
    s3://BUCKET/PREFIX URI (the map's identity, LATEST, gate records and locks in the bucket), as for rebuild.

    Exit codes: 0 published (or LATEST is already the result), 3 gate refused (LATEST unchanged), 1 error, 2 usage,
    75 another writer of the map or root holds its lock, 130/143 interrupted/terminated.

    Example: [b]cornermap maps reoptimize --root runs/maps --map kept --workers 2[/b]
    """
    import math

    from mapservice.reoptimize import ReoptimizeParams, reoptimize
    from pipeline.errors import OptionError
    from pipeline.progress import StageProgress

    for opt, v in (("--min-free-gib", min_free_gib), ("--gate-tol-m", gate_tol_m), ("--gate-tol-rel", gate_tol_rel)):
        if not (math.isfinite(v) and v >= 0):
            raise OptionError(opt, [f"expected a finite number >= 0; got {v}"])
    p = ReoptimizeParams(region_max_poses=region_max_poses, min_free_gib=min_free_gib, gate=not no_gate,
                         gate_tol_m=gate_tol_m, gate_tol_rel=gate_tol_rel, workflow=workflow, scheduler=scheduler,
                         params_file=params, workers=workers, dask_host=dask_host)
    with StageProgress(enabled=not quiet):
        result = reoptimize(root, map_name, p, say=None if as_json else typer.echo)
    if as_json:
        opts.echo_json({"map": map_name, "status": result.status, "exit_code": result.exit_code,
                        "version": f"v{result.version:04d}" if result.version is not None else None,
                        "lines": result.lines, "stages": result.summary})
    elif result.summary:
        from pipeline.progress import summary_lines

        for line in summary_lines(result.summary, root):
            typer.echo(line)
    if result.exit_code:
        raise typer.Exit(result.exit_code)
