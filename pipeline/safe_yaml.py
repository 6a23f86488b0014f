"""YAML from untrusted files with bounded work: a size cap, no aliases, and duplicate keys rejected.

PyYAML's ``safe_load`` builds no arbitrary objects but still expands aliases (a 1 kB "billion laughs"
document took 30 s and ~3 GB before a MemoryError) and lets a duplicate key silently replace the first
one. ``load_yaml`` parses with a loader that refuses both, and a document larger than ``max_bytes``:

    data = load_yaml(path.read_bytes(), where=str(path))        # ConfigError naming file, line and key

Every problem is a ``ConfigError`` (a ``ValueError``) whose message names the file and the line.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml
from yaml.constructor import ConstructorError
from yaml.nodes import MappingNode

from pipeline.errors import ConfigError

MAX_YAML_BYTES = 4 << 20  # 4 MiB: workflows, catalogs and drive files are a few kB
MAX_YAML_NODES = 1_000_000  # scalars + collections in one document (bounds time on a flat but long file)


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that refuses aliases (anchors are harmless alone) and duplicate mapping keys."""

    def __init__(self, stream: str):
        super().__init__(stream)
        self._nodes = 0

    def compose_node(self, parent, index):  # noqa: ANN001 - PyYAML's signature
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise ConstructorError(None, None, f"alias *{event.anchor} is not allowed (aliases are refused "
                                   "so that a small file cannot expand into a huge one)", event.start_mark)
        self._nodes += 1
        if self._nodes > MAX_YAML_NODES:
            raise ConstructorError(None, None, f"more than {MAX_YAML_NODES} nodes", self.peek_event().start_mark)
        return super().compose_node(parent, index)

    def construct_mapping(self, node, deep=False):  # noqa: ANN001
        if isinstance(node, MappingNode):
            seen: dict[Any, int] = {}
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=True)
                try:
                    hash(key)
                except TypeError:
                    continue  # PyYAML itself reports unhashable keys
                if key in seen:
                    raise ConstructorError(
                        None, None, f"duplicate key {key!r} (first on line {seen[key] + 1}); a duplicate would "
                        "silently replace the first value", key_node.start_mark)
                seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep=deep)


def load_yaml(text: str | bytes, where: str, *, max_bytes: int = MAX_YAML_BYTES) -> Any:
    """Parse one YAML document from ``text`` (read from ``where``) with bounded work.

    Raises ConfigError for: more than ``max_bytes`` bytes, bytes that are not UTF-8, invalid YAML, any
    alias (``*name``), a duplicate mapping key (with its line), or more than MAX_YAML_NODES nodes.
    """
    size = len(text.encode("utf-8", "surrogatepass") if isinstance(text, str) else text)
    if size > max_bytes:
        raise ConfigError(where, [f"{size} bytes, more than the {max_bytes}-byte limit for a YAML file"])
    if isinstance(text, bytes):
        try:
            text = text.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ConfigError(where, [f"not UTF-8 text (byte {exc.start}: {text[exc.start:exc.start + 1]!r})"]) from exc
    loader = _StrictLoader(text)
    try:
        return loader.get_single_data()
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        at = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        raise ConfigError(where, [f"{at}{exc.problem or exc.context or 'invalid YAML'}"]) from exc
    except yaml.YAMLError as exc:
        raise ConfigError(where, [f"not valid YAML: {exc}"]) from exc
    except RecursionError as exc:
        raise ConfigError(where, ["nested too deeply"]) from exc
    finally:
        loader.dispose()


def load_yaml_file(path: Path | str, *, max_bytes: int = MAX_YAML_BYTES) -> Any:
    """``load_yaml`` of a file's bytes; an unreadable or oversized file is a ConfigError naming it."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > max_bytes:
            raise ConfigError(str(path), [f"{size} bytes, more than the {max_bytes}-byte limit for a YAML file"])
        with open(path, "rb") as fh:  # the size was checked; read(n) would preallocate n bytes
            raw = fh.read()
    except OSError as exc:
        raise ConfigError(str(path), [f"cannot read: {exc.strerror or exc}"]) from exc
    return load_yaml(raw, str(path), max_bytes=max_bytes)
