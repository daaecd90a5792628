"""A body surface posed at one frame: a triangle mesh, and exact samples of it with outward normals.

The renderer ray-casts the posed mesh; the tracker and reconstruction engineers sample the very same
surface (``sample_body_surface``) or measure distances to it (``posed_mesh``), so "perfect data" means
points on what the cameras saw.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Clothing materials a vertex can wear; the renderer picks one colour per material and capture.
MATERIALS: tuple[str, ...] = ("skin", "shirt", "trousers", "shoes", "hair")


@dataclass(frozen=True, eq=False)
class RoundCones:
    """Tapered capsules (convex hulls of two spheres), for telling which surface points are inside others.

    Parameters
    ----------
    starts, ends : (K, 3) float, metres
        Centres of the two spheres of each capsule.
    start_radii, end_radii : (K,) float, metres
    """

    starts: np.ndarray
    ends: np.ndarray
    start_radii: np.ndarray
    end_radii: np.ndarray

    def contains(self, points: np.ndarray, *, exclude: np.ndarray, margin: float) -> np.ndarray:
        """(N,) bool: points (N, 3) deeper than ``margin`` inside a capsule other than ``exclude`` (N,)."""
        inside = np.zeros(len(points), dtype=bool)
        for k in range(len(self.starts)):
            candidates = exclude != k
            inside[candidates] |= _round_cone_depth(points[candidates], self, k) > margin
        return inside


def _round_cone_depth(points: np.ndarray, cones: RoundCones, k: int) -> np.ndarray:
    """(N,) How far inside capsule ``k`` each point lies (negative outside), metres.

    In the plane of the axis, with ``a`` along the axis from the start and ``rho`` away from it, the
    capsule is the convex hull of the circles (0, r0) and (L, r1); its straight flank has unit outward
    normal ``(sin alpha, cos alpha)``, ``sin alpha = (r0 - r1) / L``, and runs from the tangent point
    ``r0 n`` to ``(L, 0) + r1 n``.
    """
    p0, p1 = cones.starts[k], cones.ends[k]
    r0, r1 = cones.start_radii[k], cones.end_radii[k]
    axis = p1 - p0
    length = np.linalg.norm(axis)
    d0 = r0 - np.linalg.norm(points - p0, axis=1)
    d1 = r1 - np.linalg.norm(points - p1, axis=1)
    if length <= abs(r0 - r1):  # one sphere holds the other
        return np.maximum(d0, d1)
    u = axis / length
    a = (points - p0) @ u
    rho = np.linalg.norm(points - p0 - a[:, None] * u, axis=1)
    sin_alpha = (r0 - r1) / length
    cos_alpha = np.sqrt(1.0 - sin_alpha**2)
    along_flank = a * cos_alpha - rho * sin_alpha
    flank_depth = r0 - (a * sin_alpha + rho * cos_alpha)
    on_flank = (along_flank >= 0) & (along_flank <= length * cos_alpha)
    return np.maximum(np.maximum(d0, d1), np.where(on_flank, flank_depth, -np.inf))


@dataclass(frozen=True, eq=False)
class PosedBody:
    """The body surface at one frame, world metres (+z up).

    Parameters
    ----------
    vertices : (V, 3) float
    triangles : (T, 3) int32
        Counter-clockwise seen from outside, so face normals point outwards.
    vertex_normals : (V, 3) float
        Unit outward normals for smooth shading.
    vertex_materials : (V,) int
        Index into ``MATERIALS``.
    parts : RoundCones or None
        For a body made of overlapping closed parts (capsules): the parts, so that surface samples
        inside another part (not on the body's outer surface) can be dropped. None for one surface.
    triangle_parts : (T,) int or None
        The part each triangle belongs to (with ``parts``).
    """

    vertices: np.ndarray
    triangles: np.ndarray
    vertex_normals: np.ndarray
    vertex_materials: np.ndarray
    parts: RoundCones | None = None
    triangle_parts: np.ndarray | None = None


def posed_mesh(posed: PosedBody) -> tuple[np.ndarray, np.ndarray]:
    """The posed surface as ``(vertices (V, 3) float64 metres, triangles (T, 3) int32)``.

    For the capsule body the mesh is the union of closed capsule meshes that overlap at the joints;
    ray casting and unsigned distances (open3d ``RaycastingScene.compute_distance``) are exact on it.
    """
    return posed.vertices, posed.triangles


# A sample lying this deep inside another capsule is not on the outer surface. The tessellated capsule
# lies inside the analytic one by up to r (1 - cos(pi / 24)) ~ 0.5 mm, so points within that of another
# capsule's analytic surface are kept (they are on the rendered surface).
INTERIOR_MARGIN_M = 1e-3


def sample_body_surface(posed: PosedBody, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points uniformly distributed (by area) on the body's outer surface, with outward normals.

    Points lie exactly on the posed triangles; normals are the triangles' unit normals. For a body of
    overlapping parts, points inside another part are rejected and more are drawn.

    Returns
    -------
    points : (n, 3) float, metres
    normals : (n, 3) float, unit, outward
    """
    if n < 0:
        raise ValueError(f"n: expected a non-negative number of samples, got {n}")
    corners = posed.vertices[posed.triangles]  # (T, 3, 3)
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])  # (T, 3)
    double_areas = np.linalg.norm(cross, axis=1)
    keep = double_areas > 0
    corners, cross, double_areas = corners[keep], cross[keep], double_areas[keep]
    face_normals = cross / double_areas[:, None]
    face_parts = posed.triangle_parts[keep] if posed.parts is not None else None
    probabilities = double_areas / double_areas.sum()
    points, normals, total = [], [], 0
    while total < n:
        draw = max(2 * (n - total), 64)
        faces = rng.choice(len(corners), size=draw, p=probabilities)
        s, t = rng.random(draw), rng.random(draw)
        flip = s + t > 1  # fold the unit square onto the triangle
        s, t = np.where(flip, 1 - s, s), np.where(flip, 1 - t, t)
        c = corners[faces]
        drawn = c[:, 0] + s[:, None] * (c[:, 1] - c[:, 0]) + t[:, None] * (c[:, 2] - c[:, 0])
        drawn_normals = face_normals[faces]
        if posed.parts is not None:
            outer = ~posed.parts.contains(drawn, exclude=face_parts[faces], margin=INTERIOR_MARGIN_M)
            drawn, drawn_normals = drawn[outer], drawn_normals[outer]
        points.append(drawn)
        normals.append(drawn_normals)
        total += len(drawn)
    return np.concatenate(points)[:n], np.concatenate(normals)[:n]


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(V, 3) Unit area-weighted averages of the adjacent faces' normals (outward for CCW triangles)."""
    corners = vertices[triangles]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals = np.zeros_like(vertices)
    for corner in range(3):
        np.add.at(normals, triangles[:, corner], cross)
    lengths = np.linalg.norm(normals, axis=1, keepdims=True)
    return normals / np.where(lengths > 0, lengths, 1.0)
