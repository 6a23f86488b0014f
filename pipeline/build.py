"""``cornermap build``: the standard map workflow on given drives, written out for provenance."""
from __future__ import annotations

import hashlib
from pathlib import Path

import yaml

from pipeline.errors import ConfigError


def write_build_workflow(template: Path, *, drives: list[Path], map_name: str, root: Path) -> Path:
    try:
        doc = yaml.safe_load(Path(template).read_text())
    except OSError as exc:
        raise ConfigError(str(template), [f"cannot read the standard workflow: {exc}"]) from exc
    missing = [str(d) for d in drives if not Path(d).is_file()]
    if missing:
        raise ConfigError("cornermap build", [f"drive file not found: {m}" for m in missing])
    doc["map_name"] = map_name
    doc["root"] = str(Path(root).resolve())
    doc["drives"] = [{"name": Path(d).resolve().parent.name, "path": str(Path(d).resolve()), "role": "map"}
                     for d in drives]
    text = yaml.safe_dump(doc, sort_keys=False)
    out = Path(root) / "workflows" / f"build-{map_name}-{hashlib.sha256(text.encode()).hexdigest()[:8]}.yaml"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    return out
