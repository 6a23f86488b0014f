"""``cornermap build``: the standard map workflow on given drives, written out for provenance."""
from __future__ import annotations

import hashlib
from pathlib import Path

import yaml

from pipeline import storage
from pipeline.errors import ConfigError, OptionError


def parse_origin(text: str) -> dict[str, float]:
    """``--origin LAT,LON,H`` (degrees, degrees, metres above the WGS84 ellipsoid) -> an ``enu_origin`` mapping;
    OptionError (exit 2) naming every problem (``stages.common.geodesy.EnuOrigin.parse``)."""
    from stages.common.geodesy import EnuOrigin, OriginError

    try:
        return EnuOrigin.parse(text).plain()
    except OriginError as exc:
        raise OptionError("--origin", exc.problems) from None


def write_build_workflow(template: str | Path, *, drives: list[Path], map_name: str, root: Path | str,
                         origin: dict[str, float] | None = None, tile_size_m: float | None = None,
                         hold_latest: bool = False, max_radius_m: float | None = None,
                         held_poses: dict | None = None, map_root: Path | None = None) -> Path:
    """The map workflow (a file or a packaged name) with these drives, map name, root and origin, written under
    ``ROOT/workflows/`` (absolute paths: the build's record of what it ran). ``hold_latest``: publish the
    version without moving LATEST (``cornermap rebuild`` moves it after its regression gate). ``max_radius_m``: the
    map's area (default: its identity's ``max_radius_km``, else the workflow's own). An object-store root
    (``s3://``): the workflow is written in its local copy (``storage.mirror_dir``) and uploaded to
    ``ROOT/workflows/``; it names no root (the run is given it); ``map_root`` is where the map's identity was
    downloaded (default: ``root``)."""
    from pipeline.resources import resolve_workflow
    from pipeline.safe_yaml import load_yaml_file
    from pipeline.storage import Store, mirror_dir, normalise_uri, uri_scheme

    path = resolve_workflow(template)
    doc = load_yaml_file(path)
    if not isinstance(doc, dict):
        raise ConfigError(str(path), ["the map workflow is not a mapping"])
    from pipeline.drive_store import drive_exists, drive_name, is_uri

    missing = [str(normalise_uri(d)) for d in drives if not drive_exists(d)]
    if missing:
        raise ConfigError("cornermap build", [f"drive file not found: {m}" for m in missing])
    catalog = doc.get("catalog")
    if catalog:  # keep a template's own catalog where it is once the workflow is written elsewhere
        doc["catalog"] = [str((path.parent / c).resolve()) for c in catalog]
    doc["map_name"] = map_name
    remote = uri_scheme(root) is not None
    if remote:
        doc.pop("root", None)
    else:
        doc["root"] = str(Path(root).resolve())
    if origin is not None:
        doc["enu_origin"] = dict(origin)
    if tile_size_m is not None:
        doc["tile_size_m"] = float(tile_size_m)
    if hold_latest:
        doc["hold_latest"] = True
    if held_poses:  # incremental pose graph: these published poses are held (stages/posegraph/incremental.py)
        doc["held_poses"] = dict(held_poses)
    if max_radius_m is None:
        from mapservice.maps import map_dir, read_identity

        ident = read_identity(map_dir(map_root if map_root is not None else root, map_name))
        max_radius_m = ident.max_radius_km * 1000.0 if ident is not None else None
    if max_radius_m is not None:
        doc["max_radius_m"] = float(max_radius_m)
    doc["drives"] = [{"name": drive_name(d), "path": _drive_path(d, root) if remote or is_uri(d)
                      else str(Path(d).resolve()), "role": "map"} for d in drives]
    text = yaml.safe_dump(doc, sort_keys=False)
    name = f"build-{map_name}-{hashlib.sha256(text.encode()).hexdigest()[:8]}.yaml"
    out = storage.workflows_dir(mirror_dir(str(root)) if remote else Path(root)) / name
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".yaml.tmp")
    tmp.write_text(text)
    tmp.replace(out)
    if remote:
        store = Store.open(str(root))
        store.put_bytes(storage.workflows_dir(store.root) / name, text.encode("utf-8"))
    return out


def _drive_path(drive: "str | Path", root: "str | Path") -> str:
    """What the workflow of a build names a drive by when its tasks must read it from the store: a drive given by
    URI as is; a local copy of a drive delivered to a bucket (``mapservice.inbox``) by its URI; any other local drive
    (on an object-store root) staged into the root (``pipeline.drive_store.stage_drive``: uploaded once, by
    content)."""
    from pipeline.drive_store import is_uri, source_of_copy, stage_drive
    from pipeline.storage import normalise_uri

    if is_uri(drive):
        return normalise_uri(drive)
    source = source_of_copy(Path(drive))
    if source is not None:
        return source
    return stage_drive(str(root), Path(drive))
