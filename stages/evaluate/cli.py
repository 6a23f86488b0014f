"""``cornermap evaluate``: localize one drive on a published map, as a vehicle would, and score it.

The drive is ingested like any drive (ingest, odometry, corners; posegraph for the ``map`` reference) in a
small generated workflow under ``OUT/work`` whose ENU origin is the map's, then the evaluate stage's compute
runs with the map read through the tiles loader. Heavy imports happen inside the command.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from pipeline import cli_options as opts

EXAMPLES = ("Examples:\n\n"
            "  cornermap evaluate --map city --root runs/maps --drive runs/sim/drive_1/drive.yaml "
            "--reference runs/sim/truth/drive_1_poses_tum.txt --out runs/eval1\n\n"
            "  cornermap evaluate --map tiny --root runs/tiny --map-version v0001 --drive runs/sim/drive_1/drive.yaml "
            "--method ekf --reference map --out runs/eval2")


def _write_workflow(out: Path, drive: Path, reference: Optional[str], origin: dict, map_name: str,
                    stage_params: dict) -> Path:
    import re

    import yaml

    def safe(name: str, default: str) -> str:  # a generated drive/map name must pass pipeline.names
        return re.sub(r"[^A-Za-z0-9_.-]", "_", name).lstrip("._-")[:64] or default

    from pipeline.drive_store import drive_name, is_uri
    from pipeline.storage import normalise_uri

    stages = ["ingest", "odometry", "corners"] + (["posegraph"] if reference in (None, "map") else [])
    path = normalise_uri(drive) if is_uri(drive) else str(drive.resolve())  # a drive in a bucket: its tasks fetch it
    entry = {"name": safe(drive_name(drive), "drive"), "path": path, "role": "eval"}
    if reference not in (None, "map", "gnss"):
        entry["reference"] = str(Path(reference).resolve())
    doc = {"name": f"evaluate-{entry['name']}", "root": str((out / "work").resolve()),
           "map_name": safe(map_name, "map"),
           "enu_origin": {"lat_deg": origin["lat_deg"], "lon_deg": origin["lon_deg"], "h_m": origin["h_m"]},
           "drives": [entry], "stages": stages,
           "params": {k: v for k, v in stage_params.items() if k in stages}}
    path = out / "work" / "evaluate_workflow.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def open_named_map(root: Path, map_arg: Optional[str], version: str):
    """The map named as on every command: ``--root ROOT --map NAME [--map-version vNNNN]`` (the only map under
    ROOT/maps without ``--map``); a root in a bucket (``s3://BUCKET/PREFIX``) is read from the bucket (the loader
    downloads the version and checks it there)."""
    from mapformat.loader import open_map
    from pipeline.errors import OptionError
    from pipeline.names import published_map_dir
    from pipeline.storage import uri_scheme
    from pipeline.store_maps import map_location

    if map_arg is not None and ("/" in map_arg or "\\" in map_arg):
        raise OptionError("--map", [f"{map_arg!r} is a path; a map is named: --root ROOT --map NAME "
                                    "(ROOT/maps/NAME), its version --map-version vNNNN"])
    if uri_scheme(root) is not None:
        return open_map(map_location(root, map_arg), version)
    return open_map(published_map_dir(root, map_arg), version)


def _evaluate_params(params_file: Optional[Path], methods: list[str], reference_frame: Optional[str],
                     fail_on_targets: bool) -> tuple[object, dict]:
    from pydantic import ValidationError

    from pipeline.api import load_param_file
    from pipeline.errors import ConfigError
    from stages.evaluate.params import EvaluateParams

    overrides = load_param_file(params_file) if params_file else {}
    mine = dict(overrides.get("evaluate", {}))
    mine["methods"] = methods
    if reference_frame is not None:
        mine["reference"] = {**mine.get("reference", {}), "frame": reference_frame}
    if fail_on_targets:
        mine["fail_on_targets"] = True
    try:
        return EvaluateParams(**mine), {k: v for k, v in overrides.items() if k != "evaluate"}
    except ValidationError as exc:
        raise ConfigError("cornermap evaluate", [f"{'.'.join(map(str, e['loc']))}: {e['msg']}"
                                                 for e in exc.errors()]) from None


def evaluate_cmd(
    drive: Path = typer.Option(..., "--drive", help="drive.yaml of the evaluation drive."),
    root: Path = opts.ROOT_OR_URI,
    map_arg: Optional[str] = opts.MAP_OR_ONLY,
    version: str = opts.MAP_VERSION,
    old_version: Optional[str] = opts.MOVED_VERSION,
    method: str = typer.Option("both", "--method", help="ekf | mcl | both"),
    reference: Optional[str] = typer.Option(
        None, "--reference", help="TRAJ.tum (truth), 'map' (pose-graph co-registration) or 'gnss' (the drive's own "
        "GNSS/INS through its drive file, lever arm applied, in the map's frame)."
    ),
    reference_frame: Optional[str] = typer.Option(
        None,
        "--reference-frame",
        help="Frame of --reference TRAJ.tum: auto (the ENU origin its header "
        "line or TRAJ.frame.json states; refused if none), map, or LAT,LON,H.",
    ),
    fail_on_targets: bool = typer.Option(
        False, "--fail-on-targets", help="Exit 3 when a target is missed (no coverage always does)."
    ),
    params: Optional[Path] = typer.Option(
        None, "--params", help="YAML {stage: {param: value}}; the 'evaluate' entry sets targets and thresholds."
    ),
    out: Path = typer.Option(..., "--out", help="Output directory (metrics.json, report.html, ...)."),
    quiet: bool = opts.QUIET,
    as_json: bool = opts.JSON,
) -> None:
    """Localize a drive on a published map (corner EKF, marking MCL, RTK/INS and ICP baselines), score it and give a
    verdict: exit 3 when the drive has no map coverage or, with --fail-on-targets, when a target is missed."""
    import json

    from pipeline.errors import ConfigError, DataQualityError, OptionError
    from stages.evaluate.outputs import metrics_table_text
    from stages.evaluate.verdict import verdict_line

    if method not in ("ekf", "mcl", "both"):
        raise OptionError("--method", [f"expected ekf, mcl or both; got {method!r}"])
    if reference_frame is not None and reference in (None, "map", "gnss"):
        raise OptionError("--reference-frame", ["applies to a --reference TRAJ.tum file only"])
    from pipeline.drive_store import drive_exists

    problems = []
    if not drive_exists(drive):
        problems.append(f"--drive: no such file {drive}")
    if reference not in (None, "map", "gnss") and not Path(reference).is_file():
        problems.append(f"--reference: expected a TUM file, 'map' or 'gnss'; no such file {reference}")
    if out.exists() and not out.is_dir():
        problems.append(f"--out: {out} exists and is not a directory")
    if problems:
        raise ConfigError("cornermap evaluate", problems)
    p, stage_params = _evaluate_params(params, ["ekf", "mcl"] if method == "both" else [method], reference_frame,
                                       fail_on_targets)
    reader = open_named_map(root, map_arg, version)
    out.mkdir(parents=True, exist_ok=True)
    def summary(doc: dict) -> dict:
        return {"map": reader.path.parent.name, "map_version": f"v{reader.version:04d}", "drive": _shown(drive),
                "verdict": doc.get("verdict"), "methods": doc.get("methods"),
                "report": str((out / "report.html").resolve()), "metrics": str((out / "metrics.json").resolve())}

    try:
        doc = run_evaluation(reader, drive, reference, p, out, quiet, stage_params)
    except DataQualityError:  # a verdict that fails (exit 3) is still a result a program reads
        if as_json and (out / "metrics.json").is_file():
            opts.echo_json(summary(json.loads((out / "metrics.json").read_text())))
        raise
    if as_json:
        opts.echo_json(summary(doc))
        return
    typer.echo(metrics_table_text(doc))
    typer.echo(verdict_line(doc["verdict"]))
    typer.echo(f"report: {(out / 'report.html').resolve()}")


def _shown(drive: Path) -> str:
    from pipeline.storage import normalise_uri

    return normalise_uri(drive)


def run_evaluation(reader, drive: Path, reference: Optional[str], p, out: Path, quiet: bool,
                   stage_params: Optional[dict] = None) -> dict:
    """Ingest the drive in a generated workflow, then run the evaluate compute on the committed datasets. Progress
    (the ingest's stages, then the evaluation's steps) goes to the display open in this process, else to one of its
    own unless ``quiet``."""
    import json

    import pyarrow as pa

    from pipeline.api import execute_workflow
    from pipeline.catalog import resolve_schema
    from pipeline.declare import PartitionKey, StageContext
    from pipeline.progress import StageProgress, finish, report
    from pipeline.reader import StoreInputReader
    from stages.evaluate.compute import compute
    from stages.evaluate.decl import STAGE

    with StageProgress(enabled=not quiet):
        wf_path = _write_workflow(out, drive, reference, reader.origin.as_dict(), reader.path.parent.name,
                                  stage_params or {})
        result = execute_workflow(wf_path, root=None, scheduler=None, only=None, dry_run=False, quiet=True)
        plan = result["plan"]
        produced = {ds: sp.fingerprint for sp in plan.stages.values() for ds in sp.outputs.values()}
        inputs = {arg: (ds, produced.get(ds, "")) for arg, ds in STAGE.inputs.items() if arg != "map"}
        catalog = plan.workflow.catalog
        schemas = {arg: resolve_schema(catalog.datasets[ds].schema_ref) if ds in catalog.datasets else None
                   for arg, (ds, _) in inputs.items()}
        store = StoreInputReader(plan.root, inputs, schemas)
        map_row = pa.table({"map_name": [reader.path.parent.name], "version": [reader.version],
                            "path": [str(Path(reader.path).resolve())]})  # absolute: the work root is elsewhere
        drive_name = next(iter(plan.workflow.spec.drives)).name
        settings = plan.workflow.settings(plan.root)
        if reference == "gnss":  # the drive's GNSS/INS as ingest read it (gnss_enu), as a TUM file stating its frame
            reference = str(_gnss_reference_file(store.read("gnss"), drive_name, reader.origin, out))
        truth = str(Path(reference).resolve()) if reference not in (None, "map") else None
        settings["references"] = {drive_name: truth}
        ctx = StageContext(stage="evaluate", partition=PartitionKey(drive=drive_name),
                           params=p, inputs=_WithMap(store, map_row), drives={},
                           settings=settings, scratch_dir=out / "work" / "scratch", artifact_dirs={"report": out},
                           step_progress=lambda step, done, total: report("evaluate", done, total, step=step))
        compute(ctx)  # writes metrics.json, report.html, <method>_tum.txt and epochs.parquet into out
        finish("evaluate")
    return json.loads((out / "metrics.json").read_text())


def _gnss_reference_file(gnss, drive: str, origin, out: Path) -> Path:
    """``OUT/gnss_reference_tum.txt``: the drive's ``gnss_enu`` fixes (vehicle origin, map ENU frame; attitude Rz Ry
    Rx, a missing roll/pitch as 0) with the map's frame in its header. ConfigError when the drive has no fix."""
    import numpy as np
    import pyarrow.compute as pc
    from scipy.spatial.transform import Rotation

    from pipeline.errors import ConfigError
    from stages.common.geometry import write_tum
    from stages.common.trajectory_frame import frame_header

    rows = gnss.filter(pc.equal(gnss["drive"], drive)) if gnss.num_rows else gnss
    if not rows.num_rows:
        raise ConfigError("cornermap evaluate", ["--reference gnss: the drive has no GNSS/INS fix (no gnss section, "
                                                 "or every row rejected: see its ingest report)"])
    rows = rows.sort_by("stamp_ns")
    col = {c: np.nan_to_num(rows[c].to_numpy()) for c in ("east_m", "north_m", "up_m", "roll_rad", "pitch_rad",
                                                         "yaw_enu_rad")}
    T = np.tile(np.eye(4), (rows.num_rows, 1, 1))
    T[:, :3, :3] = Rotation.from_euler("ZYX", np.column_stack([col["yaw_enu_rad"], col["pitch_rad"],
                                                              col["roll_rad"]])).as_matrix()
    T[:, :3, 3] = np.column_stack([col["east_m"], col["north_m"], col["up_m"]])
    path = out / "gnss_reference_tum.txt"
    write_tum(path, rows["stamp_ns"].to_numpy() * 1e-9, T, header=frame_header(origin) + "\nreference: the drive's "
              "GNSS/INS fixes (gnss_enu)")
    return path


class _WithMap:
    """The store's reader plus the one-row ``map`` input naming the published version."""

    def __init__(self, store, map_row):
        self._store, self._map = store, map_row

    def read(self, arg, **kw):
        return self._map if arg == "map" else self._store.read(arg, **kw)

    def has(self, arg):
        return arg == "map" or self._store.has(arg)

    def __getattr__(self, name):
        return getattr(self._store, name)


def register(app: typer.Typer) -> None:
    import inspect

    app.command("evaluate", help=inspect.cleandoc(evaluate_cmd.__doc__ or "") + "\n\n" + EXAMPLES)(evaluate_cmd)
