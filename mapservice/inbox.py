"""The inbox of a maintained map: which delivered drive folders are complete and stay inside it (knows nothing about
LiDAR: a drive is a folder holding ``drive.yaml``, whose ``file:`` and ``folder:`` values name its inputs).

The delivery protocol (``docs/maintenance.md``, "Delivering drives"):
  * a drive is a folder ``INBOX/NAME`` holding ``drive.yaml``; ``INBOX/quarantine/`` and hidden entries (a copy
    tool's temporary folders) are not looked at;
  * an entry that is a symbolic link is resolved first; the folder it names must lie inside the inbox (else the link
    itself is refused: moved to quarantine, its target untouched), its name is the resolved folder's, and two entries
    naming one folder are one drive;
  * every file or folder the drive file names, and every link below those folders, must resolve inside the inbox;
  * a drive is taken when complete: a file ``READY`` in its folder with nothing changed after it, or nothing under
    the folder (nor a file it names outside it, e.g. ``../survey/``) changed for the quiet period (default 10 min).
    A change is a modification or status change (mtime or ctime: a copy that keeps the sender's modification times
    still sets the status-change time).
An inbox in a bucket (``s3://BUCKET/PREFIX``) follows the same protocol on objects: ``StoreInbox`` (``open_inbox``
gives the one a ``--inbox`` value names).
"""
from __future__ import annotations

import os
import stat
import time
from dataclasses import dataclass
from pathlib import Path

from pipeline.drive_store import remember_copy

QUARANTINE = "quarantine"
READY_MARKER = "READY"
DEFAULT_QUIET_PERIOD_S = 600.0
CLOCK_SLACK_S = 2.0  # file systems with coarse time stamps


@dataclass(frozen=True)
class Delivery:
    """One drive folder found in the inbox: the entry as delivered and the folder it resolves to."""

    entry: Path  # INBOX/<entry>: a folder, or a link to one
    folder: Path  # resolved

    @property
    def drive_yaml(self) -> Path:
        return self.folder / "drive.yaml"

    @property
    def name(self) -> str:
        return self.folder.name


def _inside(path: Path, base: Path) -> bool:
    return path == base or base in path.parents


def scan_inbox(inbox: Path) -> tuple[list[Delivery], list[tuple[Path, str]]]:
    """(drive folders in the inbox by resolved name, entries refused with a reason). Folders come before links, so a
    link to a folder that is itself delivered adds nothing."""
    inbox = inbox.resolve()
    entries = sorted((p for p in inbox.iterdir() if p.name != QUARANTINE and not p.name.startswith(".")),
                     key=lambda p: (p.is_symlink(), p.name))
    found: dict[Path, Delivery] = {}
    refused: list[tuple[Path, str]] = []
    quarantine = inbox / QUARANTINE
    for entry in entries:
        try:
            folder = entry.resolve(strict=True)
        except (OSError, RuntimeError):  # a dangling or looping link
            if entry.is_symlink():
                refused.append((entry, f"{entry.name} is a link to a path that does not exist"))
            continue
        if entry.is_symlink() and (not _inside(folder, inbox) or _inside(folder, quarantine)):
            if folder.is_dir() and (folder / "drive.yaml").exists():
                refused.append((entry, f"{entry.name} is a link to a folder outside the inbox {inbox} (or in its "
                                       "quarantine); a delivered drive must be copied into the inbox"))
            continue
        if folder.is_dir() and (folder / "drive.yaml").is_file() and folder not in found:
            found[folder] = Delivery(entry, folder)
    return sorted(found.values(), key=lambda d: (d.name, str(d.entry))), refused


def referenced_paths(drive_yaml: Path) -> list[Path]:
    """What the drive file names under its ``file`` and ``folder`` keys, as written (relative to its folder);
    [] when it does not parse (the drive check reports that)."""
    from pipeline.errors import ConfigError
    from pipeline.safe_yaml import MAX_YAML_BYTES, load_yaml

    try:
        if drive_yaml.stat().st_size > MAX_YAML_BYTES:
            return []
        doc = load_yaml(drive_yaml.read_bytes(), str(drive_yaml))
    except (OSError, ConfigError):
        return []
    out: list[Path] = []

    def walk(node) -> None:
        if isinstance(node, dict):
            for k, v in node.items():
                if k in ("file", "folder") and isinstance(v, str) and v and len(v) < 4096:
                    out.append(drive_yaml.parent / v)
                else:
                    walk(v)
        elif isinstance(node, list):
            for v in node:
                walk(v)

    walk(doc)
    return out


def containment_problem(delivery: Delivery, inbox: Path) -> str | None:
    """Why a drive's files are not all inside the inbox (a referenced path, or a link below a referenced folder or
    the drive's own folder, resolving outside it), or None. Nothing outside the inbox is opened."""
    inbox = inbox.resolve()
    yaml_path = delivery.drive_yaml
    if not _inside(yaml_path.resolve(), inbox):
        return f"{yaml_path} is a link to a file outside the inbox {inbox}"
    refs = referenced_paths(yaml_path)
    for ref in refs:
        try:
            resolved = ref.resolve()
        except (OSError, RuntimeError):
            continue  # a looping path: the drive check names it
        if not _inside(resolved, inbox):
            return (f"{ref} resolves to a path outside the inbox {inbox} (refused: a delivered drive holds its own "
                    "files)")
    outside_folder = [r.resolve() for r in refs if not _inside(Path(os.path.normpath(r)), delivery.folder)]
    for root in [delivery.folder] + [r for r in outside_folder if r.is_dir()]:
        for top, dirs, files in os.walk(root):
            for name in dirs + files:
                p = Path(top) / name
                if p.is_symlink() and not _inside(p.resolve(), inbox):
                    return (f"{p} is a link to a path outside the inbox {inbox} (refused: a delivered drive holds its "
                            "own files)")
    return None


def _changed_s(path: Path) -> float:
    st = path.lstat()
    return max(st.st_mtime, st.st_ctime)


def newest_change_s(delivery: Delivery, exclude: Path | None = None) -> float:
    """The newest modification or status change under the drive's folder and of the paths its drive file names
    outside it (links not followed)."""
    newest = _changed_s(delivery.folder)
    roots = [delivery.folder] + [p for p in referenced_paths(delivery.drive_yaml) if not _inside(
        Path(os.path.normpath(p)), delivery.folder)]
    for root in roots:
        try:
            newest = max(newest, _changed_s(root))
        except OSError:
            continue
        if not stat.S_ISDIR(root.lstat().st_mode):
            continue
        for top, dirs, files in os.walk(root):
            for name in dirs + files:
                p = Path(top) / name
                if p == exclude:
                    continue
                try:
                    newest = max(newest, _changed_s(p))
                except OSError:  # removed while we looked: it is being written
                    return time.time()
    return newest


def waiting_reason(delivery: Delivery, quiet_period_s: float, now: float | None = None) -> str | None:
    """None when the drive is complete by the protocol above, else why it is not taken yet (one line)."""
    now = time.time() if now is None else now
    marker = delivery.folder / READY_MARKER
    if marker.is_file():
        marked = _changed_s(marker)
        newest = newest_change_s(delivery, exclude=marker)
        if newest > marked + CLOCK_SLACK_S:
            return (f"{delivery.entry} changed {newest - marked:.0f} s after its {READY_MARKER} marker; taken once "
                    f"{READY_MARKER} is written again after the copy")
        return None
    age = now - newest_change_s(delivery)
    if age >= quiet_period_s:
        return None
    return (f"{delivery.entry} changed {max(age, 0):.0f} s ago; taken after {quiet_period_s / 60:g} min without a "
            f"change (--quiet-period-min), or at once with a {READY_MARKER} file in it written after the copy")


def quarantine(entry: Path, inbox: Path, reason: str) -> Path:
    """Move an inbox entry (a folder, or a link: never its target) to INBOX/quarantine/ (a new name if taken) and write
    its reason file beside it (in cornermap's own words: never a line of the drive's files)."""
    from mapservice.maps import utc_now

    qdir = inbox / QUARANTINE
    qdir.mkdir(exist_ok=True)
    dst = qdir / entry.name
    if dst.exists() or dst.is_symlink():
        dst = qdir / f"{entry.name}-{utc_now().replace(':', '')}"
    entry.rename(dst)
    tmp = qdir / f".{dst.name}.reason.tmp"
    tmp.write_text(f"{utc_now()} quarantined by cornermap rebuild: {reason.strip()}\n", encoding="utf-8")
    tmp.replace(qdir / f"{dst.name}.reason.txt")
    return dst


# --- the inbox as one face: a local folder, or a prefix in a bucket ------------------------------------------------
class LocalInbox:
    """A folder of drive folders (the protocol above)."""

    local = True

    def __init__(self, path: Path):
        self.path = Path(path).resolve()

    def __str__(self) -> str:
        return str(self.path)

    def exists(self) -> bool:
        return self.path.is_dir()

    def scan(self) -> tuple[list[Delivery], list[tuple[Path, str]]]:
        return scan_inbox(self.path)

    def recorded(self, delivery: Delivery) -> str:
        """What the map's identity records for a drive taken from here: its drive file's absolute path."""
        return str(delivery.drive_yaml)

    def waiting_reason(self, delivery: Delivery, quiet_period_s: float) -> str | None:
        return waiting_reason(delivery, quiet_period_s)

    def containment_problem(self, delivery: Delivery) -> str | None:
        return containment_problem(delivery, self.path)

    def fetch(self, delivery: Delivery) -> None:
        """Make the drive's files readable at ``delivery.drive_yaml`` (here: they are)."""

    def quarantine(self, entry: Path, reason: str) -> str:
        return str(quarantine(entry, self.path, reason))


@dataclass(frozen=True)
class StoreDelivery:
    """One drive prefix found in an object-store inbox: ``INBOX/<name>/drive.yaml``; ``folder`` is its local copy (in
    this process's scratch, ``storage.drive_copy_dir``), filled by ``StoreInbox.fetch``."""

    entry: str  # s3://bucket/inbox/NAME
    folder: Path  # the local copy of the drive's folder
    name: str

    @property
    def drive_yaml(self) -> Path:
        return self.folder / "drive.yaml"


class StoreInbox:
    """An inbox in a bucket (``s3://BUCKET/PREFIX``): drives delivered as prefixes ``PREFIX/NAME/`` holding
    ``drive.yaml``, by the protocol of the local inbox. ``quarantine/`` and hidden names are not looked at; there are
    no links, so containment is only that every path the drive file names stays inside the inbox (and outside its
    quarantine); complete is a ``READY`` object with no object under the drive's prefix (nor under a prefix the drive
    file names outside it) modified after it, or nothing modified for the quiet period (objects' LastModified). A
    taken drive stays where it was delivered (the map's identity records its ``s3://`` URI); its files are read from
    a local copy (``fetch``: the drive's prefix and what its drive file names, each file's modification time set to
    its object's, so that the drive's fingerprint is the same in every copy). A bad drive's objects are copied to
    ``quarantine/NAME/`` (server-side), with ``quarantine/NAME.reason.txt``, then deleted from the inbox (a run
    killed in between leaves the drive in the inbox: the next run quarantines it again)."""

    local = False

    def __init__(self, uri: str):
        from pipeline.storage import Store, drive_copy_dir

        self.store = Store.open(uri)
        self.base = self.store.root
        self.uri = self.store.uri
        self.copy = drive_copy_dir(self.uri)
        from pipeline.store import use_local_copy

        use_local_copy(self.copy)
        self._objects: dict[str, tuple[int, float]] | None = None

    def __str__(self) -> str:
        return self.uri

    def exists(self) -> bool:
        return bool(self.objects())

    def objects(self, refresh: bool = False) -> dict[str, tuple[int, float]]:
        """{path relative to the inbox: (bytes, modified unix s)} outside its quarantine, listed once per scan."""
        if self._objects is None or refresh:
            self._objects = {rel: v for rel, v in self.store.walk_objects(self.base).items()
                             if not rel.startswith(QUARANTINE + "/")}
        return self._objects

    def scan(self) -> tuple[list[StoreDelivery], list[tuple[str, str]]]:
        objs = self.objects(refresh=True)
        names = sorted({rel.split("/", 1)[0] for rel in objs if "/" in rel})
        found = [StoreDelivery(f"{self.uri}/{n}", self.copy / n, n) for n in names
                 if not n.startswith(".") and n != QUARANTINE and f"{n}/drive.yaml" in objs]
        return found, []

    def recorded(self, delivery: StoreDelivery) -> str:
        return f"{delivery.entry}/drive.yaml"

    def _refs(self, delivery: StoreDelivery) -> list[str] | None:
        """The paths the drive file names, relative to the inbox and normalised (``..`` resolved); None for one that
        leaves the inbox."""
        import posixpath
        import tempfile

        from pipeline.errors import ConfigError
        from pipeline.safe_yaml import MAX_YAML_BYTES

        size = self.objects().get(f"{delivery.name}/drive.yaml", (0, 0.0))[0]
        if size > MAX_YAML_BYTES:
            return []
        try:
            raw = self.store.read_bytes(self.base / delivery.name / "drive.yaml")
        except FileNotFoundError:
            return []
        with tempfile.TemporaryDirectory(prefix="cornermap-inbox-") as tmp:
            path = Path(tmp) / delivery.name / "drive.yaml"
            path.parent.mkdir()
            path.write_bytes(raw)
            try:
                refs = referenced_paths(path)
            except ConfigError:
                return []
            out = []
            for ref in refs:
                try:
                    rel = posixpath.normpath(posixpath.join(delivery.name, ref.relative_to(path.parent).as_posix()))
                except ValueError:  # an absolute path
                    return None
                if rel == ".." or rel.startswith("../") or rel.startswith("/") or rel.split("/", 1)[0] == QUARANTINE:
                    return None
                out.append(rel)
            return out

    def _keys(self, delivery: StoreDelivery, refs: list[str]) -> list[str]:
        """The inbox's objects of the drive: under its prefix and under every path its drive file names."""
        objs = self.objects()
        tops = [delivery.name] + [r for r in refs if not (r + "/").startswith(delivery.name + "/")]
        return sorted(k for k in objs if any(k == t or k.startswith(t + "/") for t in tops))

    def containment_problem(self, delivery: StoreDelivery) -> str | None:
        if self._refs(delivery) is None:
            return (f"{self.recorded(delivery)} names a path outside the inbox {self.uri} (or in its quarantine); "
                    "refused: a delivered drive holds its own files")
        return None

    def waiting_reason(self, delivery: StoreDelivery, quiet_period_s: float, now: float | None = None) -> str | None:
        now = time.time() if now is None else now
        objs = self.objects()
        keys = self._keys(delivery, self._refs(delivery) or [])
        marker = f"{delivery.name}/{READY_MARKER}"
        if marker in objs:
            marked = objs[marker][1]
            newest = max((objs[k][1] for k in keys if k != marker), default=marked)
            if newest > marked + CLOCK_SLACK_S:
                return (f"{delivery.entry} changed {newest - marked:.0f} s after its {READY_MARKER} marker; taken "
                        f"once {READY_MARKER} is written again after the copy")
            return None
        age = now - max((objs[k][1] for k in keys), default=0.0)
        if age >= quiet_period_s:
            return None
        return (f"{delivery.entry} changed {max(age, 0):.0f} s ago; taken after {quiet_period_s / 60:g} min without "
                f"a change (--quiet-period-min), or at once with a {READY_MARKER} object in it written after the "
                "copy")

    def fetch(self, delivery: StoreDelivery) -> None:
        """Download the drive's objects absent from the local copy, or of another size or time, into it; each
        file's modification time is its object's."""
        objs = self.objects()
        pairs, stamps = [], {}
        for key in self._keys(delivery, self._refs(delivery) or []):
            if key.endswith("/" + READY_MARKER) and key.count("/") == 1:
                continue
            size, stamp = objs[key]
            target = self.copy / key
            try:
                st = target.stat()
                if st.st_size == size and abs(st.st_mtime - stamp) < 1e-3:
                    os.utime(target, ns=(time.time_ns(), st.st_mtime_ns))  # read now: the last to go when pruned
                    continue
            except FileNotFoundError:
                pass
            pairs.append((self.base / key, target))
            stamps[target] = stamp
        self.store.download_files(pairs)
        for target, stamp in stamps.items():
            os.utime(target, (time.time(), stamp))
        remember_copy(delivery.drive_yaml, self.recorded(delivery))

    def quarantine(self, entry: str, reason: str) -> str:
        from mapservice.maps import utc_now

        name = entry.rstrip("/").rsplit("/", 1)[-1]
        qbase = self.base / QUARANTINE
        taken = set(self.store.listdir(qbase))
        dst = name if name not in taken else f"{name}-{utc_now().replace(':', '')}"
        keys = [k for k in self.objects() if k.startswith(name + "/")]
        for key in keys:
            self.store.copy(self.base / key, qbase / dst / key[len(name) + 1:])
        moved = self.store.url(qbase / dst)  # the reason's hints (`cornermap drive check URI`) name where it now is
        reason = reason.replace(f"{self.uri}/{name}/", f"{moved}/")
        self.store.put_bytes(qbase / f"{dst}.reason.txt",
                             f"{utc_now()} quarantined by cornermap rebuild: {reason.strip()}\n".encode())
        for key in keys:
            self.store.delete(self.base / key)
        return self.store.url(qbase / dst)


def open_inbox(value: "str | Path") -> "LocalInbox | StoreInbox":
    """The inbox ``--inbox`` names: a local folder, or ``s3://BUCKET/PREFIX``."""
    from pipeline.storage import uri_scheme

    return StoreInbox(str(value)) if uri_scheme(value) is not None else LocalInbox(Path(value))


def local_drive_file(recorded: str) -> Path | None:
    """The local drive file of a map drive as its identity records it: the path itself, or for an ``s3://.../NAME/
    drive.yaml`` its local copy, fetched now; None when it is gone."""
    from pipeline.storage import uri_scheme

    if uri_scheme(recorded) is None:
        return Path(recorded) if Path(recorded).is_file() else None
    base, name, leaf = recorded.rstrip("/").rsplit("/", 2)
    if leaf != "drive.yaml":
        return None
    inbox = StoreInbox(base)
    if f"{name}/drive.yaml" not in inbox.objects():
        return None
    delivery = StoreDelivery(f"{inbox.uri}/{name}", inbox.copy / name, name)
    inbox.fetch(delivery)
    return delivery.drive_yaml
