"""Corner truth as a sensor sees it, for a simulator output folder: walls of the union of the footprints
and per-drive "seen as a corner" counts, recomputed from its preset and seed.

``truth/corners.csv`` lists every footprint vertex with its own walls and counts a line of sight to the
corner point (``scans_visible_*``). Where buildings touch, the union's walls differ (``truth.union_corner_walls``),
and a scan looking along one wall has a line of sight without seeing a corner. A map's recall is judged
against the corners a scan could extract (two opaque walls in view, ``truth.count_corner_views``). The city
and its static scene are deterministic in (preset, seed), so they are rebuilt here rather than stored; the
rebuilt footprints are checked against ``truth/city.json``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import ConfigError
from stages.common.records import Trajectory
from stages.simulate.core import build_city, component_rng
from stages.simulate.mesh import Scene, build_static_soup
from stages.simulate.presets import get_preset
from stages.simulate.sensor import MOUNT_HEIGHT_M
from stages.simulate.truth import building_corners, count_corner_views, union_corner_walls


@dataclass
class SensedCornerTruth:
    theta_rad: np.ndarray  # (K,2) the union's wall directions, ``truth/corners.csv`` row order
    not_corner: np.ndarray  # (K,) inside the union, or a straight/stepped facade there
    views: np.ndarray  # (K,) scans of the drive that see it as a corner (0 where not_corner)


def sensed_corner_truth(sim_dir: Path, drive: str, **kwargs) -> SensedCornerTruth:
    """Union walls and view counts of each truth corner for ``drive`` (kwargs: ``count_corner_views``)."""
    sim_dir = Path(sim_dir)
    meta = json.loads((sim_dir / "simulation.json").read_text())
    overrides = {k: tuple(v) if isinstance(v, list) else v for k, v in meta.get("preset_overrides", {}).items()}
    city = build_city(get_preset(meta["preset"], **overrides), int(meta["seed"]))
    stored = json.loads((sim_dir / "truth" / "city.json").read_text())["buildings"]
    rebuilt = [np.round(b.footprint_en, 3) for b in city.buildings]
    if len(rebuilt) != len(stored) or not all(np.allclose(a, np.asarray(b["footprint_en"]), atol=2e-3)
                                              for a, b in zip(rebuilt, stored)):
        raise ConfigError(str(sim_dir / "truth" / "city.json"), [
            f"the city rebuilt from preset {meta['preset']!r}, seed {meta['seed']} differs from the stored one "
            "(simulated by another simulator version); cannot recount corner views"])
    static = Scene(build_static_soup(city, component_rng(int(meta["seed"]), "mesh")))
    T = Trajectory.from_tum(sim_dir / "truth" / f"{drive}_poses_tum.txt").T
    corners = building_corners(city)
    own = np.radians(np.column_stack([corners["theta1_deg"], corners["theta2_deg"]]))
    en = np.column_stack([corners["east_m"], corners["north_m"]])
    owner = np.repeat(np.arange(len(city.buildings)), [len(b.footprint_en) for b in city.buildings])
    theta, inward, not_corner = union_corner_walls([b.footprint_en for b in city.buildings], en, own,
                                                   glass=[b.glass for b in city.buildings], owner=owner)
    sensed = {**corners, "theta1_deg": np.degrees(theta[:, 0]), "theta2_deg": np.degrees(theta[:, 1]),
              "inward_en": np.where(np.any(inward != 0, axis=1)[:, None], inward, corners["inward_en"])}
    views = count_corner_views(sensed, static, T[:, :2, 3], MOUNT_HEIGHT_M, **kwargs)
    return SensedCornerTruth(theta, not_corner, np.where(not_corner, 0, views))
