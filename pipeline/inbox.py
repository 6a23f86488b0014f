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
"""
from __future__ import annotations

import os
import stat
import time
from dataclasses import dataclass
from pathlib import Path

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
    from pipeline.maps import utc_now

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
