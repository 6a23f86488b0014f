"""City records -> triangle soups with a material class and a reflectance per triangle, and open3d
``RaycastingScene`` wrappers. Glass walls are left out of the mesh: rays pass into the building and hit the
opposite walls, floor slabs or the ground inside.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.simulate.city import CURB_H_M, City
from stages.simulate.geom2d import triangulate_polygon

GROUND, SIDEWALK, CURB, WALL, SLAB, LEAF, TRUNK, POLE, PARKED, VEHICLE, EGO, FURNITURE = range(12)
CLASS_NAMES = ["ground", "sidewalk", "curb", "wall", "slab", "leaf", "trunk", "pole", "parked_car", "vehicle", "ego",
               "furniture"]
LEAF_DENSITY_PER_M3 = 40.0
LEAF_SIZE_M = 0.09


@dataclass
class TriangleSoup:
    tris: np.ndarray  # (M, 3, 3) float32, ENU metres
    cls: np.ndarray  # (M,) uint8 material class
    refl: np.ndarray  # (M,) float32 Lambertian reflectance 0..1

    @staticmethod
    def concat(parts: list["TriangleSoup"]) -> "TriangleSoup":
        parts = [p for p in parts if len(p.tris)]
        if not parts:
            return TriangleSoup(np.zeros((0, 3, 3), np.float32), np.zeros(0, np.uint8), np.zeros(0, np.float32))
        return TriangleSoup(np.concatenate([p.tris for p in parts]).astype(np.float32),
                            np.concatenate([p.cls for p in parts]).astype(np.uint8),
                            np.concatenate([p.refl for p in parts]).astype(np.float32))

    def normals(self) -> np.ndarray:
        n = np.cross(self.tris[:, 1] - self.tris[:, 0], self.tris[:, 2] - self.tris[:, 0])
        return (n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)).astype(np.float32)


def _soup(tris: np.ndarray, cls: int, refl) -> TriangleSoup:
    tris = np.asarray(tris, np.float32).reshape(-1, 3, 3)
    return TriangleSoup(tris, np.full(len(tris), cls, np.uint8),
                        np.broadcast_to(np.asarray(refl, np.float32), (len(tris),)).copy())


def vertical_quads(p0_en: np.ndarray, p1_en: np.ndarray, z0: np.ndarray, z1: np.ndarray) -> np.ndarray:
    """(K,2) segment ends and (K,) heights -> (2K, 3, 3) triangles of the vertical rectangles."""
    z0 = np.broadcast_to(z0, (len(p0_en),))
    z1 = np.broadcast_to(z1, (len(p0_en),))
    a = np.column_stack([p0_en, z0])
    b = np.column_stack([p1_en, z0])
    c = np.column_stack([p1_en, z1])
    d = np.column_stack([p0_en, z1])
    return np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def box_triangles(boxes: np.ndarray) -> np.ndarray:
    """(K, 7) east, north, yaw_rad, length, width, z0, height -> (12K, 3, 3) triangles."""
    k = len(boxes)
    if k == 0:
        return np.zeros((0, 3, 3), np.float32)
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float) * 0.5
    c, s = np.cos(boxes[:, 2]), np.sin(boxes[:, 2])
    local = corners[None] * boxes[:, None, 3:5]  # (K, 4, 2)
    xy = np.stack([c[:, None] * local[..., 0] - s[:, None] * local[..., 1],
                   s[:, None] * local[..., 0] + c[:, None] * local[..., 1]], -1) + boxes[:, None, :2]
    z0, z1 = boxes[:, 5], boxes[:, 5] + boxes[:, 6]
    walls = [vertical_quads(xy[:, q], xy[:, (q + 1) % 4], z0, z1).reshape(2, k, 3, 3) for q in range(4)]
    top = np.concatenate([xy, np.repeat(z1[:, None, None], 4, 1)], -1)
    bot = np.concatenate([xy, np.repeat(z0[:, None, None], 4, 1)], -1)
    caps = [top[:, [0, 1, 2]], top[:, [0, 2, 3]], bot[:, [0, 2, 1]], bot[:, [0, 3, 2]]]
    per_box = np.concatenate([w.transpose(1, 0, 2, 3) for w in walls] + [c_[:, None] for c_ in caps], axis=1)
    return per_box.reshape(-1, 3, 3)


def _polygon_at(poly_en: np.ndarray, z: float) -> np.ndarray:
    tri_idx = triangulate_polygon(poly_en)
    p3 = np.column_stack([poly_en, np.full(len(poly_en), z)])
    return p3[tri_idx]


def build_static_soup(city: City, rng: np.random.Generator) -> TriangleSoup:
    w, s, e, n = city.bounds_en
    ground = np.array([[[w, s, 0], [e, s, 0], [e, n, 0]], [[w, s, 0], [e, n, 0], [w, n, 0]]])
    parts = [_soup(ground, GROUND, 0.10)]
    for curb in city.curbs_en:
        parts.append(_soup(_polygon_at(curb, CURB_H_M), SIDEWALK, 0.28))
        parts.append(_soup(vertical_quads(curb, np.roll(curb, -1, 0), 0.0, CURB_H_M), CURB, 0.35))
    for b in city.buildings:
        fp, glass = b.walls()
        detail = b.facade
        solid = ~glass if detail is None else ~glass & ~detail.replaced
        if solid.any():
            parts.append(_soup(vertical_quads(fp[solid], np.roll(fp, -1, 0)[solid], 0.0, b.height_m), WALL,
                               b.reflectance))
        parts.append(_soup(_polygon_at(fp, b.height_m), SLAB, 0.3))
        if glass.any():  # interior floor slabs seen through the glass
            for z in np.arange(4.0, b.height_m - 1.0, max(4.0, b.height_m / 12)):
                parts.append(_soup(_polygon_at(fp, float(z)), SLAB, 0.3))
        if detail is not None:  # windows, shop fronts, balconies (facades.py); floors seen through the windows
            parts.append(TriangleSoup(detail.tris, np.full(len(detail.tris), WALL, np.uint8), detail.refl))
            if not glass.any():
                for z in detail.slab_z_m:
                    parts.append(_soup(_polygon_at(fp, float(z)), SLAB, 0.3))
            if len(detail.leaves):
                parts.append(_soup(detail.leaves, LEAF, 0.4))  # leaves reflect well in the near infrared
    parts += _tree_soups(city.trees, rng)
    if len(city.poles):
        poles = np.column_stack([city.poles, np.zeros(len(city.poles)), np.full((len(city.poles), 2), 0.22),
                                 np.full(len(city.poles), CURB_H_M), np.full(len(city.poles), 8.0)])
        parts.append(_soup(box_triangles(poles), POLE, 0.45))
    if len(city.parked):
        pk = city.parked
        top = np.full(len(pk), 1.5) if city.parked_top_m is None else city.parked_top_m
        body = np.column_stack([pk[:, :5], np.full(len(pk), 0.3), top - 0.3])
        refl = np.repeat(rng.uniform(0.1, 0.7, len(pk)), 12)
        parts.append(_soup(box_triangles(body), PARKED, refl))
    for item in city.furniture:
        parts.append(_soup(box_triangles(item.boxes), FURNITURE, item.reflectance))
    return TriangleSoup.concat(parts)


def _tree_soups(trees: np.ndarray, rng: np.random.Generator) -> list[TriangleSoup]:
    if len(trees) == 0:
        return []
    trunks = np.column_stack([trees[:, :2], np.zeros(len(trees)), np.full((len(trees), 2), 0.3),
                              np.full(len(trees), CURB_H_M), trees[:, 2] + 0.5])
    vol = 4.0 / 3.0 * np.pi * trees[:, 3] ** 2 * trees[:, 4]
    n_leaves = np.maximum((vol * LEAF_DENSITY_PER_M3).astype(np.int64), 1)
    owner = np.repeat(np.arange(len(trees)), n_leaves)
    m = len(owner)
    direction = rng.normal(size=(m, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    radius = rng.random(m) ** (1.0 / 3.0)
    t = trees[owner]
    centre = np.column_stack([t[:, 0] + direction[:, 0] * radius * t[:, 3],
                              t[:, 1] + direction[:, 1] * radius * t[:, 3],
                              t[:, 2] + t[:, 4] + direction[:, 2] * radius * t[:, 4]])
    leaves = centre[:, None, :] + rng.normal(scale=LEAF_SIZE_M, size=(m, 3, 3))
    return [_soup(box_triangles(trunks), TRUNK, 0.3), _soup(leaves, LEAF, rng.uniform(0.25, 0.45, m))]


class Scene:
    """A RaycastingScene over one triangle soup; ``cast`` returns hit distance and triangle id (-1: no hit)."""

    def __init__(self, soup: TriangleSoup):
        import open3d as o3d

        self.soup = soup
        self.normals = soup.normals()
        self._scene = o3d.t.geometry.RaycastingScene()
        if len(soup.tris):
            mesh = o3d.t.geometry.TriangleMesh()
            mesh.vertex.positions = o3d.core.Tensor(soup.tris.reshape(-1, 3))
            mesh.triangle.indices = o3d.core.Tensor(np.arange(3 * len(soup.tris), dtype=np.int32).reshape(-1, 3))
            self._scene.add_triangles(mesh)

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        import open3d as o3d

        if len(self.soup.tris) == 0:
            return np.full(len(origins), np.inf, np.float32), np.full(len(origins), -1, np.int64)
        rays = np.ascontiguousarray(np.concatenate([origins, dirs], axis=1), dtype=np.float32)
        ans = self._scene.cast_rays(o3d.core.Tensor(rays))
        t_hit = ans["t_hit"].numpy()
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        prim[~np.isfinite(t_hit)] = -1
        return t_hit, prim


def build_building_soup(city: City) -> TriangleSoup:
    """Buildings as closed solids (glass walls included): what blocks satellite signals."""
    parts = []
    for b in city.buildings:
        fp = b.walls()[0]
        parts.append(_soup(vertical_quads(fp, np.roll(fp, -1, 0), 0.0, b.height_m), WALL, b.reflectance))
        parts.append(_soup(_polygon_at(fp, b.height_m), SLAB, 0.3))
    return TriangleSoup.concat(parts)
