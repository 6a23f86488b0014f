"""Engine adapter: write the whole simulation into the stage's ``drives`` artifact directory."""
from __future__ import annotations

from pipeline.declare import StageContext


def compute(ctx: StageContext) -> dict:
    from stages.simulate.core import simulate

    p = ctx.params
    summary = simulate(p.preset, p.seed, ctx.artifact_dir("drives"), n_drives=p.drives,
                       motion_distortion=p.motion_distortion, changes=p.changes,
                       changes_from_drive=p.changes_from_drive)
    return {"drives": None, "_extra": {"enu_origin": summary.enu_origin, "drives": summary.drives,
                                        "n_scans": summary.n_scans, "utm_epsg": summary.utm_epsg}}
