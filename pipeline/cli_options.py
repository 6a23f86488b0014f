"""The command-line options every command shares, defined once (rasterio's ``rio/options.py`` is the model).

Conventions (every command):
- ``-h`` / ``--help``; ``--version`` at the top only: the program's version (``cornermap --version``).
- ``--root ROOT`` (env ``CORNERMAP_ROOT``) names the output root (``ROOT/datasets``, ``ROOT/maps/NAME``): required
  by every command that reads or writes one; ``run`` and ``<stage> run`` take the workflow's own root without it.
- ``--map NAME`` / ``-m``; a map's version is ``--map-version`` (LATEST, vNNNN or N). ``--version`` where a map
  version was meant is a usage error naming ``--map-version``.
- ``--quiet`` / ``-q`` on every long command: no progress display (results and errors are still printed).
- ``--json`` where a machine reads the result: stdout holds one JSON document and nothing else.
- ``--params FILE`` on every command that builds: ``{stage: {param: value}}`` over the workflow's params.
Exit codes: 0 ok, 1 error, 2 usage (the command line is wrong), 3 data quality, 75 locked, 130 interrupted
(SIGINT), 143 terminated (SIGTERM).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, Optional

import typer

from pipeline.errors import OptionError

ROOT_HELP = "Output root holding datasets/ and maps/NAME/ (env CORNERMAP_ROOT)."



def _local_only(option: str):
    """A callback refusing a URI (``s3://bucket/root``) with a usage error naming ``option``: a command that does not
    read or write object storage must not take the URI for the relative folder ``s3:/bucket/root``."""

    def check(ctx: typer.Context, param: Any, value: Any) -> Any:
        if value is not None and not ctx.resilient_parsing:
            from pipeline.storage import refuse_uri

            refuse_uri(value, option)
        return value

    return check


def _store_uri(option: str):
    """``_store_root`` for another option than ``--root`` (``--inbox``)."""

    def check(ctx: typer.Context, param: Any, value: Any) -> Any:
        return _store_value(ctx, value, option)

    return check


def _store_root(ctx: typer.Context, param: Any, value: Any) -> Any:
    return _store_value(ctx, value, "--root")


def _store_value(ctx: typer.Context, value: Any, option: str) -> Any:
    """A root that may be a local folder or an ``s3://`` URI: the URI kept whole (typer's ``Path`` would collapse
    ``s3://`` to ``s3:/``); an unsupported scheme is a usage error."""
    if value is None or ctx.resilient_parsing:
        return value
    from pipeline.storage import SCHEMES, normalise_uri, refuse_uri, uri_scheme

    scheme = uri_scheme(value)
    if scheme is None:
        return Path(value)
    if scheme not in SCHEMES:
        refuse_uri(value, option, "a local folder or an s3://BUCKET/PREFIX URI")
    return normalise_uri(value)


ROOT = typer.Option(..., "--root", envvar="CORNERMAP_ROOT", show_envvar=False, help=ROOT_HELP,
                    callback=_local_only("--root"))
ROOT_OF_WORKFLOW = typer.Option(None, "--root", envvar="CORNERMAP_ROOT", show_envvar=False,
                                help=ROOT_HELP + " Default: the workflow's root.", callback=_local_only("--root"))
ROOT_OF_WORKFLOW_OR_URI = typer.Option(None, "--root", envvar="CORNERMAP_ROOT", show_envvar=False, callback=_store_root,
                                       help=ROOT_HELP + " A folder or s3://BUCKET/PREFIX (endpoint and credentials "
                                       "from the AWS environment). Default: the workflow's root.")
# Commands that read a root on object storage too (tiles ls|verify|log|export, maps show): a str, not a Path.
ROOT_OR_URI = typer.Option(..., "--root", envvar="CORNERMAP_ROOT", show_envvar=False, callback=_store_root,
                           help="Output root holding datasets/ and maps/NAME/: a folder or s3://BUCKET/PREFIX "
                           "(endpoint and credentials from the AWS environment; env CORNERMAP_ROOT).")
INBOX = typer.Option(..., "--inbox", callback=_local_only("--inbox"),
                     help="Folder of drive folders (each with a drive.yaml); "
                     "bad ones move to INBOX/quarantine/.")
INBOX_OR_URI = typer.Option(..., "--inbox", callback=_store_uri("--inbox"),
                            help="Folder of drive folders (each with a drive.yaml), or s3://BUCKET/PREFIX of drive "
                            "prefixes; bad ones move to INBOX/quarantine/.")
MAP = typer.Option(..., "--map", "-m", help="Map name (ROOT/maps/NAME).")
MAP_OR_ONLY = typer.Option(None, "--map", "-m", help="Map name (ROOT/maps/NAME); default: the only map there.")
MAP_VERSION = typer.Option("LATEST", "--map-version", help="The map's version: LATEST, vNNNN or N.")
QUIET = typer.Option(False, "--quiet", "-q", help="No progress display (results and errors are still printed).")
JSON = typer.Option(False, "--json", help="Print the result as one JSON document on stdout (nothing else goes "
                    "there; progress and messages go to stderr).")
PARAMS = typer.Option(None, "--params", help="YAML file {stage: {param: value}} over the workflow's params "
                      "(cornermap STAGE params lists them).")
SCHEDULER = typer.Option(None, "--scheduler", help="local (processes sized to the machine) | sync | threads | "
                         "distributed (a local dask.distributed cluster) | tcp://HOST:PORT (a running scheduler)")
WORKERS = typer.Option(None, "--workers", min=1, help="Processes (or threads) of a local scheduler; default: the "
                       "machine's cores.")
DASK_HOST = typer.Option("127.0.0.1", "--dask-host", help="With --scheduler distributed: the address its "
                         "scheduler, workers and dashboard listen on (0.0.0.0: every interface, unauthenticated).")


def _refuse_version(ctx: typer.Context, param: Any, value: Optional[str]) -> None:
    if value is not None and not ctx.resilient_parsing:
        raise OptionError("--version", [f"is the program's version (cornermap --version); a map's version is "
                                        f"--map-version {value}"])


# Where a map version is an option: the old spelling, hidden, answered with a usage error that names the new one.
MOVED_VERSION = typer.Option(None, "--version", hidden=True, callback=_refuse_version, is_eager=True)


def echo_json(doc: Any) -> None:
    """The one JSON document of a ``--json`` command, on stdout."""
    sys.stdout.write(json.dumps(doc, indent=1, default=_plain) + "\n")
    sys.stdout.flush()


def _plain(value: Any) -> Any:
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")
