"""A workflow root as the benches read it: the newest committed version of a dataset, and the simulator's output
(truth included) that the root's simulate stage wrote."""
from __future__ import annotations

import json
from pathlib import Path


def latest(root: Path, dataset: str) -> Path:
    """The newest committed version folder of ``dataset`` under ROOT/datasets (by its manifest's
    ``committed_utc``, then the manifest's time); SystemExit naming the folder when there is none."""
    base = Path(root) / "datasets" / dataset
    dirs = [p for p in base.glob("*") if (p / "_manifest.json").is_file()] if base.is_dir() else []
    if not dirs:
        raise SystemExit(f"no committed {dataset} under {base} (run the workflow up to the stage that writes it)")

    def committed(p: Path) -> tuple[str, float]:
        manifest = p / "_manifest.json"
        return json.loads(manifest.read_text()).get("committed_utc", ""), manifest.stat().st_mtime

    return max(dirs, key=committed)


def dataset(root: Path, name: str):
    """The newest committed version of dataset ``name`` as a ``pyarrow.dataset.Dataset`` (filter before reading)."""
    import pyarrow.dataset as ds

    return ds.dataset(str(latest(root, name)), format="parquet", partitioning="hive")


def read(root: Path, name: str, **kwargs):
    """The newest committed version of dataset ``name`` as one Arrow table (``kwargs`` go to ``to_table``)."""
    return dataset(root, name).to_table(**kwargs)


def simulator_dir(root: Path) -> Path:
    """The simulator output of a root's simulate stage (its ``truth/`` folder, the drive folders), or the ``sim/``
    folder that ``bench_seeds --no-survey`` simulates into when the root has no simulate stage."""
    own = Path(root) / "sim"
    if (own / "simulation.json").is_file() and not (Path(root) / "datasets" / "raw_drives").is_dir():
        return own
    return latest(root, "raw_drives") / "artifacts" / "all"
