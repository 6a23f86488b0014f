"""Every odometry param reaches the algorithm's config (a param that changes nothing is a lie), and flat settings
are checked by name."""
from __future__ import annotations

import pytest

from stages.odometry.config import EdgeConfig
from stages.odometry.params import OdometryParams

CHANGED = {"method": "point_to_plane", "deskew": "none", "ground_split": False, "span_scans": [5],
           "knn": 7, "max_iterations": 3, "min_fitness": 0.5, "keyframe_stages": [(2.0, 3.0)]}
NOT_IN_CONFIG = set()  # fields the stage's compute uses but the algorithm does not (none today)


@pytest.mark.parametrize("name", sorted(OdometryParams.model_fields))
def test_every_param_changes_the_edge_config(name):
    base = OdometryParams()
    value = CHANGED.get(name, getattr(base, name) * 1.5 if isinstance(getattr(base, name), float) else None)
    if name in NOT_IN_CONFIG:
        pytest.skip("not an algorithm setting")
    assert value is not None, f"add a changed value for {name!r} to CHANGED"
    changed = OdometryParams(**{name: value})
    assert changed.edge_config() != base.edge_config(), f"{name} does not reach estimate_edges"


def test_flat_settings_are_named_and_complete():
    kw = dict(method="gicp", voxel_m=0.5, knn=20, max_corr_m=0.7, max_iterations=30, relative_tolerance=1e-6,
              min_range_m=2.0, max_range_m=80.0, min_fitness=0.3, max_deviation_m=0.3, max_deviation_rad=0.0175,
              point_sigma_m=0.15, min_sigma_m=0.01, min_sigma_rad=0.0003)
    cfg = EdgeConfig.flat(deskew=True, span_scans=[3], **kw)
    assert cfg.prepare.voxel_m == 0.5 and cfg.icp.max_corr_m == 0.7 and cfg.gate.min_fitness == 0.3
    assert cfg.span_scans == (3,) and cfg.registration_kwargs()["point_sigma_m"] == 0.15
    with pytest.raises(TypeError, match="unknown settings.*voxel_size"):
        EdgeConfig.flat(deskew=True, voxel_size=1.0, **kw)
    with pytest.raises(TypeError):
        EdgeConfig.flat(deskew=True, **{k: v for k, v in kw.items() if k != "knn"})
