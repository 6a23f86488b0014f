"""Names that become path components (drives, maps, stages) and paths derived from input.

One pattern for every name that ends up in a path::

    NAME_PATTERN = ^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$   and no ".." anywhere

so a name is one path component: no separator, not "." or "..", no leading dot or dash (hidden files,
options), at most 64 characters. ``inside(root, *parts)`` resolves a path built from input (a name, a
manifest entry) and raises ``PathEscapeError`` unless it stays under ``root`` after resolving ``..`` and
symlinks.
"""
from __future__ import annotations

import re
from pathlib import Path

from pipeline.errors import ConfigError, OptionError, PathEscapeError

NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"
_NAME_RE = re.compile(NAME_PATTERN)


def name_problem(name: object, kind: str) -> str | None:
    """Why ``name`` is not a valid ``kind`` name (drive, map, stage), or None when it is."""
    if not isinstance(name, str) or not _NAME_RE.match(name) or ".." in name:
        return (f"{kind} name {name!r} is not allowed; expected 1-64 characters of letters, digits, '_', '.', '-' "
                f"starting with a letter or digit and without '..' ({NAME_PATTERN})")
    return None


def check_name(name: object, kind: str, where: str = "name") -> str:
    """Return ``name`` when it matches NAME_PATTERN, else raise ConfigError naming ``where`` (an ``OptionError``,
    exit 2, when ``where`` is a command-line option)."""
    problem = name_problem(name, kind)
    if problem:
        raise (OptionError if where.startswith("--") else ConfigError)(where, [problem])
    return name  # type: ignore[return-value]


def inside(root: Path | str, *parts: str | Path) -> Path:
    """``root/parts...`` resolved (``..`` and symlinks); PathEscapeError unless it stays under ``root``."""
    base = Path(root).resolve()
    for p in parts:
        if Path(p).is_absolute():
            raise PathEscapeError(f"{p!s}: an absolute path where a path relative to {base} was expected")
    path = base.joinpath(*parts).resolve()
    if path != base and base not in path.parents:
        rel = "/".join(str(p) for p in parts)
        raise PathEscapeError(f"{rel!r} resolves to {path}, outside {base}; hint: paths from input must stay "
                              "inside their root")
    return path


def published_map_dir(root: Path | str | None, name: str | None, hint: str = "pass --root ROOT --map NAME") -> Path:
    """``ROOT/maps/NAME`` of a published map, the one naming rule of every command (``--root ROOT --map NAME``);
    with no name, the only map under ``ROOT/maps``. UnknownNameError (with "did you mean") otherwise."""
    from pipeline.errors import UnknownNameError
    from pipeline.registry import suggest

    if name is not None:
        check_name(name, "map", "--map")
    from pipeline.storage import maps_dir

    maps = maps_dir(Path(root if root is not None else "."))
    have = sorted(p.name for p in maps.iterdir() if p.is_dir()) if maps.is_dir() else []
    if name is None:
        if len(have) != 1:
            raise UnknownNameError(f"{maps}: {'no maps' if not have else 'several maps: ' + ', '.join(have)}; "
                                   f"hint: {hint}")
        name = have[0]
    if name not in have:
        raise UnknownNameError(f"{maps}: no map {name!r}; have {', '.join(have) or 'none'}{suggest(name, have)}; "
                               "hint: --root is the folder holding maps/NAME")
    return maps / name
