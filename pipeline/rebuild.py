"""``cornermap rebuild``: new drives from an inbox in, a checked new map version out, in the map's pinned frame.

One run, under the map's whole-run lock (``pipeline.maps.run_lock``, exit 75 when held):
  1. free-disk check (``min_free_gib``, exit 1 with the numbers);
  2. every map drive must still be where the identity says, with the same content fingerprint (exit 1);
  3. inbox drive folders (``INBOX/*/drive.yaml``) whose fingerprint is not in the map are new; each is checked
     (``cornermap drive check``); a bad one is moved to ``INBOX/quarantine/`` with ``<folder>.reason.txt``;
  4. no new good drive: one line, exit 0, nothing written;
  5. the map workflow runs on all the map's drives in the pinned frame with ``hold_latest``: the candidate is
     published as version N+1 but LATEST stays (per-drive work of old drives is reused: pipeline/reuse.py);
  6. the regression gate (``pipeline.gate``) localizes the check drive (the identity's, else the newest new
     drive) on the candidate and on LATEST; worse beyond tolerance: exit 3, LATEST unchanged;
  7. LATEST moves to the verified candidate, then the identity records the new drives.
A run killed at any point leaves LATEST naming a complete version; the next run finds the same drives new
and completes from the committed work (a candidate LATEST already names is only recorded).
This module calls the stages through the command line (``python -m pipeline ...``), never by import.
"""
from __future__ import annotations

import logging
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.errors import ConfigError, DataQualityError
from pipeline.maps import MapDrive, check_free_disk, map_dir, require_identity, run_lock, utc_now, write_identity

log = logging.getLogger(__name__)

QUARANTINE = "quarantine"


@dataclass(frozen=True)
class RebuildParams:
    min_free_gib: float = 2.0
    gate: bool = True
    gate_tol_m: float = 0.05  # a figure may grow by max(gate_tol_m, gate_tol_rel * previous) before refusal
    gate_tol_rel: float = 0.2
    workflow: str = "map_rebuild"
    scheduler: str | None = None
    params_file: Path | None = None  # --params: {stage: {param: value}} over the workflow's
    workers: int | None = None
    dask_host: str = "127.0.0.1"


@dataclass
class RebuildResult:
    status: str  # "nothing" | "published" | "refused"
    lines: list[str] = field(default_factory=list)
    version: int | None = None
    quarantined: list[str] = field(default_factory=list)
    summary: dict = field(default_factory=dict)  # the build's run summary (stage decisions and times)

    @property
    def exit_code(self) -> int:
        return 3 if self.status == "refused" else 0


def cli(*args: str) -> subprocess.CompletedProcess:
    """Run ``cornermap ARGS`` in a child process (the stages' own commands, without importing them)."""
    return subprocess.run([sys.executable, "-m", "pipeline", *args], capture_output=True, text=True)


def inbox_drives(inbox: Path) -> list[Path]:
    """``INBOX/*/drive.yaml`` in name order, without the quarantine folder."""
    if not inbox.is_dir():
        raise ConfigError("--inbox", [f"{inbox}: not a directory"])
    return sorted(p for p in inbox.glob("*/drive.yaml") if p.parent.name != QUARANTINE)


def quarantine(drive_yaml: Path, inbox: Path, reason: str) -> Path:
    """Move the drive folder to INBOX/quarantine/ (a new name if taken) and write its reason file beside it."""
    qdir = inbox / QUARANTINE
    qdir.mkdir(exist_ok=True)
    src = drive_yaml.parent
    dst = qdir / src.name
    if dst.exists():
        dst = qdir / f"{src.name}-{utc_now().replace(':', '')}"
    src.rename(dst)
    tmp = qdir / f".{dst.name}.reason.tmp"
    tmp.write_text(f"{utc_now()} quarantined by cornermap rebuild: {reason.strip()}\n", encoding="utf-8")
    tmp.replace(qdir / f"{dst.name}.reason.txt")
    return dst


def _known_drive_problems(ident) -> list[str]:
    from pipeline.fingerprint import drive_fingerprint

    problems = []
    for d in ident.drives:
        if not Path(d.path).is_file():
            problems.append(f"map drive {d.name}: {d.path} is gone; the map needs every drive it was built from")
        elif drive_fingerprint(Path(d.path)) != d.fingerprint:
            problems.append(f"map drive {d.name}: {d.path} changed content since it was added (fingerprint "
                            f"{d.fingerprint[:12]}); restore it, or make a new map")
    return problems


def select_new_drives(ident, inbox: Path) -> tuple[list[tuple[Path, str]], list[tuple[Path, str]]]:
    """(new good drives as (drive.yaml, fingerprint), bad ones as (drive.yaml, reason)); checks each new one."""
    from pipeline.fingerprint import drive_fingerprint
    from pipeline.names import name_problem
    from pipeline.progress import finish, report

    known = {d.fingerprint for d in ident.drives}
    names = {d.name for d in ident.drives}
    good, bad = [], []
    delivered = inbox_drives(inbox)
    for i, path in enumerate(delivered):
        report("inbox", i, len(delivered), step=f"checking {path.parent.name}")
        fp = drive_fingerprint(path)
        if fp in known:
            continue
        name = path.parent.name
        problem = name_problem(name, "drive")
        if problem is None and name in names:
            problem = f"drive name {name!r} is taken by another drive of the map (rename the folder)"
        if problem is None:
            res = cli("drive", "check", str(path))
            if res.returncode != 0:
                problem = "drive check failed: " + " ".join((res.stderr or res.stdout).split())[:2000]
        if problem is None:
            good.append((path, fp))
            names.add(name)
        else:
            bad.append((path, problem))
    report("inbox", len(delivered), len(delivered))
    finish("inbox", f"{len(good)} new, {len(bad)} quarantined")
    return good, bad


def _candidate_version(plan) -> int:
    """The version the build's tiles stage published (read from its committed map_tiles dataset)."""
    import pyarrow.parquet as pq

    from pipeline.store import dataset_dir, read_manifest

    sp = next(sp for sp in plan.stages.values() if "map_tiles" in sp.outputs.values())
    d = dataset_dir(plan.root, "map_tiles", sp.fingerprint)
    m = read_manifest(d)
    rows = [r for f in m["files"] for r in pq.read_table(d / f["path"], columns=["version"]).to_pylist()]
    return int(rows[0]["version"])


def rebuild(root: Path, name: str, inbox: Path, params: RebuildParams = RebuildParams()) -> RebuildResult:
    from pipeline.build import write_build_workflow
    from pipeline.cli import execute_workflow
    from pipeline.gate import run_gate
    from pipeline.versioned import publish_lock, read_latest, verify_version, version_name, write_latest

    root, inbox = Path(root).resolve(), Path(inbox).resolve()
    mdir = map_dir(root, name)
    ident = require_identity(mdir)
    with run_lock(mdir):
        check_free_disk(root, params.min_free_gib)
        problems = _known_drive_problems(ident)
        if problems:
            raise ConfigError(f"map {name!r}", problems)
        good, bad = select_new_drives(ident, inbox)
        result = RebuildResult("nothing")
        for path, reason in bad:
            dst = quarantine(path, inbox, reason)
            result.quarantined.append(path.parent.name)
            result.lines.append(f"quarantined {path.parent.name} -> {dst} ({reason[:200]})")
        if not good:
            result.lines.append(f"nothing to do: no new drive in {inbox} for map {name!r} "
                                f"({len(ident.drives)} drive(s), LATEST {_latest_text(mdir)})")
            return result
        drives = [Path(d.path) for d in ident.drives] + [p for p, _ in good]
        wf = write_build_workflow(params.workflow, drives=drives, map_name=name, root=root,
                                  origin=ident.enu_origin.model_dump(), tile_size_m=ident.tile_size_m,
                                  hold_latest=True)
        run = execute_workflow(wf, root=root, scheduler=params.scheduler, only=None, dry_run=False, quiet=True,
                               params_file=params.params_file, workers=params.workers, dask_host=params.dask_host)
        result.summary = run["summary"]
        result.lines.append(reuse_line(run["summary"]))
        candidate = _candidate_version(run["plan"])
        previous = read_latest(mdir)
        if candidate != previous and previous is not None and params.gate:
            check = ident.check_drive
            drive, reference = (Path(check.path), check.reference) if check else (good[-1][0], None)
            verdict = run_gate(mdir, candidate, previous, drive, reference, params.gate_tol_m, params.gate_tol_rel)
            result.lines += verdict.table
            if not verdict.ok:
                result.status, result.version = "refused", candidate
                result.lines.append(f"refused: {version_name(candidate)} is worse than {version_name(previous)} on "
                                    f"{drive.parent.name}; LATEST stays {version_name(previous)}")
                return result
        if candidate != previous:
            with publish_lock(mdir):
                problems = verify_version(mdir / version_name(candidate))
                if problems:
                    raise DataQualityError(f"{mdir / version_name(candidate)}: {problems[0]}; LATEST unchanged")
                write_latest(mdir, candidate)
        added = [MapDrive(name=p.parent.name, path=str(p), fingerprint=fp, added_utc=utc_now(), added_in=candidate)
                 for p, fp in good]
        write_identity(mdir, ident.model_copy(update={"drives": list(ident.drives) + added}))
        result.status, result.version = "published", candidate
        result.lines.append(f"published map {name!r} {version_name(candidate)} (LATEST): {len(drives)} drive(s), "
                            f"added {', '.join(p.parent.name for p, _ in good)}")
        return result


def reuse_line(summary: dict) -> str:
    """One line: per stage, ran (partitions computed/reused, wall s) or skipped as committed."""
    parts = []
    for stage, s in summary.items():
        if s.get("decision") == "ran":
            n, r = s.get("partitions", 0), s.get("partitions_reused", 0)
            parts.append(f"{stage} {n - r} computed/{r} reused {s.get('wall_s', 0):.0f} s")
        else:
            parts.append(f"{stage} skipped")
    return "build: " + ", ".join(parts)


def _latest_text(mdir: Path) -> str:
    from pipeline.versioned import read_latest, version_name

    v = read_latest(mdir) if (mdir / "LATEST").exists() else None
    return version_name(v) if v is not None else "none"

