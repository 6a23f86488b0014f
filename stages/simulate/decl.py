"""Stage declaration of ``simulate`` (imports nothing heavy)."""
from __future__ import annotations

from typing import Literal

from pipeline.declare import Params, Partitioning, StageDecl
from stages import code_version


class SimulateParams(Params):
    preset: Literal["tiny", "demo", "gangnam", "tiny_consumer", "demo_consumer", "kitti_city"] = "tiny"
    seed: int = 0
    drives: int | None = None  # None: the preset's default (2)
    motion_distortion: bool = True
    # preset fields to change, e.g. {lead_vehicle_share: 0.6} (the issue-25 test city); see `simulate --set`
    preset_overrides: dict[str, float | tuple[float, float] | str] = {}
    changes: bool = False  # dated variants: later drives see a changed city (stages/simulate/changes.py)
    changes_from_drive: int | None = None  # first drive that sees the changed city; None: the last drive


STAGE = StageDecl(
    name="simulate",
    summary="Synthetic city and drives (HDL-32E scans, urban RTK/INS, odometry, survey LAS, ground truth).",
    code_version=code_version("5", "simulate"),
    inputs={},
    outputs={"drives": "raw_drives"},
    params=SimulateParams,
    partition=Partitioning.SINGLE,
    compute="stages.simulate.compute:compute",
    cli="stages.simulate.cli",
    settings_keys=frozenset(),
)
