"""``cornermap rebuild``: new drives from an inbox in, a checked new map version out, in the map's pinned frame.

One run, under the map's writer locks (``mapservice.maps.run_lock``: the root shared, the map exclusive; exit 75 when
another writer holds either):
  1. free-disk check (``min_free_gib``, exit 1 with the numbers);
  2. every map drive must still be where the identity says with what it references unchanged (the fingerprint, or,
     when only that changed, the content of what its drive file references: ``drive check --content``; exit 1);
  3. the inbox's drive folders (``mapservice.inbox``: complete by the delivery protocol, links resolved and kept
     inside the inbox) not already in the map, by fingerprint or by content, are new; a second delivery of the same
     content is left alone; each new one is checked (``cornermap drive check``); a bad one is moved to
     ``INBOX/quarantine/`` with ``<folder>.reason.txt`` (in cornermap's words: never a line of the drive's files);
  4. no new good drive: one line, exit 0, nothing written;
  5. the map workflow runs on all the map's drives in the pinned frame with ``hold_latest``: the candidate is
     published as version N+1 but LATEST stays (per-drive work of old drives is reused: pipeline/reuse.py);
  6. the regression gate (``mapservice.gate``) localizes the check drive (the identity's, else the newest new
     drive) on the candidate and on LATEST; worse beyond tolerance: exit 3, LATEST unchanged;
  7. LATEST moves to the verified candidate, then the identity records the new drives.
Steps 6-7 are ``gate_and_publish``, which ``maps reoptimize`` (mapservice/reoptimize.py) publishes through too.
A run killed at any point leaves LATEST naming a complete version; the next run finds the same drives new
and completes from the committed work (a candidate LATEST already names is only recorded).
The root and the inbox may be ``s3://`` URIs: the map's identity, LATEST, gate records and locks (leases) are then
the bucket's (``mapservice.maps.MapHome``), the free-disk check is the local scratch folder's, the gate evaluates on a
local snapshot of both versions, and drives delivered to a bucket are read from a local copy
(``mapservice.inbox.StoreInbox``; docs/maintenance.md).
This module calls the stages through the command line (``python -m mapservice ...``), never by import; those child
processes end themselves when the rebuild is gone (``mapservice.child.run_cornermap``).
"""
from __future__ import annotations

import logging
import re
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from mapservice.inbox import DEFAULT_QUIET_PERIOD_S, QUARANTINE, Delivery, quarantine  # noqa: F401 - re-exported
from mapservice.maps import MapDrive, check_free_disk, utc_now
from pipeline import storage
from pipeline.errors import ConfigError, StageError

log = logging.getLogger(__name__)

_CONTENT_RE = re.compile(r"^content: sha256 ([0-9a-f]{64})", re.M)


@dataclass(frozen=True)
class RebuildParams:
    min_free_gib: float = 2.0
    gate: bool = True
    gate_tol_m: float = 0.05  # a figure may grow by max(gate_tol_m, gate_tol_rel * previous) before refusal
    gate_tol_rel: float = 0.2
    workflow: str = "map_rebuild"
    scheduler: str | None = None
    quiet_period_s: float = DEFAULT_QUIET_PERIOD_S  # a drive folder is taken after this long without a change
    params_file: Path | None = None  # --params: {stage: {param: value}} over the workflow's
    workers: int | None = None
    dask_host: str = "127.0.0.1"
    # False (the default): incremental, the new drives solved against LATEST's poses held fixed; True: every map
    # drive solved jointly again (``--full``; ``held_solution`` is the hook a scheduled re-optimization uses)
    full: bool = False


@dataclass
class RebuildResult:
    status: str  # "nothing" | "published" | "refused"
    lines: list[str] = field(default_factory=list)
    version: int | None = None
    quarantined: list[str] = field(default_factory=list)
    summary: dict = field(default_factory=dict)  # the build's run summary (stage decisions and times)
    say: Callable[[str], None] | None = field(default=None, repr=False)  # each line also goes here as it is made

    def add(self, *lines: str) -> None:
        for line in lines:
            self.lines.append(line)
            if self.say is not None:
                self.say(line)

    @property
    def exit_code(self) -> int:
        return 3 if self.status == "refused" else 0


def cli(*args: str) -> subprocess.CompletedProcess:
    """Run ``cornermap ARGS`` in a child process (the stages' own commands, without importing them), which ends itself
    once this process is gone (``mapservice.child.run_cornermap``)."""
    from mapservice.child import run_cornermap

    return run_cornermap(list(args))


@dataclass
class DriveCheck:
    ok: bool
    content: str | None  # sha256 of what the drive file references; None when the drive file does not parse
    reason: str  # in cornermap's words, when not ok


def check_delivery(drive_yaml: Path) -> DriveCheck:
    """``cornermap drive check --content`` of one drive; the reason names what failed and where, never a line of the
    drive's files (the check's own messages may quote them: they stay on the command line that asks for them)."""
    res = cli("drive", "check", "--content", "--placed", str(drive_yaml))
    m = _CONTENT_RE.search(res.stdout)
    content = m.group(1) if m else None
    if res.returncode == 0:
        return DriveCheck(True, content, "")
    if res.returncode == 3:  # valid, but nothing places it in the map's frame (the drive check's --placed)
        return DriveCheck(False, content, "its frame cannot be fixed: no GNSS/INS, no prior trajectory the map can "
                                          "place, no start heading; add a gnss section, prior: (ENU, or local with "
                                          "start:) or start: to its drive file; run `cornermap drive check "
                                          f"{drive_yaml}` to read what it lacks")
    text = res.stderr + "\n" + res.stdout
    count = re.search(r"(\d+) problems? in ", text)
    keys = sorted(set(re.findall(r"(?:^\s+- |drive\.yaml: )([A-Za-z_][A-Za-z0-9_]*(?:\.[A-Za-z0-9_]+)*):", text, re.M)))
    folder = drive_yaml.parent
    files = sorted({Path(p).name if Path(p).parent == folder else p
                    for p in re.findall(r"(/[^\s:;,'\"()]+)", text)
                    if Path(p).is_relative_to(folder.parent) and Path(p).exists() and Path(p) != drive_yaml})
    n = int(count.group(1)) if count else 1
    reason = (f"`cornermap drive check` refused it (exit {res.returncode}: {n} problem{'s' if n != 1 else ''}"
              + (f" about {', '.join(keys)}" if keys else "")
              + (f"; files named: {', '.join(files[:5])}" if files else "")
              + f"); run `cornermap drive check {drive_yaml}` to read them")
    return DriveCheck(False, content, reason)


def check_map_drives(ident) -> tuple[object, list[str], list[str]]:
    """(identity, problems, notes): every map drive must be where it was with the fingerprint it had, or, when only
    the fingerprint changed (files around it touched, copied or added), the same content of what its drive file
    references; such a drive's fingerprint is updated in the returned identity. A drive delivered to a bucket
    (``s3://.../NAME/drive.yaml``) is checked on its local copy (``mapservice.inbox.local_drive_file``)."""
    from mapservice.inbox import local_drive_file
    from pipeline.fingerprint import drive_fingerprint

    problems, notes, drives = [], [], []
    for d in ident.drives:
        local = local_drive_file(d.path)
        if local is None:
            problems.append(f"map drive {d.name}: {d.path} is gone; the map needs every drive it was built from")
        elif (fp := drive_fingerprint(local)) != d.fingerprint:
            check = check_delivery(local) if d.content else None
            if check is not None and check.content == d.content:
                notes.append(f"note: map drive {d.name}: files in its folder changed, what its drive file references "
                             "did not (same content)")
                d = d.model_copy(update={"fingerprint": fp})
            else:
                problems.append(f"map drive {d.name}: {d.path} changed content since it was added (fingerprint "
                                f"{d.fingerprint[:12]}); restore it, or make a new map")
        drives.append(d)
    return ident.model_copy(update={"drives": drives}), problems, notes


def checked_identity(home, min_free_gib: float) -> tuple[object, object, list[str]]:
    """(identity as read, identity with updated drive fingerprints, notes) of a map, under its run lock: the
    identity read again (the last writer's), the free disk checked, every map drive checked (``check_map_drives``);
    its problems raise ``ConfigError`` naming the map. What a rebuild and a reoptimize do first."""
    before = home.require_identity()  # read again under the lock: the last writer's
    check_free_disk(home.root if home.local else storage.scratch_base(), min_free_gib)
    ident, problems, notes = check_map_drives(before)
    if problems:
        raise ConfigError(f"map {home.name!r}", problems)
    return before, ident, notes


@dataclass
class Selection:
    good: list[tuple[Delivery, str, str | None]] = field(default_factory=list)  # (drive, fingerprint, content)
    bad: list[tuple[Path | str, str]] = field(default_factory=list)  # (inbox entry, reason): quarantined
    lines: list[str] = field(default_factory=list)  # waiting, already in the map, duplicates


def select_new_drives(ident, inbox, quiet_period_s: float = DEFAULT_QUIET_PERIOD_S):
    """(Selection, identity with the content of older map drives filled in where it had to be computed). ``inbox``:
    a folder, or a ``mapservice.inbox.LocalInbox`` / ``StoreInbox`` (a bucket: a drive is fetched into its local copy
    once it is complete and stays inside the inbox)."""
    from mapservice.inbox import LocalInbox
    from pipeline.fingerprint import drive_fingerprint
    from pipeline.names import name_problem
    from pipeline.progress import finish, report

    if isinstance(inbox, (str, Path)):
        inbox = LocalInbox(Path(inbox))
    by_fp = {d.fingerprint: d for d in ident.drives}
    by_path = {d.path if "://" in d.path else str(Path(d.path)): d for d in ident.drives}
    names = {d.name for d in ident.drives}
    sel = Selection()
    deliveries, refused = inbox.scan()
    sel.bad += refused
    content_of: dict[str, str] = {}  # map drive name -> content (recorded, or computed now for older identities)
    taken: dict[str, Delivery] = {}  # content -> the delivery taken this run
    for i, dlv in enumerate(deliveries):
        report("inbox", i, len(deliveries), step=f"checking {dlv.name}")
        fp = drive_fingerprint(dlv.drive_yaml) if inbox.local else None  # a bucket's drive: once it is fetched
        known = by_path.get(inbox.recorded(dlv)) or (by_fp.get(fp) if fp else None)
        if known is not None:
            if inbox.recorded(dlv) != known.path:
                sel.lines.append(f"already in the map as {known.name}: {dlv.entry} (the same files) left alone")
            continue
        waiting = inbox.waiting_reason(dlv, quiet_period_s)
        if waiting:
            sel.lines.append(f"waiting: {waiting}")
            continue
        outside = inbox.containment_problem(dlv)
        if outside:
            sel.bad.append((dlv.entry, outside))
            continue
        if fp is None:
            inbox.fetch(dlv)
            fp = drive_fingerprint(dlv.drive_yaml)
            if fp in by_fp:
                sel.lines.append(f"already in the map as {by_fp[fp].name}: {dlv.entry} (the same files) left alone")
                continue
        check = check_delivery(dlv.drive_yaml)
        if not inbox.local:  # the check names the local copy: name the bucket's objects instead
            check = DriveCheck(check.ok, check.content, check.reason.replace(str(inbox.copy), inbox.uri))
        if check.content is not None:
            if not content_of:
                content_of = _map_contents(ident)
            same = next((n for n, c in content_of.items() if c == check.content), None)
            if same is not None:
                sel.lines.append(f"already in the map as {same}: {dlv.entry} (the same content) left alone")
                continue
            if check.content in taken:
                sel.lines.append(f"duplicate of {taken[check.content].entry} (the same content): {dlv.entry} left "
                                 "alone; the drive is taken once")
                continue
        problem = name_problem(dlv.name, "drive")
        if problem is None and dlv.name in names:
            problem = f"drive name {dlv.name!r} is taken by another drive of the map (rename the folder)"
        if problem is None and not check.ok:
            problem = check.reason
        if problem is None:
            sel.good.append((dlv, fp, check.content))
            names.add(dlv.name)
            if check.content is not None:
                taken[check.content] = dlv
        else:
            sel.bad.append((dlv.entry, problem))
    report("inbox", len(deliveries), len(deliveries))
    finish("inbox", f"{len(sel.good)} new, {len(sel.bad)} quarantined")
    missing = {d.name for d in ident.drives if d.content is None}
    if content_of and missing:
        ident = ident.model_copy(update={"drives": [d if d.content else d.model_copy(
            update={"content": content_of.get(d.name)}) for d in ident.drives]})
    return sel, ident


def _map_contents(ident) -> dict[str, str]:
    """Map drive name -> content: the identity's, else computed now (identities written before it was recorded)."""
    from mapservice.inbox import local_drive_file

    out = {}
    for d in ident.drives:
        if d.content:
            out[d.name] = d.content
        elif (local := local_drive_file(d.path)) is not None:
            content = check_delivery(local).content
            if content:
                out[d.name] = content
    return out


def rebuild(root: "Path | str", name: str, inbox: "Path | str", params: RebuildParams = RebuildParams(),
            say: Callable[[str], None] | None = None) -> RebuildResult:
    """One rebuild (module docstring); ``say(line)`` gets each line of the result as it is made, so that what was
    quarantined or left alone is told even when the build then fails. ``root`` and ``inbox`` are local folders or
    ``s3://`` URIs (``mapservice.maps.MapHome``, ``mapservice.inbox.StoreInbox``)."""
    from mapservice.build import write_build_workflow
    from mapservice.inbox import open_inbox
    from mapservice.maps import MapHome
    from pipeline.api import execute_workflow
    from pipeline.versioned import version_name

    home = MapHome(root, name)
    home.require_identity()
    box = open_inbox(inbox)
    if not box.exists():
        raise ConfigError("--inbox", [f"{box}: not a directory" if box.local else f"{box}: no object under it"])
    with home.run_lock():
        before, ident, notes = checked_identity(home, params.min_free_gib)
        sel, ident = select_new_drives(ident, box, params.quiet_period_s)
        result = RebuildResult("nothing", say=say)
        result.add(*notes, *sel.lines)
        for entry, reason in sel.bad:
            dst = box.quarantine(entry, reason)
            entry_name = entry.name if isinstance(entry, Path) else entry.rstrip("/").rsplit("/", 1)[-1]
            result.quarantined.append(entry_name)
            result.add(f"quarantined {entry_name} -> {dst} ({reason[:300]})")
        if not sel.good:
            if ident != before:  # fingerprints or contents brought up to date
                home.write_identity(ident)
            result.add(f"nothing to do: no new drive in {box} for map {name!r} "
                       f"({len(ident.drives)} drive(s), LATEST {_latest_text(home)})")
            return result
        from mapservice.inbox import local_drive_file

        drives = [local_drive_file(d.path) for d in ident.drives] + [dlv.drive_yaml for dlv, _, _ in sel.good]
        with home.view(whole=()) as view:
            held = None if params.full else held_solution(home.root, view)
        if held is None and not params.full and ident.drives:
            result.add("note: no published pose-graph solution to hold (LATEST none or its poses gone): every "
                       "drive is solved jointly")
        wf = write_build_workflow(params.workflow, drives=drives, map_name=name, root=home.root,
                                  origin=ident.enu_origin.plain(), tile_size_m=ident.tile_size_m,
                                  hold_latest=True, max_radius_m=ident.max_radius_km * 1000.0, held_poses=held)
        run = execute_workflow(wf, root=home.root, scheduler=params.scheduler, only=None, dry_run=False, quiet=True,
                               params_file=params.params_file, workers=params.workers, dask_host=params.dask_host)
        result.summary = run["summary"]
        result.add(reuse_line(run["summary"]))
        candidate, _ = gate_and_publish(home, run, ident, before, params, result, "rebuild",
                                        fallback_drive=sel.good[-1][0].drive_yaml)
        if result.status == "refused":
            return result
        added = [MapDrive(name=dlv.name, path=box.recorded(dlv), fingerprint=fp, content=content,
                          added_utc=utc_now(), added_in=candidate) for dlv, fp, content in sel.good]
        home.write_identity(ident.model_copy(update={"drives": list(ident.drives) + added}))
        result.status, result.version = "published", candidate
        result.add(f"published map {name!r} {version_name(candidate)} (LATEST): {len(drives)} drive(s), "
                   f"added {', '.join(dlv.name for dlv, _, _ in sel.good)}")
        return result


def gate_and_publish(home, run: dict, ident, before, params, result: RebuildResult, what: str,
                     fallback_drive: Path) -> tuple[int, int | None]:
    """The publishing half of a run that wrote a candidate version with ``hold_latest`` (``rebuild``, ``maps
    reoptimize``), on a local root or an ``s3://`` one alike (``MapHome``), under the map's lock the caller holds:
    the candidate is the version the run's plan published (StageError naming ``what`` when it committed none); when it
    is not already LATEST and a LATEST exists, the regression gate (``mapservice.gate.run_gate`` on a local view of both
    versions; its record written to the map) localizes the identity's check drive (else ``fallback_drive``) on both;
    a refusal sets ``result`` refused (exit 3), writes ``ident`` when it differs from ``before`` (fingerprints brought
    up to date) and leaves LATEST; otherwise LATEST moves to the candidate (``MapHome.move_latest``: verified under
    the publish lock). Returns (candidate, the LATEST before); the caller records what the run adds to the
    identity."""
    from mapservice.gate import run_gate
    from mapservice.inbox import local_drive_file
    from mapservice.maps import published_version
    from pipeline.versioned import version_name

    candidate = published_version(run["plan"])
    if candidate is None:
        raise StageError(f"{what} of map {home.name!r}: the build committed no map_tiles rows (no version published)")
    previous = home.latest()
    if candidate != previous and previous is not None and params.gate:
        check = ident.check_drive
        drive = local_drive_file(check.path) if check else Path(fallback_drive)
        if drive is None:
            raise ConfigError(f"map {home.name!r}", [f"its check drive {check.path} is gone"])
        reference = check.reference if check else None
        with home.view(whole=_gate_versions(home, candidate, previous)) as view:
            verdict = run_gate(view, candidate, previous, drive, reference, params.gate_tol_m, params.gate_tol_rel)
            home.put_gate(view, candidate)
        result.add(*verdict.table)
        if not verdict.ok:
            result.status, result.version = "refused", candidate
            result.add(f"refused: {version_name(candidate)} is worse than {version_name(previous)} on "
                       f"{drive.parent.name}; LATEST stays {version_name(previous)}")
            if ident != before:
                home.write_identity(ident)
            return candidate, previous
    if candidate != previous:
        home.move_latest(candidate)
    return candidate, previous


def _gate_versions(home, candidate: int, previous: int) -> list[int]:
    """The versions the gate reads in full: both, and the parent of each (``cornermap evaluate`` also localizes on a
    version's parent, ``stages/evaluate/compare.py``). On a local root every version is in place; on a bucket the
    parents are found in a snapshot of the manifests (without them the gate of a third version failed reading its
    previous version's parent)."""
    from pipeline.version_read import read_manifest

    wanted = {candidate, previous}
    if home.local:
        return sorted(wanted)
    with home.view(whole=()) as manifests:
        for v in (candidate, previous):
            parent = read_manifest(storage.version_dir(manifests, v))[0].get("parent_version")
            if isinstance(parent, int):
                wanted.add(parent)
    return sorted(wanted)


def held_solution(root: "Path | str", mdir: Path) -> dict | None:
    """``{fingerprint, version}`` of the pose-graph solution LATEST was published from (its manifest's ``poses``
    input), which an incremental rebuild holds fixed; None without a LATEST, a manifest naming none, or when that
    dataset is no longer committed under ROOT (the rebuild then solves every drive jointly). ``mdir``: the map's
    local folder (on an object-store root, a snapshot of it: ``MapHome.view``)."""
    from pipeline.store import data_root
    from pipeline.versioned import read_latest
    from pipeline.versioned import read_manifest as read_version_manifest

    if not storage.latest_file(mdir).exists():
        return None
    latest = read_latest(mdir)
    if latest is None:
        return None
    manifest, _ = read_version_manifest(storage.version_dir(mdir, latest))
    poses = (manifest.get("inputs") or {}).get("poses") or {}
    fp = poses.get("fingerprint")
    if poses.get("dataset") != "poses_optimized" or not fp:
        return None
    if data_root(root if storage.uri_scheme(root) else Path(root).resolve()).manifest("poses_optimized", fp) is None:
        return None
    return {"fingerprint": fp, "version": int(latest)}


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


def _latest_text(home) -> str:
    from pipeline.versioned import version_name

    v = home.latest()
    return version_name(v) if v is not None else "none"
