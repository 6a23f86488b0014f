"""Every example in the CLI's help and in the README runs as written, from a folder outside the checkout.

In the default suite every example is parsed against the CLI (commands, options, required values: what broke
``cornermap ingest inspect``); running them all (a tiny build, two evaluations: ~8 minutes) is ``slow``.

Examples are the ``cornermap ...`` commands of the README's code blocks, and in help texts the ones at the start
of a line, after ``Example:`` / ``Examples:``, or in ``[b]...[/b]``. They share one convention (a tiny city):
``runs/sim`` (simulated drives), ``runs/maps`` (map ``city`` built from them), ``runs/tiny`` (the packaged tiny
workflow's root with map ``tiny``); ``../shared/data`` is the real samples. The examples that make those run
first; a dask scheduler is started on 127.0.0.1:8786 for the one that names it.
"""
from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CORNERMAP = str(Path(sys.executable).parent / "cornermap")
SETUP = ("cornermap simulate --preset tiny --seed 7 --out runs/sim",
         "cornermap build --drive runs/sim/drive_0/drive.yaml --map city --root runs/maps",
         "cornermap run tiny --root runs/tiny")
_HELP_EXAMPLE = re.compile(r"(?:^[ \t]*|Examples?:\s*|\[b\])(cornermap [^\n\[;]*)", re.M)


def readme_examples() -> list[str]:
    blocks = re.findall(r"```bash\n(.*?)```", (REPO / "README.md").read_text(), re.S)
    lines = [ln.split(" #")[0].strip() for b in blocks for ln in b.splitlines()]
    return [ln for ln in lines if ln.startswith("cornermap ")]


def help_examples() -> list[str]:
    import typer

    from mapservice.cli import _register_stages, app

    _register_stages()

    def walk(cmd):
        yield cmd
        for sub in getattr(cmd, "commands", {}).values():
            yield from walk(sub)

    out = []
    for cmd in walk(typer.main.get_command(app)):
        text = f"{cmd.help or ''}\n{cmd.epilog or ''}"
        out += [m.strip().rstrip(".") for m in _HELP_EXAMPLE.findall(text)]
    return out


def ordered_examples() -> list[str]:
    found = list(dict.fromkeys(readme_examples() + help_examples()))
    first = [e for prefix in SETUP for e in found if e.startswith(prefix)]
    return list(dict.fromkeys(first + found))


def test_examples_are_found_and_follow_one_map_convention():
    examples = ordered_examples()
    assert len(examples) >= 25, examples
    for prefix in SETUP:
        assert any(e.startswith(prefix) for e in examples), prefix
    for e in examples:  # a map is named by --root ROOT --map NAME everywhere, never by a path
        m = re.search(r"--map (\S+)", e)
        assert m is None or "/" not in m.group(1), e


def _parse(command, info_name: str, args: list[str]) -> None:
    """Parse ``args`` as click would before invoking: unknown commands/options and missing values raise."""
    ctx = command.make_context(info_name, list(args))
    protected = getattr(ctx, "_protected_args", None) or getattr(ctx, "protected_args", None) or []
    rest = list(protected) + list(ctx.args)
    if hasattr(command, "resolve_command") and rest:
        name, sub, tail = command.resolve_command(ctx, rest)
        _parse(sub, name, tail)


def test_every_example_parses_against_the_cli():
    import typer

    from mapservice.cli import _register_stages, app

    _register_stages()
    root = typer.main.get_command(app)
    failures = []
    for example in ordered_examples():
        try:
            _parse(root, "cornermap", shlex.split(example)[1:])
        except Exception as exc:  # noqa: BLE001 - collected and reported together
            if type(exc).__name__ == "Exit" and getattr(exc, "exit_code", 1) == 0:  # --help: parsed, answered
                continue
            failures.append(f"{example}: {type(exc).__name__}: {exc}")
    assert not failures, "\n".join(failures)


@pytest.fixture(scope="module")
def scheduler():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, scheduler_port=8786,
                                  host="127.0.0.1", dashboard_address=None) as cluster:
        yield cluster


@pytest.mark.slow
def test_every_example_runs_as_written(tmp_path, scheduler):
    cwd = tmp_path / "work"
    cwd.mkdir()
    shared = REPO.parent / "shared"
    if shared.is_dir():
        (tmp_path / "shared").symlink_to(shared)  # ../shared/data from the examples' folder (a link, no copy)
    env = {k: v for k, v in os.environ.items() if k not in ("CORNERMAP_EXTRA_STAGES",)}
    env["COLUMNS"] = "200"
    failures = []
    for example in ordered_examples():
        args = shlex.split(example)
        if "../shared/data" in example and not shared.is_dir():
            continue
        if "s3://" in example:  # the README's object-storage section: run whole, with its S3 server and cluster,
            continue  # by tests/test_s3_readme.py
        out = subprocess.run([CORNERMAP] + args[1:], cwd=cwd, env=env, capture_output=True, text=True, timeout=900)
        if out.returncode != 0:
            failures.append(f"{example}\n  exit {out.returncode}: {(out.stderr or out.stdout).strip()[-600:]}")
    assert not failures, "\n".join(failures)
