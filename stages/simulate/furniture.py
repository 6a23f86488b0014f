"""Small street furniture with corner-like shapes, on the sidewalks: bus shelters (a back panel, two side
panels and a roof, open to the street), kiosks (solid boxes) and L-shaped fences. They stand on the sidewalk
(z = kerb height) between the kerb and the building line, clear of tree trunks and poles.

Their vertical corners are *not* building corners: ``furniture_corners`` lists them for
``truth/furniture_corners.csv`` (a shelter's two back corners, a kiosk's four: interior angle 90 deg; an L-fence's
bend on the street side:
270 deg, the faces' directions point along the panels away from the bend).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.simulate.city import CURB_H_M

KINDS = ("shelter", "kiosk", "fence")
KIND_P = (0.35, 0.35, 0.30)
PANEL_M = 0.08  # panel / fence thickness
CLEARANCE_M = 0.6  # from trunks and poles


@dataclass(frozen=True)
class Furniture:
    kind: str
    boxes: np.ndarray  # (K, 7) east, north, yaw_enu_rad, length, width, z0, height
    corners_en: np.ndarray  # (C, 2)
    corner_theta_rad: np.ndarray  # (C, 2) directions of the two faces away from each corner
    interior_deg: float  # angle inside the material between the faces: 90 (box corners) or 270 (fence bend)
    height_m: float
    reflectance: float


def generate_furniture(curbs_en: list[np.ndarray], sidewalk_m: float, per_km: float, trees: np.ndarray,
                       poles: np.ndarray, rng: np.random.Generator) -> list[Furniture]:
    """Furniture along every kerb side (ccw kerb polygons, inward = into the block), Poisson ``per_km``."""
    posts = np.concatenate([trees[:, :2], poles]) if len(trees) else poles.reshape(-1, 2)
    out = []
    for curb in curbs_en:
        for k in range(len(curb)):
            a, b = curb[k], curb[(k + 1) % len(curb)]
            length = float(np.linalg.norm(b - a))
            if length < 12.0:
                continue
            t = (b - a) / length
            inward = np.array([-t[1], t[0]])
            for s in np.sort(rng.uniform(5.0, length - 5.0, rng.poisson(per_km * length / 1000.0))):
                kind = str(rng.choice(KINDS, p=KIND_P))
                item = _make(kind, a + t * s, t, inward, sidewalk_m, rng)
                if item is not None and _clear(item, posts) and all(_apart(item, o) for o in out):
                    out.append(item)
    return out


def _make(kind: str, base: np.ndarray, t: np.ndarray, inward: np.ndarray, sidewalk_m: float,
          rng: np.random.Generator) -> Furniture | None:
    """One item at ``base`` (a kerb point); its local frame: u along the kerb, v into the block."""
    room = sidewalk_m - 0.4  # keep off the building line
    if kind == "shelter":
        w, depth, h = rng.uniform(3.0, 4.5), rng.uniform(1.2, 1.6), rng.uniform(2.4, 2.8)
        v_back = min(room, 0.6 + depth)
        if v_back - depth < 0.4:
            return None
        rects = [(-w / 2, w / 2, v_back - PANEL_M, v_back, 0.0, h),  # back panel
                 (-w / 2, -w / 2 + PANEL_M, v_back - depth, v_back, 0.0, h),  # side panels
                 (w / 2 - PANEL_M, w / 2, v_back - depth, v_back, 0.0, h),
                 (-w / 2, w / 2, v_back - depth, v_back, h, 0.1)]  # roof
        corners = [((-w / 2, v_back), (1, 0), (0, -1)), ((w / 2, v_back), (-1, 0), (0, -1))]
    elif kind == "kiosk":
        w, depth, h = rng.uniform(1.8, 2.6), rng.uniform(1.6, 2.2), rng.uniform(2.4, 3.0)
        v0 = rng.uniform(0.5, max(0.5, room - depth))
        if v0 + depth > room + 1e-9:
            return None
        rects = [(-w / 2, w / 2, v0, v0 + depth, 0.0, h)]
        corners = [((-w / 2, v0), (1, 0), (0, 1)), ((w / 2, v0), (-1, 0), (0, 1)),
                   ((w / 2, v0 + depth), (-1, 0), (0, -1)), ((-w / 2, v0 + depth), (1, 0), (0, -1))]
    else:  # an L-shaped fence: a run along the building line and a leg towards the kerb
        run, leg, h = rng.uniform(4.0, 10.0), rng.uniform(1.2, 2.0), rng.uniform(1.2, 2.0)
        v_line = room
        if v_line - leg < 0.3:
            leg = v_line - 0.3
        side = 1.0 if rng.random() < 0.5 else -1.0  # the leg at the run's left or right end
        u_end = side * run / 2
        rects = [(-run / 2, run / 2, v_line - PANEL_M, v_line, 0.0, h),
                 (u_end - PANEL_M / 2, u_end + PANEL_M / 2, v_line - leg, v_line, 0.0, h)]
        corners = [((u_end - side * PANEL_M / 2, v_line - PANEL_M), (-side, 0), (0, -1))]  # the street side's bend
    boxes = []
    for u0, u1, v0_, v1_, z0, hh in rects:
        centre = base + t * (u0 + u1) / 2 + inward * (v0_ + v1_) / 2
        boxes.append([centre[0], centre[1], np.arctan2(t[1], t[0]), u1 - u0, v1_ - v0_, CURB_H_M + z0, hh])
    en = np.array([base + t * c[0][0] + inward * c[0][1] for c in corners])
    theta = np.array([[np.arctan2(*(t * d[0] + inward * d[1])[::-1]) for d in c[1:]] for c in corners])
    return Furniture(kind, np.array(boxes, float), en, theta, 270.0 if kind == "fence" else 90.0, float(h),
                     float(rng.uniform(0.2, 0.6)))


def _footprint_points(item: Furniture) -> np.ndarray:
    b = item.boxes
    c, s = np.cos(b[:, 2]), np.sin(b[:, 2])
    pts = [b[:, :2] + np.column_stack([c * du * b[:, 3] / 2 - s * dv * b[:, 4] / 2,
                                       s * du * b[:, 3] / 2 + c * dv * b[:, 4] / 2])
           for du in (-1, 0, 1) for dv in (-1, 0, 1)]
    return np.concatenate(pts)


def _clear(item: Furniture, posts: np.ndarray) -> bool:
    if not len(posts):
        return True
    pts = _footprint_points(item)
    return float(np.linalg.norm(pts[:, None] - posts[None], axis=-1).min()) > CLEARANCE_M + 0.3


def _apart(a: Furniture, b: Furniture) -> bool:
    return float(np.linalg.norm(_footprint_points(a)[:, None] - _footprint_points(b)[None], axis=-1).min()) > 2.0


def furniture_corners(items: list[Furniture]) -> dict[str, np.ndarray]:
    """Vertical corners of the furniture: kind, east/north, the faces' directions (deg) and the height."""
    rows = [(it.kind, *p, *np.degrees(th), it.height_m, it.interior_deg) for it in items for p, th in
            zip(it.corners_en, it.corner_theta_rad)]
    deg = lambda a: (np.asarray(a, float) + 180.0) % 360.0 - 180.0  # noqa: E731
    return {"id": np.arange(len(rows)), "kind": np.array([r[0] for r in rows], dtype=object),
            "east_m": np.array([r[1] for r in rows], float), "north_m": np.array([r[2] for r in rows], float),
            "theta1_deg": deg([r[3] for r in rows]), "theta2_deg": deg([r[4] for r in rows]),
            "height_m": np.array([r[5] for r in rows], float),
            "interior_angle_deg": np.array([r[6] for r in rows], float)}
