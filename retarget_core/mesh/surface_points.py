"""Points on a triangle mesh as (face index, barycentric coordinates).

DESIGN.md: a point on a surface is never a vertex id snapped from elsewhere, so meshes of
any resolution exchange data without clamping error. A vertex id is the special case
``barycentric = (1, 0, 0)`` on one of its faces.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError


@dataclass(frozen=True)
class SurfacePoints:
    """P points on a mesh. faces: (P,) int64; barycentric: (P, 3) float64, rows sum to 1."""

    faces: np.ndarray
    barycentric: np.ndarray

    def __post_init__(self):
        faces = np.asarray(self.faces, dtype=np.int64).reshape(-1)
        bary = np.asarray(self.barycentric, dtype=np.float64).reshape(-1, 3)
        if len(faces) != len(bary):
            raise InputError(
                f"{len(faces)} faces but {len(bary)} barycentric rows", element="surface points"
            )
        if not np.all(np.isfinite(bary)):
            raise InputError("barycentric coordinates contain NaN or inf", element="surface points")
        object.__setattr__(self, "faces", faces)
        object.__setattr__(self, "barycentric", bary)

    def __len__(self) -> int:
        return len(self.faces)

    def validate(self, mesh_faces: np.ndarray, *, source: str = "") -> None:
        """Raise InputError unless every face index exists and every barycentric row is a
        valid convex combination (non-negative within 1e-6, sums to 1 within 1e-6)."""
        n = len(mesh_faces)
        bad = np.nonzero((self.faces < 0) | (self.faces >= n))[0]
        if len(bad):
            raise InputError(
                f"face index {int(self.faces[bad[0]])} out of range [0, {n})",
                source=source,
                element=f"surface point {int(bad[0])}",
            )
        sums = self.barycentric.sum(axis=1)
        bad = np.nonzero((np.abs(sums - 1) > 1e-6) | np.any(self.barycentric < -1e-6, axis=1))[0]
        if len(bad):
            raise InputError(
                f"barycentric {self.barycentric[bad[0]].tolist()} is not a convex combination",
                source=source,
                element=f"surface point {int(bad[0])}",
            )

    @classmethod
    def from_vertices(cls, vertex_ids: np.ndarray, mesh_faces: np.ndarray) -> "SurfacePoints":
        """Surface points exactly at the given vertices (one incident face each)."""
        vertex_ids = np.asarray(vertex_ids, dtype=np.int64).reshape(-1)
        mesh_faces = np.asarray(mesh_faces, dtype=np.int64)
        n_vertices = int(mesh_faces.max()) + 1
        if np.any((vertex_ids < 0) | (vertex_ids >= n_vertices)):
            bad = vertex_ids[(vertex_ids < 0) | (vertex_ids >= n_vertices)][0]
            raise InputError(f"vertex id {int(bad)} out of range [0, {n_vertices})", element="vertex ids")
        # First incident face and corner of every vertex.
        flat = mesh_faces.reshape(-1)
        first = np.full(n_vertices, -1, dtype=np.int64)
        first[flat[::-1]] = np.arange(len(flat))[::-1]
        slot = first[vertex_ids]
        if np.any(slot < 0):
            raise InputError("vertex is used by no face", element=f"vertex {int(vertex_ids[slot < 0][0])}")
        faces = slot // 3
        bary = np.zeros((len(vertex_ids), 3))
        bary[np.arange(len(vertex_ids)), slot % 3] = 1.0
        return cls(faces, bary)

    def positions(self, vertices: np.ndarray, mesh_faces: np.ndarray) -> np.ndarray:
        """(P, 3) positions on a mesh with vertices (V, 3) and faces (F, 3)."""
        corners = np.asarray(vertices)[np.asarray(mesh_faces)[self.faces]]  # (P, 3, 3)
        return np.einsum("pk,pkd->pd", self.barycentric, corners)


def closest_surface_points(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> SurfacePoints:
    """The surface points of a mesh closest to query points (N, 3), as (face, barycentric)."""
    import igl

    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    points = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    _, face, closest = igl.point_mesh_squared_distance(points, vertices, faces)
    face = np.asarray(face, dtype=np.int64)
    return SurfacePoints(face, barycentric_of(vertices[faces[face]], closest))


def barycentric_of(triangles: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 3) barycentric coordinates of points (N, 3) in triangles (N, 3, 3), clipped to the
    triangle and renormalised (points are expected on or very near their triangle)."""
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    v0, v1, v2 = b - a, c - a, points - a
    d00 = np.einsum("ij,ij->i", v0, v0)
    d01 = np.einsum("ij,ij->i", v0, v1)
    d11 = np.einsum("ij,ij->i", v1, v1)
    d20 = np.einsum("ij,ij->i", v2, v0)
    d21 = np.einsum("ij,ij->i", v2, v1)
    denom = d00 * d11 - d01 * d01
    denom = np.where(np.abs(denom) < 1e-300, 1e-300, denom)
    v = (d11 * d20 - d01 * d21) / denom
    w = (d00 * d21 - d01 * d20) / denom
    bary = np.clip(np.column_stack([1.0 - v - w, v, w]), 0.0, None)
    return bary / bary.sum(axis=1, keepdims=True)
