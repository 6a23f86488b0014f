"""The typer root app ``cornermap``. Heavy imports happen inside commands so ``--help`` is instant."""
from __future__ import annotations

import contextlib
import logging
import signal
import sys
import threading
from pathlib import Path
from typing import Optional

import typer

from pipeline.api import execute_workflow
from pipeline.errors import CornermapError

app = typer.Typer(
    name="cornermap",
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode="rich",
    help="Batch production of LiDAR localization maps (vertical-corner landmarks + road-marking rasters).\n\n"
    "Examples:\n\n"
    "  cornermap simulate --preset tiny --seed 7 --out runs/sim\n\n"
    "  cornermap build --drive runs/sim/drive_0/drive.yaml --map city --root runs/maps --origin 37.4979,127.0276,57\n\n"
    "  cornermap run tiny --root runs/tiny --dry-run\n\n"
    "  cornermap corners params",
)
catalog_app = typer.Typer(no_args_is_help=True, help="Inspect and validate the data catalog.")
app.add_typer(catalog_app, name="catalog")

ROOT_OPT = typer.Option(None, "--root", help="Output root (datasets/, maps/); default: the workflow's root.")
SCHED_OPT = typer.Option(None, "--scheduler",
                         help="local (processes sized to the machine) | sync | threads | distributed | tcp://HOST:PORT")
WORKERS_OPT = typer.Option(None, "--workers", min=1,
                           help="Processes (or threads) of a local scheduler; default: the machine's cores.")
QUIET_OPT = typer.Option(False, "--quiet", "-q", help="No progress display.")
PARAMS_OPT = typer.Option(None, "--params", help="YAML file {stage: {param: value}} overriding workflow params.")


def _version_callback(value: bool) -> None:
    if value:
        from importlib.metadata import version

        import dask
        import gtsam  # noqa: F401 - fails here, not later, when gtsam is broken
        import open3d

        typer.echo(f"cornermap {version('cornermap')} (open3d {open3d.__version__}, "
                   f"gtsam {version('gtsam')}, dask {dask.__version__})")
        raise typer.Exit()


@app.callback()
def _root(version: bool = typer.Option(False, "--version", callback=_version_callback, is_eager=True,
                                       help="Print versions of cornermap, open3d, gtsam and dask."),
          verbose: bool = typer.Option(False, "--verbose", "-v", help="Log at INFO level.")) -> None:
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")


@app.command("run")
def run_cmd(workflow: Path = typer.Argument(..., help="Workflow YAML file, or a packaged workflow's name "
                                                     "(demo, tiny, gangnam, map_rebuild)"),
            root: Optional[Path] = ROOT_OPT, scheduler: Optional[str] = SCHED_OPT,
            only: Optional[list[str]] = typer.Option(None, "--only", help="Run only these stages (repeatable)."),
            dry_run: bool = typer.Option(False, "--dry-run", help="Print order, partitions, fingerprints, decisions."),
            quiet: bool = QUIET_OPT, params: Optional[Path] = PARAMS_OPT,
            workers: Optional[int] = WORKERS_OPT) -> None:
    """Run a workflow: stages in dependency order; unchanged stages are skipped.

    Relative paths inside a workflow file resolve against the file's folder; the output root is --root, else the
    workflow's root, else runs/NAME in the current directory.

    Examples: [b]cornermap run tiny --root runs/tiny[/b]; [b]cornermap run tiny --root runs/tiny --only corners[/b];
    [b]cornermap run tiny --root runs/tiny --scheduler tcp://127.0.0.1:8786[/b] (a dask.distributed scheduler)
    """
    result = execute_workflow(workflow, root=root, scheduler=scheduler, only=only, dry_run=dry_run, quiet=quiet,
                              params_file=params, workers=workers)
    if not dry_run:
        from pipeline.progress import print_outcomes

        print_outcomes(result["plan"])


@app.command("build")
def build_cmd(
    drive: list[Path] = typer.Option(..., "--drive", help="drive.yaml of a map drive (repeatable)."),
    map_name: str = typer.Option(..., "--map", help="Map name: publishes ROOT/maps/NAME/vNNNN."),
    root: Path = typer.Option(..., "--root", help="Output root."),
    origin: Optional[str] = typer.Option(
        None,
        "--origin",
        help="The map's ENU origin LAT,LON,H (degrees, "
        "degrees, metres WGS84); default: the first GNSS fix of the first drive.",
    ),
    scheduler: Optional[str] = SCHED_OPT,
    quiet: bool = QUIET_OPT,
    workflow: str = typer.Option(
        "map_rebuild", "--workflow", help="The map workflow to run on these drives (a file or a packaged name)."
    ),
) -> None:
    """Build and publish the next version of map NAME from drives (the standard map workflow).

    A map with an identity (cornermap maps create) or a published version keeps its frame: its origin is used,
    and an --origin that differs is refused (exit 1).

    Example:
    [b]cornermap build --drive runs/sim/drive_0/drive.yaml --map city --root runs/maps --origin 37.4979,127.0276,57[/b]
    """
    from pipeline.build import parse_origin, write_build_workflow
    from pipeline.maps import pinned_frame
    from pipeline.names import check_name

    check_name(map_name, "map", "--map")
    pinned, tile_size_m = pinned_frame(root, map_name, parse_origin(origin) if origin else None)
    path = write_build_workflow(workflow, drives=drive, map_name=map_name, root=root, origin=pinned,
                                tile_size_m=tile_size_m)
    result = execute_workflow(path, root=root, scheduler=scheduler, only=None, dry_run=False, quiet=quiet)
    from pipeline.maps import stale_latest_note
    from pipeline.progress import print_outcomes

    print_outcomes(result["plan"])
    note = stale_latest_note(result["plan"], map_name)
    if note:
        typer.echo(note, err=True)


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


_REGISTERED: list[bool] = []


def _register_stages() -> None:
    if _REGISTERED:  # main() may run more than once in one process (tests)
        return
    _REGISTERED.append(True)
    from pipeline.maps_cli import register as register_maps

    register_maps(app)
    from pipeline.registry import load_stages
    from pipeline.stage_cli import stage_app

    for name, decl in load_stages().items():
        sub = stage_app(decl)
        if decl.cli:
            import importlib
            import inspect

            register = importlib.import_module(decl.cli).register
            # register(app) adds top-level commands; register(app, stage_app) may also extend the stage's group.
            register(app, sub) if len(inspect.signature(register).parameters) >= 2 else register(app)
        # A stage whose CLI module adds a top-level command of its own name (simulate, evaluate) is used that way.
        if not any(c.name == name for c in app.registered_commands):
            app.add_typer(sub, name=name, help=sub.info.help or decl.summary)


EXIT_TERMINATED = 143  # 128 + SIGTERM, the shells' convention for a process ended by that signal


class Terminated(BaseException):
    """SIGTERM reached the command (a job scheduler's timeout or cancel). Raised in the main thread, so the run's
    cleanup runs on the way out; not an ``Exception``: no handler of a stage takes it for a stage's own error."""


@contextlib.contextmanager
def sigterm_stops_the_run():
    """Within: a SIGTERM ends the pool processes this process started (they would otherwise finish their task
    first) and raises ``Terminated`` in the main thread; a second SIGTERM ends the process at once (the default).
    Outside the main thread (a test's runner), nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum, frame):
        import multiprocessing

        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        for child in multiprocessing.active_children():
            child.terminate()
        raise Terminated()

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def main(argv: list[str] | None = None) -> None:
    """Entry point: every error a user can cause ends as one ``error: ...`` line on stderr and exit 1 (3 for
    data-quality failures); an unexpected exception is reported the same way (traceback with -v); a SIGTERM ends
    the run with one line and exit 143 (``sigterm_stops_the_run``)."""
    try:  # typer >= 0.20 vendors click
        from typer._click.exceptions import ClickException, UsageError
    except ImportError:  # pragma: no cover - older typer
        from click.exceptions import ClickException, UsageError

    try:
        _register_stages()
        command = typer.main.get_command(app)
        with sigterm_stops_the_run():
            command.main(args=argv, prog_name="cornermap", standalone_mode=False)
    except Terminated:
        typer.echo("terminated: SIGTERM; the run stopped (what it committed before stays; nothing half-written is "
                   "visible; run it again to go on)", err=True)
        sys.exit(EXIT_TERMINATED)
    except typer.Exit as exc:
        sys.exit(getattr(exc, "exit_code", 0))
    except UsageError as exc:
        path = exc.ctx.command_path if exc.ctx is not None else "cornermap"
        typer.echo(f"error: {exc.format_message()} (see '{path} --help')", err=True)
        sys.exit(1)
    except ClickException as exc:
        typer.echo(f"error: {exc.format_message()}", err=True)
        sys.exit(1)
    except typer.Abort:
        typer.echo("aborted", err=True)
        sys.exit(130)
    except CornermapError as exc:
        from pipeline.errors import ConfigError

        one = isinstance(exc, ConfigError) and len(exc.problems) == 1
        typer.echo(f"error: {exc.where}: {exc.problems[0]}" if one else f"error: {exc}", err=True)
        sys.exit(exc.exit_code)
    except OSError as exc:  # the file system refused (permissions, full disk, a directory where a file goes)
        where = f"{exc.filename}: " if exc.filename else ""
        typer.echo(f"error: {where}{exc.strerror or exc}", err=True)
        sys.exit(1)
    except Exception as exc:  # noqa: BLE001 - the last line of defence: a bug, reported without a traceback
        if logging.getLogger().isEnabledFor(logging.INFO):
            logging.getLogger("cornermap").exception("unexpected error")
        typer.echo(f"error: internal error {type(exc).__name__}: {exc} (a bug; rerun with -v for the traceback)",
                   err=True)
        sys.exit(1)
