"""``cornermap evaluate``: localize one drive on a published map, as a vehicle would, and score it.

The drive is ingested like any drive (ingest, odometry, corners; posegraph for the ``map`` reference) in a
small generated workflow under ``OUT/work`` whose ENU origin is the map's, then the evaluate stage's compute
runs with the map read through the tiles loader. Heavy imports happen inside the command.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

EXAMPLES = ("Examples:\n\n"
            "  cornermap evaluate --map runs/demo/maps/demo --drive runs/sim/drive_1/drive.yaml "
            "--reference runs/sim/truth/drive_1_poses_tum.txt --out runs/eval1\n\n"
            "  cornermap evaluate --map runs/demo/maps/demo --version v0002 --drive D.yaml --method ekf "
            "--reference map --out runs/eval2")


def _write_workflow(out: Path, drive: Path, reference: Optional[str], origin: dict, map_name: str) -> Path:
    import yaml

    stages = ["ingest", "odometry", "corners"] + (["posegraph"] if reference in (None, "map") else [])
    import re

    entry = {"name": re.sub(r"[^A-Za-z0-9_.-]", "_", drive.resolve().parent.name).lstrip("._-")[:64] or "drive", "path": str(drive.resolve()), "role": "eval"}
    if reference not in (None, "map"):
        entry["reference"] = str(Path(reference).resolve())
    doc = {"name": f"evaluate-{entry['name']}", "root": str((out / "work").resolve()),
           "map_name": re.sub(r"[^A-Za-z0-9_.-]", "_", map_name).lstrip("._-")[:64] or "map",
           "enu_origin": {"lat_deg": origin["lat_deg"], "lon_deg": origin["lon_deg"], "h_m": origin["h_m"]},
           "drives": [entry], "stages": stages}
    path = out / "work" / "evaluate_workflow.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def evaluate_cmd(map_dir: Path = typer.Option(..., "--map", help="ROOT/maps/NAME of a published map."),
                 version: str = typer.Option("LATEST", "--version", help="LATEST, vNNNN or N."),
                 drive: Path = typer.Option(..., "--drive", help="drive.yaml of the evaluation drive."),
                 method: str = typer.Option("both", "--method", help="ekf | mcl | both"),
                 reference: Optional[str] = typer.Option(None, "--reference",
                                                         help="TRAJ.tum (truth) or 'map' (pose-graph co-registration)."),
                 out: Path = typer.Option(..., "--out", help="Output directory (metrics.json, report.html, ...)."),
                 quiet: bool = typer.Option(False, "--quiet", "-q")) -> None:
    """Localize a drive on a published map (corner EKF, marking MCL, RTK/INS and ICP baselines) and score it."""
    from pipeline.errors import ConfigError
    from stages.evaluate.outputs import metrics_table_text
    from stages.tiles.loader import open_map

    problems = []
    if method not in ("ekf", "mcl", "both"):
        problems.append(f"--method: expected ekf, mcl or both; got {method!r}")
    if not drive.is_file():
        problems.append(f"--drive: no such file {drive}")
    if reference not in (None, "map") and not Path(reference).is_file():
        problems.append(f"--reference: expected a TUM file or 'map'; no such file {reference}")
    if out.exists() and not out.is_dir():
        problems.append(f"--out: {out} exists and is not a directory")
    if problems:
        raise ConfigError("cornermap evaluate", problems)
    reader = open_map(map_dir, version)
    out.mkdir(parents=True, exist_ok=True)
    doc = run_evaluation(reader, drive, reference, ["ekf", "mcl"] if method == "both" else [method], out, quiet)
    typer.echo(metrics_table_text(doc))
    typer.echo(f"report: {(out / 'report.html').resolve()}")


def run_evaluation(reader, drive: Path, reference: Optional[str], methods: list[str], out: Path, quiet: bool) -> dict:
    """Ingest the drive in a generated workflow, then run the evaluate compute on the committed datasets."""
    import json

    import pyarrow as pa

    from pipeline.cli import execute_workflow
    from pipeline.declare import PartitionKey, StageContext
    from pipeline.store import StoreInputReader
    from stages.evaluate.compute import compute
    from stages.evaluate.decl import STAGE
    from stages.evaluate.params import EvaluateParams

    wf_path = _write_workflow(out, drive, reference, reader.origin.as_dict(), reader.path.parent.name)
    result = execute_workflow(wf_path, root=None, scheduler=None, only=None, dry_run=False, quiet=quiet)
    plan = result["plan"]
    produced = {ds: sp.fingerprint for sp in plan.stages.values() for ds in sp.outputs.values()}
    inputs = {arg: (ds, produced.get(ds, "")) for arg, ds in STAGE.inputs.items() if arg != "map"}
    store = StoreInputReader(plan.root, inputs, {arg: None for arg in inputs})
    map_row = pa.table({"map_name": [reader.path.parent.name], "version": [reader.version],
                        "path": [str(reader.path)]})
    drive_name = next(iter(plan.workflow.spec.drives)).name
    settings = plan.workflow.settings(plan.root)
    settings["references"] = {drive_name: str(Path(reference).resolve()) if reference not in (None, "map") else None}
    ctx = StageContext(stage="evaluate", partition=PartitionKey(drive=drive_name),
                       params=EvaluateParams(methods=methods), inputs=_WithMap(store, map_row), drives={},
                       settings=settings, scratch_dir=out / "work" / "scratch", artifact_dirs={"report": out})
    compute(ctx)  # writes metrics.json, report.html, <method>_tum.txt and epochs.parquet into out
    return json.loads((out / "metrics.json").read_text())


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
    app.command("evaluate", help=(evaluate_cmd.__doc__ or "") + "\n\n" + EXAMPLES)(evaluate_cmd)
