"""Facades as real streets have them (issue 62): windows set into the wall, ground-floor shop fronts with glass
and recessed entrances, balconies, and hedges in front of the wall. A plain simulated wall is one flat
rectangle; a real facade breaks a lidar ring into short lines (piers between windows), lets rays through glass
into the rooms behind, puts small vertical corners at entrances and balconies, and hides its foot behind
plants. What the corner extractor makes of that is what decides how often a building corner is extracted.

Every opaque outline segment of at least ``MIN_WALL_M`` (shaped-corner facets are shorter) gets, on its own
generator draws (``core.build_city``: component ``facades``):
- **floors**: a ground floor of U(3.5, 4.5) m, then floors of U(3.0, 3.4) m up to the roof;
- **windows** (``window_share`` of the walls): on every upper floor (and on a ground floor without a shop front)
  a row of U(1.0, 1.6) x U(1.3, 1.7) m openings, sill 0.9 m above the floor, at a pitch of U(2.2, 3.5) m, at
  least U(0.35, 1.2) m (``END_PIER_M``) from the wall's ends, set U(0.12, 0.30) m into the wall (reveals), a frame
  bar across the middle of the glass; half the panes return
  (blinds, curtains, reflections: a plane at the reveal's depth), the others let the ray into the room (floor
  slabs inside the building, the far walls);
- **shop fronts** (``shopfront_share`` of the walls): the ground floor as bays of U(3, 6) m between 0.4-0.8 m
  piers (end piers U(0.4, 1.2) m), glass from 0.4 m up to U(2.2, 3.0) m set U(0.2, 0.6) m back with frame bars
  every U(0.8, 1.6) m, a fascia above; behind 60 % of the bays a display U(1, 5) m inside; 15 %
  (``ENTRANCE_SHARE``) of the bays are entrances recessed U(1.0, 2.0) m, with a door at the back (glass, the ray
  going on into the shop, for half of them);
- **balconies** (``balcony_share`` of the buildings, on all their walls with windows): on every upper floor at
  every second or third window, a U(2.5, 4.0) m wide slab U(1.0, 1.6) m deep, 0.2 m thick, with a parapet
  0.9 m high (solid on 60 % of the buildings, otherwise a railing the lidar sees through: no parapet);
- **hedges** (``facade_vegetation_share`` of the walls): bushes of leaf triangles (like the tree crowns,
  ``mesh.LEAF_DENSITY_PER_M3``) U(1.0, 2.5) m high, U(0.5, 0.9) m in radius, 0.8-1.4 m in front of the wall, every
  1.5-2.5 m over U(40, 100) % of its length.

The building's footprint and its truth corners (``truth/corners.csv``: the walls' intersections, on the wall
plane) do not move. ``facade_corners`` lists the vertical corners the detail adds that an extractor can take as
corners (walls >= 0.8 m, ``truth/facade_corners.csv``): an entrance's two front edges (90 deg) and the two inside
corners where its door meets its sides (270 deg), a balcony's two front corners (90 deg) and the two where its sides
meet the facade (270 deg); window reveals and shop-front bays are shallower than a line.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_WALL_M = 4.0  # outline segments shorter than this stay flat (rounded-corner facets, short chamfers)
END_PIER_M = (0.35, 1.2)  # range of the smallest pier between a window and the wall's end
SILL_M, LEAF_SIZE_M = 0.9, 0.09
MULLION_M = 0.08  # width of a frame bar across the glass of a shop window or a window
ENTRANCE_SHARE = 0.15  # share of shop-front bays that are recessed entrances


@dataclass(frozen=True)
class FacadeDetail:
    """The detail of one building: triangles replacing its flat walls ``replaced`` (outline segment flags), the
    heights of its inside floor slabs, and the vertical corners the detail adds."""

    tris: np.ndarray  # (M, 3, 3) ENU metres, opaque facade parts (walls with openings, reveals, panes, balconies)
    refl: np.ndarray  # (M,)
    leaves: np.ndarray  # (L, 3, 3) hedge leaves
    replaced: np.ndarray  # (n_segments,) bool: the outline segment's flat wall is replaced by ``tris``
    slab_z_m: np.ndarray  # floor slabs inside the building (rays through the windows land on them)
    corners: np.ndarray  # (C, 8) east, north, theta1_rad, theta2_rad, kind (0 entrance, 1 balcony), z0, z1,
    # interior angle (deg, in the material: 90 an edge, 270 a recess' inside corner)


CORNER_KINDS = ("entrance", "balcony")


def generate_facades(buildings: list, window_share: float, shopfront_share: float, balcony_share: float,
                     vegetation_share: float, rng: np.random.Generator) -> list[FacadeDetail | None]:
    """One ``FacadeDetail`` (or None: plain walls) per building, in the order given."""
    out: list[FacadeDetail | None] = []
    for b in buildings:
        outline, glass = b.walls()
        n = len(outline)
        balconies = rng.random() < balcony_share
        solid_parapet = rng.random() < 0.6
        ground = rng.uniform(3.5, 4.5)
        floor_h = rng.uniform(3.0, 3.4)
        slabs = np.arange(ground, b.height_m - 1.0, floor_h)
        tris, refl, leaves, corners = [], [], [], []
        replaced = np.zeros(n, bool)
        for k in range(n):
            a, e = outline[k], outline[(k + 1) % n]
            length = float(np.linalg.norm(e - a))
            windows, shop, hedge = (rng.random() < window_share, rng.random() < shopfront_share,
                                    rng.random() < vegetation_share)
            if glass[k] or length < MIN_WALL_M:
                continue
            wall = _Wall(a, e, b.height_m)
            if hedge:
                leaves.append(_hedge(wall, rng))
            if not (windows or shop):
                continue
            openings, parts = [], []
            if shop:
                openings += _shop_front(wall, ground, rng, corners)
            if windows:
                openings += _window_rows(wall, ground if shop else 0.0, ground, floor_h, rng)
                if balconies and slabs.size:
                    parts.append(_balconies(wall, slabs, solid_parapet, rng, corners))
            parts.append(wall.with_openings(openings))
            tris.append(np.concatenate(parts))
            refl.append(np.full(len(tris[-1]), b.reflectance))
            replaced[k] = True
        if not replaced.any() and not leaves:
            out.append(None)
            continue
        cat = lambda parts, shape: (np.concatenate(parts) if parts else np.zeros(shape)).astype(np.float32)  # noqa: E731
        out.append(FacadeDetail(cat(tris, (0, 3, 3)), cat(refl, (0,)), cat(leaves, (0, 3, 3)), replaced,
                                slabs if replaced.any() else np.zeros(0), np.array(corners, float).reshape(-1, 8)))
    return out


@dataclass(frozen=True)
class _Opening:
    u0: float
    u1: float
    z0: float
    z1: float
    depth_m: float  # reveal depth into the wall
    back: str  # "pane": an opaque plane at depth_m; "open": nothing (glass the lidar sees through)
    inside_m: float = 0.0  # > 0: an opaque plane this far behind the opening (a shop's display, a door)
    mullion_pitch_m: float = 0.0  # > 0: frame bars (MULLION_M wide) across the glass at about this spacing


class _Wall:
    """A wall from ``a`` to ``e`` (building outline counter-clockwise: the building on the left) of height ``h``;
    local coordinates u along the wall from ``a``, z up, depth d into the building."""

    def __init__(self, a: np.ndarray, e: np.ndarray, height_m: float):
        self.a, self.h = np.asarray(a, float), float(height_m)
        self.length = float(np.linalg.norm(e - a))
        self.t = (np.asarray(e, float) - self.a) / self.length
        self.inward = np.array([-self.t[1], self.t[0]])

    def point(self, u, z, d=0.0) -> np.ndarray:
        u, z, d = np.broadcast_arrays(np.asarray(u, float), np.asarray(z, float), np.asarray(d, float))
        en = self.a + u[..., None] * self.t + d[..., None] * self.inward
        return np.concatenate([en, z[..., None]], axis=-1)

    def quad(self, u0, u1, z0, z1, d0=0.0, d1=None) -> np.ndarray:
        """Two triangles of the rectangle u0..u1 x z0..z1 at depth d0 (d1: a horizontal/side face from d0 to d1)."""
        if d1 is None:
            p = self.point([u0, u1, u1, u0], [z0, z0, z1, z1], d0)
        elif u0 == u1:  # side face at u0, from depth d0 to d1
            p = self.point([u0, u0, u0, u0], [z0, z0, z1, z1], [d0, d1, d1, d0])
        else:  # horizontal face at z0, from depth d0 to d1
            p = self.point([u0, u1, u1, u0], [z0, z0, z0, z0], [d0, d0, d1, d1])
        return np.stack([p[[0, 1, 2]], p[[0, 2, 3]]])

    def with_openings(self, openings: list[_Opening]) -> np.ndarray:
        """The wall as opaque rectangles around the openings (row bands between the openings' heights), each
        opening's four reveals, its pane and what stands inside."""
        zs = np.unique(np.clip([0.0, self.h] + [z for o in openings for z in (o.z0, o.z1)], 0.0, self.h))
        out = []
        for z0, z1 in zip(zs[:-1], zs[1:]):
            cuts = sorted((o.u0, o.u1) for o in openings if o.z0 < z1 and o.z1 > z0)
            u = 0.0
            for c0, c1 in cuts + [(self.length, self.length)]:
                if c0 > u:
                    out.append(self.quad(u, c0, z0, z1))
                u = max(u, c1)
        for o in openings:
            d = o.depth_m
            out += [self.quad(o.u0, o.u0, o.z0, o.z1, 0.0, d), self.quad(o.u1, o.u1, o.z0, o.z1, 0.0, d),
                    self.quad(o.u0, o.u1, o.z0, o.z0, 0.0, d), self.quad(o.u0, o.u1, o.z1, o.z1, 0.0, d)]
            if o.back == "pane":
                out.append(self.quad(o.u0, o.u1, o.z0, o.z1, o.depth_m))
            if o.inside_m > 0:
                out.append(self.quad(o.u0, o.u1, 0.0, o.z1, o.depth_m + o.inside_m))
            if o.mullion_pitch_m > 0 and o.back == "open":  # the glass' frame bars
                n = int((o.u1 - o.u0) / o.mullion_pitch_m)
                for u in o.u0 + (o.u1 - o.u0) * np.arange(1, n + 1) / (n + 1):
                    out.append(self.quad(u - MULLION_M / 2, u + MULLION_M / 2, o.z0, o.z1, o.depth_m))
        return np.concatenate(out).reshape(-1, 3, 3) if out else np.zeros((0, 3, 3))


def _bays(length: float, lo: float, hi: float, pier: tuple[float, float], end_pier: tuple[float, float],
          rng: np.random.Generator) -> list[tuple[float, float]]:
    """Openings (u0, u1) of U(lo, hi) width separated by piers of U(pier), end piers of U(end_pier)."""
    out, u = [], rng.uniform(*end_pier)
    end = length - rng.uniform(*end_pier)
    while True:
        w = rng.uniform(lo, hi)
        if u + w > end:
            break
        out.append((u, u + w))
        u += w + rng.uniform(*pier)
    if out:  # centre the row: spread the slack left at the end over both ends
        shift = 0.5 * (end - out[-1][1])
        out = [(a + shift, b + shift) for a, b in out]
    return out


def _shop_front(wall: _Wall, ground_m: float, rng: np.random.Generator, corners: list) -> list[_Opening]:
    top = rng.uniform(2.2, 3.0)
    out = []
    for u0, u1 in _bays(wall.length, 3.0, 6.0, (0.4, 0.8), (0.4, 1.2), rng):
        if rng.random() < ENTRANCE_SHARE:  # a recessed entrance: a door at its back
            depth = rng.uniform(1.0, 2.0)
            z1 = min(top, ground_m - 0.3)
            glass_door = rng.random() < 0.5  # a glass door: the ray goes on into the shop
            out.append(_Opening(u0, u1, 0.0, z1, depth, "open" if glass_door else "pane",
                                mullion_pitch_m=rng.uniform(0.8, 1.6) if glass_door else 0.0))
            for u, side in ((u0, 1.0), (u1, -1.0)):  # side: +1 the recess lies at larger u
                along = -side * wall.t  # from the front edge along the facade, away from the recess
                _corner(corners, wall.point(u, 0.0)[:2], along, wall.inward, 90.0, 0, 0.0, z1)
                # back: the door plane (towards the recess' middle) meets the side wall (out to the street)
                _corner(corners, wall.point(u, 0.0, depth)[:2], -along, -wall.inward, 270.0, 0, 0.0, z1)
        else:
            inside = rng.uniform(1.0, 5.0) if rng.random() < 0.6 else 0.0
            out.append(_Opening(u0, u1, 0.4, top, rng.uniform(0.2, 0.6), "open", inside, rng.uniform(0.8, 1.6)))
    return out


def _window_rows(wall: _Wall, z_first_m: float, ground_m: float, floor_m: float, rng: np.random.Generator
                 ) -> list[_Opening]:
    width, height, pitch = rng.uniform(1.0, 1.6), rng.uniform(1.3, 1.7), rng.uniform(2.2, 3.5)
    depth, end_pier = rng.uniform(0.12, 0.30), rng.uniform(*END_PIER_M)
    n = int((wall.length - 2 * end_pier - width) // pitch) + 1 if wall.length > 2 * end_pier + width else 0
    if n <= 0:
        return []
    u_start = 0.5 * (wall.length - (n - 1) * pitch - width)
    floors = [0.0] if z_first_m == 0.0 else []
    floors += list(np.arange(ground_m, wall.h - SILL_M - height - 0.3, floor_m))
    out = []
    for z in floors:
        for i in range(n):
            u0 = u_start + i * pitch
            out.append(_Opening(u0, u0 + width, z + SILL_M, z + SILL_M + height, depth,
                                "pane" if rng.random() < 0.5 else "open", mullion_pitch_m=0.6 * width))
    return out


def _balconies(wall: _Wall, slabs: np.ndarray, solid_parapet: bool, rng: np.random.Generator, corners: list
               ) -> np.ndarray:
    from stages.simulate.mesh import box_triangles

    width, depth = rng.uniform(2.5, 4.0), rng.uniform(1.0, 1.6)
    every = int(rng.integers(2, 4))
    pitch = width * every / 2 + rng.uniform(1.0, 3.0)
    u_c = np.arange(rng.uniform(0.3, 2.0) + width / 2, wall.length - width / 2 - 0.3, pitch)
    if not len(u_c):
        return np.zeros((0, 3, 3))
    yaw = np.arctan2(wall.t[1], wall.t[0])
    boxes = []
    for z in slabs:
        for u in u_c:
            c = wall.point(u, 0.0, -depth / 2)[:2]
            boxes.append([c[0], c[1], yaw, width, depth, z, 0.2])
            if solid_parapet:
                boxes.append([c[0], c[1], yaw, width, depth, z + 0.2, 0.9])
    z0, z1 = float(slabs[0]), float(slabs[-1] + (1.1 if solid_parapet else 0.2))
    for u in u_c:
        for side in (-1.0, 1.0):
            along = -side * wall.t  # from the balcony's end back along it
            # front corner: along the balcony's front and back to the facade
            _corner(corners, wall.point(u + side * width / 2, 0.0, -depth)[:2], along, wall.inward, 90.0, 1, z0, z1)
            # where its side meets the facade: along the facade away from it and out along the side
            _corner(corners, wall.point(u + side * width / 2, 0.0)[:2], -along, -wall.inward, 270.0, 1, z0, z1)
    return box_triangles(np.array(boxes, float))


def _corner(rows: list, en: np.ndarray, dir1: np.ndarray, dir2: np.ndarray, interior_deg: float, kind: int,
            z0: float, z1: float) -> None:
    """A facade-detail corner: position, the directions of its two faces away from it, the angle inside the
    material between them (90 convex, 270 a recess' inside corner), kind and height range."""
    rows.append([en[0], en[1], np.arctan2(dir1[1], dir1[0]), np.arctan2(dir2[1], dir2[0]), kind, z0, z1,
                 interior_deg])


def _hedge(wall: _Wall, rng: np.random.Generator) -> np.ndarray:
    share = rng.uniform(0.4, 1.0)
    start = rng.uniform(0.0, wall.length * (1.0 - share))
    centres = np.arange(start + 0.8, start + share * wall.length - 0.8, rng.uniform(1.5, 2.5))
    parts = []
    for u in centres:
        r, h = rng.uniform(0.5, 0.9), rng.uniform(1.0, 2.5)
        c = wall.point(u, h / 2 + 0.15, -rng.uniform(0.8, 1.4))
        n = max(int(4.0 / 3.0 * np.pi * r * r * (h / 2) * 40.0), 1)
        d = rng.normal(size=(n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        rad = rng.random(n) ** (1.0 / 3.0)
        centre = c + d * rad[:, None] * np.array([r, r, h / 2])
        parts.append(centre[:, None, :] + rng.normal(scale=LEAF_SIZE_M, size=(n, 3, 3)))
    return np.concatenate(parts) if parts else np.zeros((0, 3, 3))


def facade_corner_rows(details: list[FacadeDetail | None]) -> dict[str, np.ndarray]:
    """``truth/facade_corners.csv`` columns over every building's detail."""
    rows = np.concatenate([d.corners for d in details if d is not None] or [np.zeros((0, 8))])
    th = np.degrees(rows[:, 2:4])
    th = (th + 180.0) % 360.0 - 180.0
    return {"id": np.arange(len(rows)), "kind": np.array([CORNER_KINDS[int(k)] for k in rows[:, 4]], dtype=object),
            "east_m": rows[:, 0], "north_m": rows[:, 1], "theta1_deg": th[:, 0], "theta2_deg": th[:, 1],
            "interior_angle_deg": rows[:, 7], "z_min_m": rows[:, 5], "z_max_m": rows[:, 6]}
