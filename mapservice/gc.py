"""``cornermap gc``: remove intermediates that no kept map version and no current drive set references.

Kept fingerprints (each keeps every ``datasets/*/<fp16>`` directory of that fingerprint, i.e. all outputs of
the stage run):
  1. roots: the tiles inputs recorded in the manifest of every version directory under ``ROOT/maps/*/``
     (kept versions, LATEST or not), the ``map_tiles`` rows naming such a version, and every stage of the
     newest build workflow (``ROOT/workflows/build-NAME-*.yaml``) of each map whose identity lists the same
     drives (the current drive set: the next rebuild reuses its per-drive work);
  2. upstream: every input fingerprint a kept dataset's manifest records, and every dataset folder holding a file
     it read by path (its drive files, reference trajectories: the simulator's drives), transitively;
  3. downstream: a committed dataset all of whose inputs are kept (e.g. evaluations of a kept map).
A directory without ``_manifest.json`` (a run in progress or a killed one) is removed only when older than
``min_age_h``; so is an entry of ``ROOT/tmp`` (a task's scratch folder, a run's verified-files ledger, a stage's
planning folder: a run removes its own, a killed one leaves them) when nothing in it changed for ``min_age_h``.
Deleting holds the root's lock exclusive (``pipeline.locks``; exit 75 while any run, build or rebuild writes in the
root, each of which holds it shared from its planning on) and plans again under it: only what both plans would
remove goes (a run that ended between the dry plan and the lock keeps what it made and reused). Files are hard-linked
between dataset
directories by drive-scoped reuse (pipeline/reuse.py), so the bytes freed are counted per inode: a removed directory
whose files live on in a kept one frees nothing.

Staged drives (``ROOT/drives/<fp16>/``: local drives a build or rebuild uploaded into an object-store root,
``pipeline.drive_store.stage_drive``) are removed when nothing live names them: no kept dataset's manifest (its
``drives``), no map identity (its drives and check drive). A staged drive named by nothing is kept while its marker
``_staged.json`` (rewritten each time a build stages or finds the drive) is younger than ``min_age_h`` (a build
staged it and has not yet started its run); a folder without its marker (an upload in progress or killed) is dated
by its newest file. Deleting holds the root's lock exclusive, as for datasets (staging holds it shared), and removes
the marker first, then the folder.
"""
from __future__ import annotations

import json
import logging
import shutil
import stat
import time
from dataclasses import dataclass, field
from pathlib import Path

from pipeline import storage
from pipeline.storage import FP_LEN

log = logging.getLogger(__name__)


@dataclass
class GcPlan:
    keep: list[Path] = field(default_factory=list)
    remove: list[Path] = field(default_factory=list)
    remove_bytes: int = 0  # bytes freed (inodes with no link left in a kept directory)
    keep_bytes: int = 0
    young_uncommitted: list[Path] = field(default_factory=list)
    stale_scratch: list[Path] = field(default_factory=list)  # ROOT/tmp entries of killed runs
    scratch_bytes: int = 0
    drives_keep: list[Path] = field(default_factory=list)  # ROOT/drives/<fp16> named by a kept dataset or a map
    drives_young: list[Path] = field(default_factory=list)  # named by nothing, staged less than min_age_h ago
    drives_remove: list[Path] = field(default_factory=list)  # named by nothing, older
    drives_bytes: int = 0  # bytes of drives_remove

    def as_json(self, root: Path, url=None) -> dict:
        """The plan as ``cornermap gc --json`` prints it (``url``: a location as the user writes it)."""
        name = url or (lambda p: Path(p).relative_to(root).as_posix())
        return {"datasets": {"remove": [name(d) for d in self.remove], "remove_bytes": self.remove_bytes,
                             "kept": len(self.keep), "keep_bytes": self.keep_bytes,
                             "young_uncommitted": [name(d) for d in self.young_uncommitted]},
                "drives": {"remove": [name(d) for d in self.drives_remove], "remove_bytes": self.drives_bytes,
                           "young": [name(d) for d in self.drives_young], "kept": [name(d) for d in self.drives_keep]},
                "scratch": {"remove": [name(d) for d in self.stale_scratch], "remove_bytes": self.scratch_bytes}}


def _manifest(d: Path) -> dict | None:
    try:
        return json.loads(storage.dataset_manifest(d).read_text())
    except (OSError, ValueError):
        return None


def _version_roots(root: Path) -> tuple[set[str], set[tuple[str, int]]]:
    from pipeline.version_read import _VERSION_RE

    fps, versions = set(), set()
    maps = storage.maps_dir(root)
    for mdir in sorted(maps.iterdir()) if maps.is_dir() else []:
        for vdir in sorted(mdir.iterdir()) if mdir.is_dir() else []:
            m = _VERSION_RE.match(vdir.name)
            if not m or not storage.version_manifest(vdir).is_file():
                continue
            versions.add((mdir.name, int(m.group(1))))
            try:
                doc = json.loads(storage.version_manifest(vdir).read_text())
            except (OSError, ValueError):
                continue
            for entry in (doc.get("inputs") or {}).values():
                if isinstance(entry, dict) and entry.get("fingerprint"):
                    fps.add(str(entry["fingerprint"])[:FP_LEN])
    return fps, versions


def _map_tiles_roots(root: Path, versions: set[tuple[str, int]]) -> set[str]:
    import pyarrow.parquet as pq

    out = set()
    base = storage.datasets_dir(root) / "map_tiles"
    for d in sorted(base.iterdir()) if base.is_dir() else []:
        m = _manifest(d)
        for rec in (m or {}).get("files", []):
            try:
                rows = pq.read_table(d / rec["path"], columns=["map_name", "version"]).to_pylist()
            except (OSError, ValueError):
                continue
            if any((r["map_name"], r["version"]) in versions for r in rows):
                out.add(d.name)
    return out


def _drive_set_roots(root: Path) -> set[str]:
    """Every stage fingerprint of the newest build workflow of each map that lists the map's current drives."""
    from mapservice.maps import read_identity
    from pipeline.plan import make_plan
    from pipeline.safe_yaml import load_yaml_file
    from pipeline.workflow import load_workflow

    out: set[str] = set()
    maps = storage.maps_dir(root)
    for mdir in sorted(maps.iterdir()) if maps.is_dir() else []:
        ident = read_identity(mdir) if mdir.is_dir() else None
        if ident is None or not ident.drives:
            continue
        current = sorted(d.path for d in ident.drives)
        files = sorted(storage.workflows_dir(root).glob(f"build-{mdir.name}-*.yaml"), key=lambda p: p.stat().st_mtime)
        for wf_path in reversed(files):
            doc = load_yaml_file(wf_path) or {}
            if sorted(d.get("path") for d in doc.get("drives", [])) != current:
                continue
            plan = make_plan(load_workflow(wf_path), root)
            out |= {sp.fingerprint[:FP_LEN] for sp in plan.stages.values()}
            break
    return out


def _newest_mtime_and_bytes(path: Path) -> tuple[float, int]:
    """The newest modification time of ``path`` and everything below it (a live run writes somewhere inside), and the
    bytes of its files, in one walk. A file removed while we looked: its run is alive (now, 0)."""
    st = path.lstat()
    newest, size = st.st_mtime, 0 if stat.S_ISDIR(st.st_mode) else st.st_size
    if stat.S_ISDIR(st.st_mode):
        for p in path.rglob("*"):
            try:
                st = p.lstat()
            except OSError:
                return time.time(), 0
            newest = max(newest, st.st_mtime)
            size += st.st_size if stat.S_ISREG(st.st_mode) else 0
    return newest, size


def _stale_scratch(root: Path, min_age_h: float) -> tuple[list[Path], int]:
    tmp = storage.tmp_dir(root)
    stale, size, now = [], 0, time.time()
    for entry in sorted(tmp.iterdir()) if tmp.is_dir() else []:
        try:
            newest, entry_bytes = _newest_mtime_and_bytes(entry)
        except OSError:  # gone while we looked
            continue
        if now - newest >= min_age_h * 3600:
            stale.append(entry)
            size += entry_bytes
    return stale, size


def _read_by_path(manifest: dict, root: Path) -> set[str]:
    """Fingerprints of the dataset folders under ``root`` that a stage read by path: its drive files (``drives``,
    e.g. the simulator's drives read by the ingest) and reference trajectories (``settings.references``). They are
    no manifest input, but a kept dataset was made from them."""
    paths = list((manifest.get("drives") or {}).values())
    paths += list(((manifest.get("settings") or {}).get("references") or {}).values())
    base = storage.datasets_dir(Path(root)).resolve()
    out = set()
    for p in paths:
        if not isinstance(p, str) or not p:
            continue
        try:
            rel = Path(p).resolve().relative_to(base)
        except (ValueError, OSError):
            continue
        if len(rel.parts) >= 2:
            out.add(rel.parts[1][:FP_LEN])
    return out


def _named_drives(root: Path, kept: list[dict], store_uri: str | None) -> set[str]:
    """The ``fp16`` of every staged drive (``ROOT/drives/<fp16>/``) a kept dataset's manifest (``kept``) or a map's
    identity names (``store_uri``: the root's URI when ``root`` is a local snapshot of an object-store root)."""
    from mapservice.maps import read_identity

    base = store_uri or root
    values = [v for m in kept for v in (m.get("drives") or {}).values()]
    maps = storage.maps_dir(root)
    for mdir in sorted(maps.iterdir()) if maps.is_dir() else []:
        try:
            ident = read_identity(mdir) if mdir.is_dir() else None
        except Exception:  # noqa: BLE001 - an identity that does not read names nothing gc may remove on its word
            ident = None
        if ident is not None:
            values += [d.path for d in ident.drives]
            values += [ident.check_drive.path] if ident.check_drive is not None else []
    return {fp for v in values for fp in (storage.staged_drive_of(v, base),) if fp}


def _staged_drives(root: Path, named: set[str], min_age_h: float, plan: "GcPlan", now: float) -> None:
    """Sort ``ROOT/drives/*`` into the plan: named (kept), young (kept), or to remove (with their bytes)."""
    sd = storage.drives_dir(root)
    for d in sorted(sd.iterdir()) if sd.is_dir() else []:
        if not d.is_dir() or d.name.startswith("."):
            continue
        if d.name in named:
            plan.drives_keep.append(d)
            continue
        try:
            newest, size = _newest_mtime_and_bytes(d)
            marker = storage.staged_marker(d)
            if marker.is_file():  # the marker's time: when a build last staged or found the drive
                newest = marker.stat().st_mtime
        except OSError:  # gone while we looked
            continue
        if now - newest < min_age_h * 3600:
            plan.drives_young.append(d)
        else:
            plan.drives_remove.append(d)
            plan.drives_bytes += size


def check_min_age_h(min_age_h: float) -> float:
    """``min_age_h`` when it is a finite number >= 0; ConfigError otherwise (a negative age would remove the folders
    of runs in progress)."""
    import math

    from pipeline.errors import ConfigError

    if not (isinstance(min_age_h, (int, float)) and math.isfinite(min_age_h) and min_age_h >= 0):
        raise ConfigError("--min-age-h", [f"expected a number of hours >= 0; got {min_age_h}"])
    return float(min_age_h)


def plan_gc(root: Path, min_age_h: float = 24.0, store_uri: str | None = None, now: float | None = None) -> GcPlan:
    """What ``cornermap gc`` removes from the local root ``root`` (the module's rules); ``store_uri``: ``root`` is a
    local snapshot of that object-store root (``plan_gc_store``); ``now``: the time ages are judged at (unix s,
    default the clock's)."""
    root = Path(root)
    check_min_age_h(min_age_h)
    dirs = sorted(d for d in storage.datasets_dir(root).glob("*/*") if d.is_dir())
    manifests = {d: _manifest(d) for d in dirs}
    roots, versions = _version_roots(root)
    kept = roots | _map_tiles_roots(root, versions) | _drive_set_roots(root)
    # each committed dataset's manifest inputs, and the folders it read by path (upstream only), taken once
    inputs = {d: {str(v.get("fingerprint"))[:FP_LEN] for v in (m.get("inputs") or {}).values() if v.get("fingerprint")}
              for d, m in manifests.items() if m is not None}
    read_by_path = {d: _read_by_path(m, root) for d, m in manifests.items() if m is not None}
    changed = True
    while changed:  # upstream and downstream closure
        changed = False
        for d, ins in inputs.items():
            if d.name in kept and not read_by_path[d] <= kept:
                kept |= read_by_path[d]
                changed = True
            if d.name in kept and not ins <= kept:
                kept |= ins
                changed = True
            elif d.name not in kept and ins and ins <= kept:
                kept.add(d.name)
                changed = True
    plan = GcPlan()
    now = time.time() if now is None else now
    for d in dirs:
        if d.name in kept:
            plan.keep.append(d)
        elif manifests[d] is None and now - d.stat().st_mtime < min_age_h * 3600:
            plan.young_uncommitted.append(d)
        else:
            plan.remove.append(d)
    plan.remove_bytes, plan.keep_bytes = _bytes(plan.remove, plan.keep + plan.young_uncommitted)
    plan.stale_scratch, plan.scratch_bytes = _stale_scratch(root, min_age_h)
    kept_manifests = [manifests[d] for d in plan.keep if manifests[d] is not None]
    _staged_drives(root, _named_drives(root, kept_manifests, store_uri), min_age_h, plan, now)
    return plan


def _bytes(remove: list[Path], keep: list[Path]) -> tuple[int, int]:
    """(bytes freed by removing ``remove``, bytes kept in ``keep``), per inode: a file hard-linked into a kept
    folder frees nothing, and one linked twice counts once."""
    kept_sizes = {(st.st_dev, st.st_ino): st.st_size for d in keep
                  for p in d.rglob("*") if p.is_file() for st in (p.stat(),)}
    seen: set[tuple[int, int]] = set()
    freed = 0
    for d in remove:
        for p in d.rglob("*"):
            if p.is_file():
                st = p.stat()
                key = (st.st_dev, st.st_ino)
                if key not in kept_sizes and key not in seen:
                    seen.add(key)
                    freed += st.st_size
    return freed, sum(kept_sizes.values())


def apply_gc(root: Path, plan: GcPlan, min_age_h: float = 24.0, at_s: float | None = None) -> GcPlan:
    """Delete what ``plan`` lists and a plan made now, under the root's exclusive lock, still lists; returns what
    was deleted. RunLockedError (exit 75) naming a holder while a run writes in the root: nothing is deleted then."""
    from pipeline.locks import root_exclusive

    root = Path(root)
    with root_exclusive(root):
        now = plan_gc(root, min_age_h, now=at_s)
        done = GcPlan(keep=now.keep, young_uncommitted=now.young_uncommitted, keep_bytes=now.keep_bytes)
        done.remove = [d for d in plan.remove if d in set(now.remove)]
        done.stale_scratch = [e for e in plan.stale_scratch if e in set(now.stale_scratch)]
        done.remove_bytes = now.remove_bytes if done.remove == now.remove else _bytes(done.remove, now.keep)[0]
        done.scratch_bytes = now.scratch_bytes if done.stale_scratch == now.stale_scratch else 0
        done.drives_keep, done.drives_young = now.drives_keep, now.drives_young
        done.drives_remove = [d for d in plan.drives_remove if d in set(now.drives_remove)]
        done.drives_bytes = now.drives_bytes if done.drives_remove == now.drives_remove else \
            sum(_newest_mtime_and_bytes(d)[1] for d in done.drives_remove)
        for d in done.drives_remove:
            storage.staged_marker(d).unlink(missing_ok=True)  # the drive stops being staged at once
            trash = d.with_name(f".gc-{d.name}")
            d.rename(trash)
            shutil.rmtree(trash)
            log.info("gc: removed %s", d)
        for d in done.remove:
            trash = d.with_name(f".gc-{d.name}")
            d.rename(trash)  # the dataset vanishes atomically, then its files go
            shutil.rmtree(trash)
            log.info("gc: removed %s", d)
        for entry in done.stale_scratch:
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)
            log.info("gc: removed %s", entry)
    return done


def plan_gc_store(store, min_age_h: float = 24.0, now: float | None = None) -> GcPlan:
    """``plan_gc`` on an object-store root: the same rules, judged on a local snapshot of what they read (every
    dataset manifest, the ``map_tiles`` files, every map's manifests and identity, the build workflows, each staged
    drive's marker), each uncommitted dataset folder and each staged drive without its marker dated by its newest
    object. Returns the plan with the store's locations (``PurePosixPath``) in place of the snapshot's folders and
    the bytes of what it removes counted in the bucket (no hard links there; ``keep_bytes`` is not counted: 0)."""
    import os
    import tempfile
    from pathlib import PurePosixPath

    from pipeline.store_maps import _newest_modified, map_names, snapshot_map

    check_min_age_h(min_age_h)
    with tempfile.TemporaryDirectory(prefix="cornermap-gc-", dir=storage.scratch_base()) as tmp:
        local = Path(tmp)
        base = storage.datasets_dir(store.root)
        for ds in store.listdir(base):
            for fp in store.listdir(base / ds):
                loc, d = base / ds / fp, storage.datasets_dir(local) / ds / fp
                d.mkdir(parents=True)
                try:
                    raw = store.read_bytes(storage.dataset_manifest(loc))
                except FileNotFoundError:
                    stamp = _newest_modified(store, loc) or time.time()
                    os.utime(d, (stamp, stamp))  # an uncommitted folder: as old as its newest object
                    continue
                storage.dataset_manifest(d).write_bytes(raw)
                if ds == "map_tiles":  # its rows name the versions it published
                    with_files = json.loads(raw).get("files", [])
                    store.download_files([(loc / PurePosixPath(r["path"]).as_posix(), d / r["path"])
                                          for r in with_files])
        for name in map_names(store):
            snapshot_map(store, name, local, whole=())
        wf = storage.workflows_dir(store.root)
        for rel, (_, stamp) in store.walk_objects(wf).items():
            target = storage.workflows_dir(local) / PurePosixPath(rel).name
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(store.read_bytes(wf / rel))
            if stamp:  # the newest build workflow of a map is the one that counts
                os.utime(target, (stamp, stamp))
        sizes: dict[str, int] = {}
        for fp in store.listdir(storage.drives_dir(store.root)):  # each staged drive: dated by its marker
            objects = store.walk_objects(storage.drives_dir(store.root) / fp)
            d = storage.drives_dir(local) / fp
            d.mkdir(parents=True)
            marker = objects.get(storage.STAGED_MARKER)
            stamp = marker[1] if marker else max((t for _, t in objects.values()), default=0.0) or time.time()
            if marker:
                storage.staged_marker(d).write_bytes(b"")
                os.utime(storage.staged_marker(d), (stamp, stamp))
            os.utime(d, (stamp, stamp))
            sizes[fp] = sum(size for size, _ in objects.values())
        plan = plan_gc(local, min_age_h, store_uri=store.uri, now=now)
        to_loc = lambda d: store.root / d.relative_to(local).as_posix()  # noqa: E731
        out = GcPlan(keep=[to_loc(d) for d in plan.keep], remove=[to_loc(d) for d in plan.remove],
                     young_uncommitted=[to_loc(d) for d in plan.young_uncommitted],
                     drives_keep=[to_loc(d) for d in plan.drives_keep],
                     drives_young=[to_loc(d) for d in plan.drives_young],
                     drives_remove=[to_loc(d) for d in plan.drives_remove])
    out.remove_bytes = sum(size for loc in out.remove for _, size in store.walk_files(loc))
    out.drives_bytes = sum(sizes.get(loc.name, 0) for loc in out.drives_remove)
    return out


def apply_gc_store(store, plan: GcPlan, min_age_h: float = 24.0, at_s: float | None = None) -> GcPlan:
    """Delete the dataset folders and staged drives ``plan`` lists that a plan made now, under the root's exclusive
    lease, still lists: each manifest (marker) first (the dataset stops being committed, the drive being staged, at
    once), then its objects. Returns what went."""
    from pipeline.locks import root_exclusive

    with root_exclusive(store, what="cornermap gc --apply"):
        now = plan_gc_store(store, min_age_h, now=at_s)
        done = GcPlan(keep=now.keep, young_uncommitted=now.young_uncommitted, drives_keep=now.drives_keep,
                      drives_young=now.drives_young)
        done.remove = [loc for loc in plan.remove if loc in set(now.remove)]
        done.drives_remove = [loc for loc in plan.drives_remove if loc in set(now.drives_remove)]
        done.remove_bytes = now.remove_bytes if done.remove == now.remove else \
            sum(size for loc in done.remove for _, size in store.walk_files(loc))
        done.drives_bytes = now.drives_bytes if done.drives_remove == now.drives_remove else \
            sum(size for loc in done.drives_remove for _, size in store.walk_files(loc))
        for loc in done.remove:
            store.delete(storage.dataset_manifest(loc))
            store.delete_tree(loc)
            log.info("gc: removed %s", store.url(loc))
        for loc in done.drives_remove:
            store.delete(storage.staged_marker(loc))
            store.delete_tree(loc)
            log.info("gc: removed %s", store.url(loc))
    return done
