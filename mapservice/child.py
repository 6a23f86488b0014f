"""``cornermap ARGS`` in a child process (``python -m mapservice``): the rebuild's drive checks and the gate's runs of
stage commands, with the child's progress relayed to the parent's display (``pipeline.progress.run_child``)."""

from __future__ import annotations

import subprocess
import sys


def run_cornermap(args: list[str], label: str | None = None, step: str = "") -> subprocess.CompletedProcess:
    """``cornermap ARGS`` in a child process, its output captured (text); the child ends itself within a second once
    this process is gone (``pipeline.parallel.exit_with_parent_from_env``, started by ``python -m mapservice``): a
    SIGKILLed rebuild leaves no child running. ``label`` and ``step``: ``pipeline.progress.run_child``."""
    from pipeline.progress import run_child

    return run_child([sys.executable, "-m", "mapservice", *args], label=label, step=step)
