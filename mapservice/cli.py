"""The typer root app ``cornermap`` and its entry point ``main``: the exit codes of every command.

The app is assembled here, above the engine and the stages: the engine's commands (``run``, ``catalog``, every
stage's, ``pipeline.engine_cli``), then the map service's (``build`` here, ``maps ...``, ``rebuild``,
``mapservice.maps_cli``). Heavy imports happen inside commands so ``--help`` is instant. Shared options:
``pipeline.cli_options``.
"""
from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Optional

import typer

from pipeline import cli_options as opts
from pipeline.api import execute_workflow
from pipeline.engine_cli import catalog_app, register_stages, report_run, run_cmd
from pipeline.errors import CornermapError

app = typer.Typer(
    name="cornermap",
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode="rich",
    context_settings={"help_option_names": ["-h", "--help"]},
    help="Batch production of LiDAR localization maps (vertical-corner landmarks + road-marking rasters).\n\n"
    "Exit codes: 0 ok, 1 error, 2 usage, 3 data quality (a gate refused), 75 locked (try later), 130 interrupted "
    "(SIGINT), 143 terminated (SIGTERM).\n\n"
    "Examples:\n\n"
    "  cornermap simulate --preset tiny --seed 7 --out runs/sim\n\n"
    "  cornermap build --drive runs/sim/drive_0/drive.yaml --map city --root runs/maps --origin 37.4979,127.0276,57\n\n"
    "  cornermap run tiny --root runs/tiny --dry-run\n\n"
    "  cornermap corners params",
)
app.add_typer(catalog_app, name="catalog")
app.command("run")(run_cmd)


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


@app.command("build")
def build_cmd(
    drive: list[Path] = typer.Option(..., "--drive", help="drive.yaml of a map drive (repeatable)."),
    map_name: str = opts.MAP,
    root: Path = opts.ROOT_OR_URI,
    origin: Optional[str] = typer.Option(
        None,
        "--origin",
        help="The map's ENU origin LAT,LON,H (degrees, "
        "degrees, metres WGS84); default: the first GNSS fix of the first drive, else a prior trajectory's ENU "
        "origin, else a stated start position. A drive whose start: has no position starts here.",
    ),
    scheduler: Optional[str] = opts.SCHEDULER,
    workers: Optional[int] = opts.WORKERS,
    dask_host: str = opts.DASK_HOST,
    quiet: bool = opts.QUIET,
    params: Optional[Path] = opts.PARAMS,
    as_json: bool = opts.JSON,
    workflow: str = typer.Option(
        "map_rebuild", "--workflow", help="The map workflow to run on these drives (a file or a packaged name)."
    ),
) -> None:
    """Build and publish the next version of map NAME from drives (the standard map workflow).

    A map with an identity (cornermap maps create) or a published version keeps its frame: its origin is used,
    and an --origin that differs is refused (exit 1). A drive nothing places in the map's frame (no GNSS, no prior
    trajectory, no start heading) is refused before any stage runs (exit 3); a drive that starts at the map's
    origin needs one (exit 2 without).

    Example:
    [b]cornermap build --drive runs/sim/drive_0/drive.yaml --map city --root runs/maps --origin 37.4979,127.0276,57[/b]
    """
    from mapservice.build import parse_origin, write_build_workflow
    from mapservice.maps import pinned_frame, published_version, stale_latest_note
    from pipeline.names import check_name
    from pipeline.store_maps import map_view

    check_name(map_name, "map", "--map")
    with map_view(root, map_name) as local_root:  # an object-store root: its map's identity and LATEST, downloaded
        pinned, tile_size_m = pinned_frame(local_root, map_name, parse_origin(origin) if origin else None)
        path = write_build_workflow(workflow, drives=drive, map_name=map_name, root=root, origin=pinned,
                                    tile_size_m=tile_size_m, map_root=local_root)
    result = execute_workflow(path, root=root, scheduler=scheduler, only=None, dry_run=False, quiet=quiet,
                              params_file=params, workers=workers, dask_host=dask_host)
    version = published_version(result["plan"])
    note = stale_latest_note(result["plan"], map_name)
    report_run(result, as_json, notes=[note] if note else [],
               extra={"map": map_name, "map_version": f"v{version:04d}" if version is not None else None})


# The stages in the order data flows through them: the order `cornermap --help` lists their commands.
STAGE_ORDER = ("simulate", "ingest", "odometry", "posegraph", "corners", "cornermap", "markings", "tiles", "evaluate")
_REGISTERED: list[bool] = []


def _register_stages() -> None:
    if _REGISTERED:  # main() may run more than once in one process (tests)
        return
    _REGISTERED.append(True)
    from mapservice.maps_cli import register as register_maps

    register_maps(app)
    register_stages(app, STAGE_ORDER)


EXIT_USAGE = 2  # the command line is wrong (click's and argparse's code)
EXIT_INTERRUPTED = 130  # 128 + SIGINT, the shells' convention for a process ended by that signal
EXIT_TERMINATED = 143  # 128 + SIGTERM


class Stopped(BaseException):
    """A signal asked the command to stop. Raised in the main thread, so the run's cleanup runs on the way out; not
    an ``Exception``: no handler of a stage takes it for a stage's own error."""

    exit_code = 1
    line = "stopped"


class Interrupted(Stopped):
    """SIGINT reached the command (Ctrl-C in its terminal, or ``kill -INT``)."""

    exit_code = EXIT_INTERRUPTED
    line = ("interrupted: SIGINT; the command stopped (what it committed before stays; nothing half-written is "
            "visible; run it again to go on)")


class Terminated(Stopped):
    """SIGTERM reached the command (a job scheduler's timeout or cancel, systemd stopping a unit)."""

    exit_code = EXIT_TERMINATED
    line = ("terminated: SIGTERM; the command stopped (what it committed before stays; nothing half-written is "
            "visible; run it again to go on)")


@contextlib.contextmanager
def signals_stop_the_run():
    """Within: SIGINT and SIGTERM end the pool processes this process started (they would otherwise finish their
    task first; they ignore SIGINT themselves, ``pipeline.parallel``) and raise ``Interrupted`` / ``Terminated`` in
    the main thread; a second signal ends the process at once (the default action). Outside the main thread (a
    test's runner), nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum, frame):
        import multiprocessing

        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        for child in multiprocessing.active_children():
            child.terminate()
        raise Interrupted() if signum == signal.SIGINT else Terminated()

    previous = {s: signal.signal(s, stop) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


sigterm_stops_the_run = signals_stop_the_run  # the name of its first version (SIGTERM only)


def _exceptions():
    try:  # typer >= 0.20 vendors click
        from typer._click import exceptions
    except ImportError:  # pragma: no cover - older typer
        from click import exceptions
    return exceptions


def _command_path(argv: list[str] | None) -> str:
    """``cornermap SUB CMD``: the commands named at the start of ``argv`` (for "see '... --help'")."""
    command = typer.main.get_command(app)
    path = ["cornermap"]
    for arg in (sys.argv[1:] if argv is None else argv):
        sub = getattr(command, "commands", {}).get(arg)
        if sub is None:
            if arg.startswith("-"):
                continue  # a root option (-v) before the command
            break
        command, path = sub, path + [arg]
    return " ".join(path)


def run_command(argv: list[str] | None = None) -> int:
    """Run ``cornermap ARGV`` and return its exit code (see ``main``); what a user should read is on stderr."""
    exc_mod = _exceptions()
    try:
        _register_stages()
        command = typer.main.get_command(app)
        with signals_stop_the_run():
            code = command.main(args=argv, prog_name="cornermap", standalone_mode=False)
        if code == EXIT_INTERRUPTED:  # typer's own answer to a KeyboardInterrupt (a SIGINT outside our handler)
            typer.echo(Interrupted.line, err=True)
        return code if isinstance(code, int) else 0
    except Stopped as exc:
        typer.echo(exc.line, err=True)
        return exc.exit_code
    except KeyboardInterrupt:
        typer.echo(Interrupted.line, err=True)
        return EXIT_INTERRUPTED
    except exc_mod.NoArgsIsHelpError as exc:  # a group named without a command: its help is the answer
        message = exc.format_message().strip()
        if message:
            typer.echo(message, err=True)
        return EXIT_USAGE
    except exc_mod.UsageError as exc:
        path = exc.ctx.command_path if exc.ctx is not None else _command_path(argv)
        typer.echo(f"error: {exc.format_message()} (see '{path} --help')", err=True)
        return EXIT_USAGE
    except exc_mod.ClickException as exc:
        typer.echo(f"error: {exc.format_message()}", err=True)
        return exc.exit_code or 1
    except typer.Abort:
        typer.echo("aborted", err=True)
        return 1
    except typer.Exit as exc:
        return exc.exit_code
    except CornermapError as exc:
        from pipeline.errors import ConfigError

        one = isinstance(exc, ConfigError) and len(exc.problems) == 1
        text = f"error: {exc.where}: {exc.problems[0]}" if one else f"error: {exc}"
        if exc.exit_code == EXIT_USAGE:
            text += f" (see '{_command_path(argv)} --help')"
        typer.echo(text, err=True)
        return exc.exit_code
    except OSError as exc:  # the file system refused (permissions, full disk, a directory where a file goes)
        where = f"{exc.filename}: " if exc.filename else ""
        typer.echo(f"error: {where}{exc.strerror or exc}", err=True)
        return 1
    except Exception as exc:  # noqa: BLE001 - the last line of defence: a bug, reported without a traceback
        from pipeline.storage import object_store_error_line

        line = object_store_error_line(exc)
        if line is not None:  # the object store failed (unreachable, credentials, bucket): not a bug of ours
            typer.echo(f"error: {line}", err=True)
            return 1
        if logging.getLogger().isEnabledFor(logging.INFO):
            logging.getLogger("cornermap").exception("unexpected error")
        typer.echo(f"error: internal error {type(exc).__name__}: {exc} (a bug; rerun with -v for the traceback)",
                   err=True)
        return 1


def main(argv: list[str] | None = None) -> None:
    """Entry point. Exit codes: 0 ok; 1 error (one ``error: ...`` line on stderr, a bug too: traceback with -v);
    2 usage (unknown command or option, a missing or malformed option value); 3 data quality (a gate refused);
    75 locked (another run holds the lock: try later); 130 interrupted (SIGINT), 143 terminated (SIGTERM), each
    with one line, pool processes ended, nothing half-written visible (``signals_stop_the_run``)."""
    quiet_resource_tracker()
    code = run_command(argv)
    if code in (EXIT_INTERRUPTED, EXIT_TERMINATED) and _computing_threads():
        # a single-partition stage still computing in a thread of this process: not waited for (it would finish
        # its stage first); what it writes is invisible until committed, and nothing commits any more
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        logging.shutdown()
        os._exit(code)
    if code:
        sys.exit(code)


def quiet_resource_tracker() -> None:
    """The process multiprocessing starts to track its semaphores (at the first one, with this process's warning
    options) unlinks those a signal left behind, and warns about each as it does (``UserWarning: resource_tracker:
    There appear to be 3 leaked semaphore objects``, two lines after an interrupted build's one line). The clean-up
    is its job; the warning is not for a user: it is filtered in that process only."""
    option = "ignore::UserWarning:multiprocessing.resource_tracker"
    if option not in sys.warnoptions:
        sys.warnoptions.append(option)


def _computing_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t is not threading.main_thread() and not t.daemon and t.is_alive()]
