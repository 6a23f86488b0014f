"""``cornermap maps reoptimize``: the map's drives solved again together, region by region, published through the gate.

The scheduled counterpart of the incremental rebuild (which never moves an old drive's pose): every map drive's
poses are re-solved as ``rebuild --full`` solves them (pass 1, survey anchors, loops between every pair of passes,
passes 2-3), but each solve of the pose graph runs region by region (``stages/posegraph/regions.py``: regions of at
most ``region_max_poses`` poses, a condensed separator between them, the regions of a round as tasks side by side on
the build's dask workers or pool) to the same optimum. The version then goes through what a rebuild does:
``hold_latest`` publishing, then the rebuild's own publishing (``mapservice.rebuild.gate_and_publish``: the regression
gate, LATEST moved to the verified version under the publish lock); a run killed anywhere leaves LATEST a complete
version and the next run completes from what was committed (the workflow and its params are named by content). No
drive is added; the identity is unchanged. The root may be an ``s3://`` URI as for ``rebuild``
(``mapservice.maps.MapHome``: identity, LATEST, gate records and leases in the bucket, the free-disk check on the
local scratch folder, drives delivered to a bucket read from their local copies).
Exit codes: 0 published (or LATEST already the result), 3 refused by the gate, 1 error, 75 locked.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import yaml

from mapservice.maps import MapHome
from mapservice.rebuild import RebuildResult, checked_identity, gate_and_publish, reuse_line
from pipeline import storage
from pipeline.errors import ConfigError

DEFAULT_REGION_MAX_POSES = 600  # tiny (5 drives, ~3000 poses): 6-8 regions; a region's solve stays a few seconds


@dataclass(frozen=True)
class ReoptimizeParams:
    region_max_poses: int = DEFAULT_REGION_MAX_POSES
    min_free_gib: float = 2.0
    gate: bool = True
    gate_tol_m: float = 0.05
    gate_tol_rel: float = 0.2
    workflow: str = "map_rebuild"
    scheduler: str | None = None
    params_file: Path | None = None  # --params: {stage: {param: value}} over the workflow's
    workers: int | None = None
    dask_host: str = "127.0.0.1"


def region_params_file(root: "Path | str", name: str, params: ReoptimizeParams) -> Path:
    """The run's params: the user's ``--params`` with the posegraph's region settings over them, written by content
    under ``ROOT/workflows/`` (an ``s3://`` root: its local copy's, ``storage.mirror_dir``, as the build's workflow)
    so that a killed run's next run plans the same fingerprints."""
    from pipeline.api import load_param_file
    from pipeline.declare import nested

    doc = load_param_file(params.params_file)
    doc = {k: nested(v) for k, v in doc.items()}
    posegraph = doc.setdefault("posegraph", {})
    posegraph["regions"] = {**posegraph.get("regions", {}), "max_poses": int(params.region_max_poses)}
    text = yaml.safe_dump(doc, sort_keys=True)
    base = storage.mirror_dir(str(root)) if storage.uri_scheme(root) is not None else Path(root)
    out = storage.workflows_dir(base) / f"reoptimize-{name}-{hashlib.sha256(text.encode()).hexdigest()[:8]}.yaml"
    out.parent.mkdir(parents=True, exist_ok=True)
    if not out.is_file():
        tmp = out.with_suffix(".yaml.tmp")
        tmp.write_text(text)
        tmp.replace(out)
    return out


def reoptimize(root: "Path | str", name: str, params: ReoptimizeParams = ReoptimizeParams(),
               say: Callable[[str], None] | None = None) -> RebuildResult:
    """One re-optimization of map ``name`` (module docstring); ``say(line)`` gets each line as it is made. ``root``:
    a local folder or an ``s3://`` URI."""
    from mapservice.build import write_build_workflow
    from mapservice.inbox import local_drive_file
    from pipeline.api import execute_workflow
    from pipeline.versioned import version_name

    if params.region_max_poses < 0:
        raise ConfigError("--region-max-poses", [f"expected >= 0 (0: one joint solve); got {params.region_max_poses}"])
    home = MapHome(root, name)
    home.require_identity()
    with home.run_lock():
        before, ident, notes = checked_identity(home, params.min_free_gib)
        result = RebuildResult("nothing", say=say)
        result.add(*notes)
        if not ident.drives:
            if ident != before:
                home.write_identity(ident)
            result.add(f"nothing to do: map {name!r} has no drive yet (`cornermap rebuild` adds them)")
            return result
        drives = [local_drive_file(d.path) for d in ident.drives]
        pfile = region_params_file(home.root, name, params)
        wf = write_build_workflow(params.workflow, drives=drives, map_name=name, root=home.root,
                                  origin=ident.enu_origin.plain(), tile_size_m=ident.tile_size_m,
                                  hold_latest=True, max_radius_m=ident.max_radius_km * 1000.0, held_poses=None)
        run = execute_workflow(wf, root=home.root, scheduler=params.scheduler, only=None, dry_run=False, quiet=True,
                               params_file=pfile, workers=params.workers, dask_host=params.dask_host)
        result.summary = run["summary"]
        result.add(reuse_line(run["summary"]))
        candidate, previous = gate_and_publish(home, run, ident, before, params, result, "reoptimize",
                                               fallback_drive=drives[-1])
        if result.status == "refused":
            return result
        if ident != before:
            home.write_identity(ident)
        result.status, result.version = "published", candidate
        if candidate == previous:
            result.add(f"map {name!r}: LATEST {version_name(candidate)} is already this re-optimization")
        else:
            result.add(f"published map {name!r} {version_name(candidate)} (LATEST): {len(drives)} drive(s) "
                       f"re-optimized region by region (at most {params.region_max_poses} poses a region)")
        return result
