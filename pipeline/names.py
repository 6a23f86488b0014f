"""Names that become path components (drives, maps, stages) and paths derived from input.

One pattern for every name that ends up in a path::

    NAME_PATTERN = ^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$   and no ".." anywhere

so a name is one path component: no separator, not "." or "..", no leading dot or dash (hidden files,
options), at most 64 characters. ``inside(root, *parts)`` (defined beside the layout, ``pipeline.storage``)
resolves a path built from input (a name, a manifest entry) and raises ``PathEscapeError`` unless it stays under
``root`` after resolving ``..`` and symlinks. ``suggest``: the "did you mean" of every unknown name.
"""
from __future__ import annotations

import difflib
import re
from pathlib import Path

from pipeline.errors import ConfigError, OptionError, UnknownNameError
from pipeline.storage import inside, maps_dir  # noqa: F401 - inside: the path rule, imported from here by its callers

NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"
_NAME_RE = re.compile(NAME_PATTERN)


def suggest(name: str, known) -> str:
    """`` (did you mean 'x'?)`` for the closest of ``known`` to ``name``, or ``""``."""
    close = difflib.get_close_matches(name, list(known), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


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


def published_map_dir(root: Path | str | None, name: str | None, hint: str = "pass --root ROOT --map NAME") -> Path:
    """``ROOT/maps/NAME`` of a published map, the one naming rule of every command (``--root ROOT --map NAME``);
    with no name, the only map under ``ROOT/maps``. UnknownNameError (with "did you mean") otherwise."""
    if name is not None:
        check_name(name, "map", "--map")
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
