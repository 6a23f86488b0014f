"""Engine adapter: write the whole simulation into the stage's ``drives`` artifact directory."""
from __future__ import annotations

from pipeline.declare import StageContext


def compute(ctx: StageContext) -> dict:
    from stages.simulate.core import simulate
    from stages.simulate.presets import get_preset

    p = ctx.params
    summary = simulate(get_preset(p.preset, **p.preset_overrides), p.seed, ctx.artifact_dir("drives"),
                       n_drives=p.drives, motion_distortion=p.motion_distortion, changes=p.changes,
                       changes_from_drive=p.changes_from_drive)
    return {"drives": None, "_extra": {"enu_origin": summary.enu_origin, "drives": summary.drives,
                                        "n_scans": summary.n_scans, "utm_epsg": summary.utm_epsg}}
