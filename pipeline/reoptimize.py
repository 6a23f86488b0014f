"""``cornermap maps reoptimize``: the map's drives solved again together, region by region, published through the gate.

The scheduled counterpart of the incremental rebuild (which never moves an old drive's pose): every map drive's
poses are re-solved as ``rebuild --full`` solves them (pass 1, survey anchors, loops between every pair of passes,
passes 2-3), but each solve of the pose graph runs region by region (``stages/posegraph/regions.py``: regions of at
most ``region_max_poses`` poses, a condensed separator between them, the regions of a round as tasks side by side on
the build's dask workers or pool) to the same optimum. The version then goes through what a rebuild does:
``hold_latest`` publishing, the regression gate (``pipeline.gate``), LATEST moved under the publish lock; a run
killed anywhere leaves LATEST a complete version and the next run completes from what was committed (the
workflow and its params are named by content). No drive is added; the identity is unchanged.
Exit codes: 0 published (or LATEST already the result), 3 refused by the gate, 1 error, 75 locked.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import yaml

from pipeline import storage
from pipeline.errors import ConfigError, StageError
from pipeline.maps import MapHome, check_free_disk, map_dir, require_identity, run_lock, write_identity
from pipeline.rebuild import RebuildResult, check_map_drives, reuse_line

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


def region_params_file(root: Path, name: str, params: ReoptimizeParams) -> Path:
    """The run's params: the user's ``--params`` with the posegraph's region settings over them, written by content
    under ``ROOT/workflows/`` (a killed run's next run plans the same fingerprints)."""
    from pipeline.api import load_param_file

    doc = load_param_file(params.params_file)
    doc = {k: dict(v) for k, v in doc.items()}
    doc.setdefault("posegraph", {})["region_max_poses"] = int(params.region_max_poses)
    text = yaml.safe_dump(doc, sort_keys=True)
    out = storage.workflows_dir(Path(root)) / f"reoptimize-{name}-{hashlib.sha256(text.encode()).hexdigest()[:8]}.yaml"
    out.parent.mkdir(parents=True, exist_ok=True)
    if not out.is_file():
        tmp = out.with_suffix(".yaml.tmp")
        tmp.write_text(text)
        tmp.replace(out)
    return out


def reoptimize(root: Path, name: str, params: ReoptimizeParams = ReoptimizeParams(),
               say: Callable[[str], None] | None = None) -> RebuildResult:
    """One re-optimization of map ``name`` (module docstring); ``say(line)`` gets each line as it is made."""
    from pipeline.api import execute_workflow, published_version
    from pipeline.build import write_build_workflow
    from pipeline.gate import run_gate
    from pipeline.versioned import read_latest, version_name

    if params.region_max_poses < 0:
        raise ConfigError("--region-max-poses", [f"expected >= 0 (0: one joint solve); got {params.region_max_poses}"])
    root = Path(root).resolve()
    mdir = map_dir(root, name)
    require_identity(mdir)
    with run_lock(mdir):
        ident = require_identity(mdir)
        before = ident
        check_free_disk(root, params.min_free_gib)
        ident, problems, notes = check_map_drives(ident)
        if problems:
            raise ConfigError(f"map {name!r}", problems)
        result = RebuildResult("nothing", say=say)
        result.add(*notes)
        if not ident.drives:
            if ident != before:
                write_identity(mdir, ident)
            result.add(f"nothing to do: map {name!r} has no drive yet (`cornermap rebuild` adds them)")
            return result
        drives = [Path(d.path) for d in ident.drives]
        pfile = region_params_file(root, name, params)
        wf = write_build_workflow(params.workflow, drives=drives, map_name=name, root=root,
                                  origin=ident.enu_origin.model_dump(), tile_size_m=ident.tile_size_m,
                                  hold_latest=True, max_radius_m=ident.max_radius_km * 1000.0, held_poses=None)
        run = execute_workflow(wf, root=root, scheduler=params.scheduler, only=None, dry_run=False, quiet=True,
                               params_file=pfile, workers=params.workers, dask_host=params.dask_host)
        result.summary = run["summary"]
        result.add(reuse_line(run["summary"]))
        candidate = published_version(run["plan"])
        if candidate is None:
            raise StageError(f"reoptimize of map {name!r}: the build committed no map_tiles rows (no version)")
        previous = read_latest(mdir) if storage.latest_file(mdir).exists() else None
        if candidate == previous:
            result.status, result.version = "published", candidate
            result.add(f"map {name!r}: LATEST {version_name(candidate)} is already this re-optimization")
            if ident != before:
                write_identity(mdir, ident)
            return result
        if previous is not None and params.gate:
            check = ident.check_drive
            drive, reference = (Path(check.path), check.reference) if check else (drives[-1], None)
            verdict = run_gate(mdir, candidate, previous, drive, reference, params.gate_tol_m, params.gate_tol_rel)
            result.add(*verdict.table)
            if not verdict.ok:
                result.status, result.version = "refused", candidate
                result.add(f"refused: {version_name(candidate)} is worse than {version_name(previous)} on "
                           f"{drive.parent.name}; LATEST stays {version_name(previous)}")
                if ident != before:
                    write_identity(mdir, ident)
                return result
        MapHome(root, name).move_latest(candidate)  # verified under the publish lock, as a rebuild publishes
        if ident != before:
            write_identity(mdir, ident)
        result.status, result.version = "published", candidate
        result.add(f"published map {name!r} {version_name(candidate)} (LATEST): {len(drives)} drive(s) re-optimized "
                   f"region by region (at most {params.region_max_poses} poses a region)")
        return result
