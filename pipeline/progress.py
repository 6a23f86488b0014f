"""Progress of long work, on stderr, and the closing summaries of runs.

One facility for every long command, ``StageProgress``: a row per task (a stage, a drive check, a gate's
evaluation, an export) with its counts where the work is countable (``done/total``), the step it is in (with the
step's own counts), the time since it started and an estimate of the time left (elapsed x remaining / done).
- On a terminal: a live display (rich), redrawn a few times a second.
- Elsewhere (cron, a systemd unit, a pipe): plain timestamped lines, so a log file reads well: a task's start,
  each new step, its counts at most every ``every_s`` seconds (``CORNERMAP_PROGRESS_EVERY_S``, default 30), its
  end with the time it took. ``CORNERMAP_PROGRESS=live|plain|off`` overrides the choice.
Progress never goes to stdout: stdout holds a command's results (``--json`` keeps it machine-clean).

Library code reports into the display a command opened without being handed it: ``report``, ``finish`` and
``event`` do nothing when none is open (a library call, a pool process, ``--quiet``). A display opened while
another is open joins it (a rebuild's build shows in the rebuild's display).
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

_ACTIVE: list["StageProgress"] = []  # the open displays of this process, innermost last
PLAIN_EVERY_S = 30.0


def hms(seconds: float) -> str:
    s = int(round(max(0.0, seconds)))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


def count(n: int | None) -> str:
    """A count as a person reads it: 950, 12k, 4.5M."""
    if n is None:
        return "?"
    if n >= 1_000_000:
        return f"{n / 1e6:.1f}M"
    if n >= 10_000:
        return f"{n / 1e3:.0f}k"
    return str(n)


def eta_s(elapsed_s: float, done: int | None, total: int | None, since_s: float = 0.0) -> float | None:
    """The time left at the pace so far: ``done`` of ``total`` took ``elapsed_s``, so the rest takes
    elapsed x remaining / done, less the ``since_s`` gone by since ``done`` was reached. None when it cannot be told
    (nothing done yet, all done, under a second of pace)."""
    if not total or not done or done >= total or elapsed_s < 1.0:
        return None
    return max(0.0, elapsed_s * (total - done) / done - since_s)


@dataclass
class _Row:
    label: str
    t0: float
    done: int | None = None
    total: int | None = None
    done_t: float = 0.0  # when ``done`` last changed
    step: str | None = None
    step_done: int | None = None
    step_total: int | None = None
    step_t0: float = 0.0
    step_done_t: float = 0.0
    t_end: float | None = None
    note: str | None = None
    last_plain: float = field(default=0.0)

    def counts(self) -> str:
        return f"{count(self.done)}/{count(self.total)}" if self.total is not None else ""

    def set_counts(self, done: int | None, total: int | None, now: float) -> None:
        if done != self.done:
            self.done_t = now
        self.done, self.total = done, total

    def set_step_counts(self, done: int | None, total: int | None, now: float) -> None:
        if done != self.step_done:
            self.step_done_t = now
        self.step_done, self.step_total = done, total

    def step_text(self, now: float) -> str:
        if not self.step:
            return self.note or ""
        text = self.step
        if self.step_total is not None:
            text += f" {count(self.step_done)}/{count(self.step_total)}"
            left = eta_s(self.step_done_t - self.step_t0, self.step_done, self.step_total, now - self.step_done_t)
            if left is not None:
                text += f" (~{hms(left)} left)"
        return text

    def elapsed(self, now: float) -> float:
        return (self.t_end if self.t_end is not None else now) - self.t0

    def eta(self, now: float) -> float | None:
        if self.t_end is not None:
            return None
        return eta_s(self.done_t - self.t0, self.done, self.total, now - self.done_t)


def _mode(stream: TextIO) -> str:
    forced = os.environ.get("CORNERMAP_PROGRESS", "").strip().lower()
    if forced in ("live", "plain", "off"):
        return forced
    try:
        tty = stream.isatty()
    except (AttributeError, ValueError):
        tty = False
    return "live" if tty and os.environ.get("TERM", "") != "dumb" else "plain"


class StageProgress:
    """A progress display (see the module's docstring). ``update(label, done, total)`` is the engine's progress
    callback (stages' partitions); ``step`` names what a row does now; ``finish`` ends a row; ``event`` prints one
    line (above a live display)."""

    def __init__(self, enabled: bool = True, *, stream: TextIO | None = None, mode: str | None = None,
                 every_s: float | None = None):
        self.stream = stream if stream is not None else sys.stderr
        self.mode = "off" if not enabled else (mode or _mode(self.stream))
        self.every_s = every_s if every_s is not None else float(os.environ.get("CORNERMAP_PROGRESS_EVERY_S",
                                                                                PLAIN_EVERY_S))
        self._rows: dict[str, _Row] = {}
        self._lock = threading.RLock()
        self._live = None
        self._tasks: dict[str, Any] = {}
        self._joined: StageProgress | None = None
        self._log_streams: list = []  # (logging handler, its stream) while a live display shows its lines

    # -- opening and closing ------------------------------------------------------------------------------
    def __enter__(self) -> "StageProgress":
        if _ACTIVE:  # a command's display is open: report into it
            self._joined = _ACTIVE[-1]
        elif self.mode == "live":
            self._live = _live_display(self.stream)
            self._live.__enter__()
            self._log_streams = _log_above(self._live)
        if self.mode != "off" or self._joined is not None:
            _ACTIVE.append(self)
        return self

    def __exit__(self, *exc) -> None:
        if self in _ACTIVE:
            _ACTIVE.remove(self)
        if self._live is not None:
            for row in list(self._rows.values()):
                if row.t_end is None:  # left unfinished (an error, a stop): its time freezes where it stopped
                    row.t_end = time.monotonic()
            for handler, stream in self._log_streams:
                handler.setStream(stream)
            self._live.__exit__(*exc)
            self._live = None

    @property
    def enabled(self) -> bool:
        return self.mode != "off" or self._joined is not None

    # -- reporting -----------------------------------------------------------------------------------------
    def __call__(self, label: str, done: int, total: int) -> None:
        self.update(label, done, total)

    def update(self, label: str, done: int | None, total: int | None) -> None:
        """A countable row: ``done`` of ``total`` (a stage's partitions, an export's tiles)."""
        if self._joined is not None:
            return self._joined.update(label, done, total)
        if self.mode == "off":
            return
        with self._lock:
            row, new = self._row(label)
            if row.t_end is not None and total is not None and done is not None and done < total:
                row.t_end = None  # more work arrived (a streaming stage's next drive)
            row.set_counts(done, total, time.monotonic())
            self._show(row, "started" if new else None)

    def step(self, label: str, step: str, done: int | None = None, total: int | None = None) -> None:
        """What row ``label`` does now, with the step's own counts when it has them."""
        if self._joined is not None:
            return self._joined.step(label, step, done, total)
        if self.mode == "off":
            return
        with self._lock:
            row, new = self._row(label)
            changed = step != row.step
            now = time.monotonic()
            if changed:
                row.step, row.step_t0, row.step_done = step, now, None
            row.set_step_counts(done, total, now)
            self._show(row, "started" if new else ("step" if changed else None))

    def finish(self, label: str, note: str | None = None) -> None:
        """Row ``label`` is done (its time stops; ``note`` replaces its step text)."""
        if self._joined is not None:
            return self._joined.finish(label, note)
        if self.mode == "off":
            return
        with self._lock:
            row, _ = self._row(label)
            if row.t_end is not None:
                return
            row.t_end, row.step, row.note = time.monotonic(), None, note
            self._show(row, "done")

    def event(self, text: str) -> None:
        """One line: printed above a live display, or as a timestamped line."""
        if self._joined is not None:
            return self._joined.event(text)
        if self.mode == "off":
            return
        with self._lock:
            if self._live is not None:
                self._live.console.print(text, markup=False, highlight=False, soft_wrap=True)
            else:
                self._write(text)

    # -- rendering -----------------------------------------------------------------------------------------
    def _row(self, label: str) -> tuple[_Row, bool]:
        row = self._rows.get(label)
        if row is None:
            row = self._rows[label] = _Row(label, time.monotonic())
            if self._live is not None:
                self._tasks[label] = self._live.add_task(label, total=None, row=row)
            return row, True
        return row, False

    def _show(self, row: _Row, what: str | None) -> None:
        now = time.monotonic()
        if self._live is not None:  # the bar: the row's counts, else its step's, else full once it ended
            done, total = (row.done, row.total) if row.total is not None else (row.step_done, row.step_total)
            if total is None and row.t_end is not None:
                done, total = 1, 1
            self._live.update(self._tasks[row.label], completed=done or 0, total=total)
            return
        if what is None and now - row.last_plain < self.every_s:
            return
        row.last_plain = now
        if what == "done":
            text = " ".join(p for p in ("done", row.counts(), f"in {hms(row.elapsed(now))}") if p)
            self._write(f"{row.label}: {text}" + (f" ({row.note})" if row.note else ""))
            return
        parts = [row.counts()] if row.total is not None else []
        if row.step:
            parts.append(row.step_text(now))
        if what == "started":
            parts.insert(0, "started")
        else:
            parts.append(f"{hms(row.elapsed(now))} elapsed")
            left = row.eta(now)
            if left is not None:
                parts.append(f"~{hms(left)} left")
        self._write(f"{row.label}: " + ", ".join(p for p in parts if p))

    def _write(self, text: str) -> None:
        stamp = time.strftime("%Y-%m-%d %H:%M:%S")
        try:
            self.stream.write(f"{stamp} {text}\n")
            self.stream.flush()
        except (OSError, ValueError):  # a closed or broken stream: progress is not worth failing the run for
            pass


def _log_above(progress) -> list:
    """Point the logging handlers that write to the terminal's stderr at the live display's stderr, which prints each
    line above the display (a log line written past it would break the display's redraw); returns what to restore."""
    import logging

    swapped = []
    for handler in logging.getLogger().handlers:
        if (isinstance(handler, logging.StreamHandler) and handler.stream in (sys.__stderr__, progress.console.file)
                and sys.stderr is not handler.stream):
            swapped.append((handler, handler.setStream(sys.stderr)))
    return swapped


def _live_display(stream: TextIO):
    from rich.console import Console
    from rich.progress import BarColumn, Progress, ProgressColumn, TextColumn
    from rich.text import Text

    class _Counts(ProgressColumn):
        def render(self, task) -> Text:
            return Text(task.fields["row"].counts(), style="progress.download")

    class _Step(ProgressColumn):
        def render(self, task) -> Text:
            return Text(task.fields["row"].step_text(time.monotonic()), style="cyan", overflow="ellipsis",
                        no_wrap=True)

    class _Times(ProgressColumn):
        def render(self, task) -> Text:
            row, now = task.fields["row"], time.monotonic()
            left = row.eta(now)
            text = hms(row.elapsed(now)) + (f"  ~{hms(left)} left" if left is not None else "")
            return Text(text, style="progress.elapsed" if row.t_end is None else "green")

    console = Console(file=stream, stderr=stream is sys.stderr)
    return Progress(TextColumn("{task.description:>12}"), BarColumn(bar_width=24), _Counts(), _Times(), _Step(),
                    console=console, transient=False, refresh_per_second=4, redirect_stdout=False,
                    redirect_stderr=True)


# -- library code reports into the open display ---------------------------------------------------------------
def active() -> StageProgress | None:
    """The display a command opened in this process, or None."""
    return _ACTIVE[-1] if _ACTIVE else None


def report(label: str, done: int | None = None, total: int | None = None, *, step: str | None = None) -> None:
    """Row ``label``: its counts, or (with ``step``) the step it is in with the step's counts. No display: nothing."""
    p = active()
    if p is None:
        return
    if step is None:
        p.update(label, done, total)
    else:
        p.step(label, step, done, total)


def finish(label: str, note: str | None = None) -> None:
    p = active()
    if p is not None:
        p.finish(label, note)


def event(text: str) -> None:
    p = active()
    if p is not None:
        p.event(text)


_PLAIN_LINE = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d (.+)$")  # what a plain display writes


def run_child(cmd: list[str], label: str | None = None, step: str = "") -> subprocess.CompletedProcess:
    """Command ``cmd`` (a command line of this package's app, ``mapservice.child.run_cornermap``) in a child process,
    its output captured (text). With a display open and a ``label``, the child's own progress shows live as that
    row's step (after ``step``), and the child's other stderr lines (its error line) are the result's ``stderr``;
    without, the child shows none. The child ends itself within a second once this process is gone
    (``pipeline.parallel.exit_with_parent_from_env``, which the app's ``__main__`` starts): a SIGKILLed parent leaves
    no child running."""
    from pipeline.parallel import EXIT_WITH_PARENT_VARIABLE

    own = {**os.environ, EXIT_WITH_PARENT_VARIABLE: str(os.getpid())}  # the child ends once this process is gone
    display = active()
    if display is None or label is None:
        return subprocess.run(cmd, capture_output=True, text=True, env={**own, "CORNERMAP_PROGRESS": "off"})
    env = {**own, "CORNERMAP_PROGRESS": "plain", "CORNERMAP_PROGRESS_EVERY_S": "2"}
    kept: list[str] = []

    def relay(stream) -> None:
        for line in stream:
            m = _PLAIN_LINE.match(line.rstrip("\n"))
            if m:
                display.step(label, f"{step}: {m.group(1)}" if step else m.group(1))
            else:
                kept.append(line)

    with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env) as proc:
        reader = threading.Thread(target=relay, args=(proc.stderr,), name="cornermap-child-progress", daemon=True)
        reader.start()
        try:
            out = proc.stdout.read()
            proc.wait()
        except BaseException:  # a stop (SIGINT, SIGTERM) of this command ends the child too
            proc.kill()
            raise
        reader.join()
    return subprocess.CompletedProcess(cmd, proc.returncode, out, "".join(kept))


# -- summaries --------------------------------------------------------------------------------------------------
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


def summary_lines(summary: dict[str, Any], root: Path, wall_s: float | None = None,
                  cpu_s: float | None = None) -> list[str]:
    """The closing summary of a run, one line per stage: decision, partitions (computed / reused), wall and CPU
    seconds, peak memory of its largest task; then the run's totals. Plain text: it reads the same in a terminal
    and in a log file."""
    lines = [f"run (root {root}):",
             f"  {'stage':12s} {'decision':9s} {'partitions':>14s} {'wall s':>9s} {'CPU s':>9s} {'peak MB':>8s}"]
    for stage, s in summary.items():
        if s.get("decision") != "ran":
            lines.append(f"  {stage:12s} {'skipped':9s} {'(committed)':>14s}")
            continue
        n, reused = s.get("partitions", 0), s.get("partitions_reused", 0)
        parts = f"{n}" + (f" ({reused} reused)" if reused else "")
        peak = s.get("peak_rss_mb")
        lines.append(f"  {stage:12s} {'ran':9s} {parts:>14s} {s.get('wall_s', 0.0):9.1f} {s.get('cpu_s', 0.0):9.1f} "
                     f"{peak if peak is not None else '-':>8}")
    if wall_s is not None:
        lines.append(f"  {'total':12s} {'':9s} {'':>14s} {wall_s:9.1f} {cpu_s if cpu_s is not None else 0.0:9.1f}")
    return lines


def outcome_lines(plan) -> list[str]:
    """What stages said about their products (a published map version, a report path), once per stage.
    ``{root}`` in a stage's line is the plan's root (stages store root-relative paths: a moved root still prints
    true paths); a stage skipped as committed says its line is from an earlier run."""
    from pipeline.store import data_root

    out = []
    for sp in plan.stages.values():
        if not sp.selected:
            continue
        for ds in sp.outputs.values():
            m = data_root(plan.uri).manifest(ds, sp.fingerprint)
            if not m:
                continue
            parts = (m.get("extra") or {}).get("partitions") or {}
            for label in sorted(parts):
                for line in parts[label].get("outcome", []):
                    line = line.replace("{root}", plan.uri)
                    out.append(line if sp.ran else f"unchanged (committed by an earlier run): {line}")
            break
    return out


def print_outcomes(plan) -> None:
    for line in outcome_lines(plan):
        print(line)
