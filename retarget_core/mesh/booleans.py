"""Exact mesh booleans and volumes through the manifold library (``manifold3d``).

Manifold computes intersections and unions of closed, consistently wound triangle meshes
exactly up to float64 round-off (symbolic perturbation settles coplanar and coincident faces),
so the volumes here are the volumes of the meshes as given, not of a sampling of them. Units
are whatever the vertices carry (metres throughout the project): volumes in m^3.

Only this module imports ``manifold3d``.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError


def solid(vertices: np.ndarray, faces: np.ndarray, *, what: str = "mesh"):
    """A ``manifold3d.Manifold`` of the closed mesh vertices (V, 3) / faces (F, 3), wound
    outward (counter-clockwise seen from outside). Raises :class:`InputError` naming ``what``
    and manifold's status when the mesh is not a closed oriented 2-manifold."""
    from manifold3d import Manifold, Mesh64

    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.uint32)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise InputError(f"needs (V, 3) vertices and (F, 3) faces, got {v.shape} and {f.shape}", element=what)
    if not np.all(np.isfinite(v)):
        raise InputError("vertices are not all finite", element=what)
    m = Manifold(Mesh64(vert_properties=v, tri_verts=f))
    status = m.status()
    if status.name != "NoError":
        raise InputError(f"not a closed oriented manifold for exact booleans (manifold3d: {status.name})",
                         element=what)
    return m


def box_solid(pose: np.ndarray, half_extents: np.ndarray):
    """The box of ``half_extents`` (3,) centred on the rigid ``pose`` (4, 4, world-from-box)."""
    from manifold3d import Manifold

    he = np.asarray(half_extents, dtype=np.float64)
    return Manifold.cube(list(2.0 * he), True).transform(np.asarray(pose, dtype=np.float64)[:3, :])


def union(solids: list):
    """The union of manifolds (one batched boolean)."""
    from manifold3d import Manifold, OpType

    if len(solids) == 1:
        return solids[0]
    return Manifold.batch_boolean(list(solids), OpType.Add)


def mesh_of(m) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64, faces (F, 3) int64) of a manifold."""
    mesh = m.to_mesh64()
    v = np.asarray(mesh.vert_properties, dtype=np.float64)[:, :3]
    return v, np.asarray(mesh.tri_verts, dtype=np.int64).reshape(-1, 3)


def transformed(m, pose: np.ndarray):
    """``m`` moved by the (4, 4) affine ``pose``."""
    return m.transform(np.asarray(pose, dtype=np.float64)[:3, :])
