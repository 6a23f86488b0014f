"""Progress display (partitions done / total per stage) and run summaries, with rich."""
from __future__ import annotations

from pathlib import Path
from typing import Any


class StageProgress:
    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self._progress = None
        self._tasks: dict[str, Any] = {}

    def __enter__(self) -> "StageProgress":
        if self.enabled:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

            self._progress = Progress(TextColumn("{task.description:>12}"), BarColumn(), MofNCompleteColumn(),
                                      TimeElapsedColumn(), transient=False)
            self._progress.__enter__()
        return self

    def update(self, label: str, done: int, total: int) -> None:
        if self._progress is None:
            return
        if label not in self._tasks:
            self._tasks[label] = self._progress.add_task(label, total=total)
        self._progress.update(self._tasks[label], completed=done, total=total)

    def __exit__(self, *exc) -> None:
        if self._progress is not None:
            self._progress.__exit__(*exc)


def print_plan(rows: list[dict[str, Any]], root: Path, summary: dict | None = None) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"plan (root {root})" if summary is None else f"run (root {root})")
    for col in ("stage", "fingerprint", "partitions", "decision", "outputs"):
        table.add_column(col)
    for r in rows:
        decision = r["decision"]
        if summary and r["stage"] in summary:
            decision = summary[r["stage"]]["decision"]
        table.add_row(r["stage"], r["fingerprint"], r["partitions"], decision, r["outputs"])
    Console().print(table)


def print_outcomes(plan) -> None:
    """Print what stages said about their products (a published map version, a report path), once per stage.
    ``{root}`` in a stage's line is the plan's root (stages store root-relative paths: a moved root still prints
    true paths); a stage skipped as committed says its line is from an earlier run."""
    from pipeline.store import dataset_dir, read_manifest

    for sp in plan.stages.values():
        if not sp.selected:
            continue
        for ds in sp.outputs.values():
            m = read_manifest(dataset_dir(plan.root, ds, sp.fingerprint))
            if not m:
                continue
            parts = (m.get("extra") or {}).get("partitions") or {}
            for label in sorted(parts):
                for line in parts[label].get("outcome", []):
                    line = line.replace("{root}", str(plan.root))
                    print(line if sp.ran else f"unchanged (committed by an earlier run): {line}")
            break
