"""Geometry of triangle meshes and boxes, over numpy arrays, for every stage of the pipeline.

Meshes: vertices (V, 3) float metres, faces (F, 3) int vertex ids, counter-clockwise seen from
outside for an outward-wound mesh. Boxes: a rigid ``pose`` (4, 4, world-from-box) whose origin
is the box centre and ``half_extents`` (3,) metres along the box's own axes. Signed distances
are negative inside.

The solver and the pairing depend on these functions to the last bit: change a formula here
and the retarget results change.
"""

from __future__ import annotations

import numpy as np

#: Distance (m) within which a point counts as lying *on* a surface in the evaluation's
#: predicates (``retarget_core.evaluate``): a hand vertex is inside the table (a box) only
#: deeper than this, and a contact is realised within a distance threshold up to this much
#: beyond it. One nanometre: far below any capture or modelling accuracy, far above the
#: round-off of float64 coordinates in metres (about 1e-17 m near 0.1 m), so a vertex placed
#: exactly on a surface is never counted as in it because of the arithmetic of its pose. The
#: solver's own terms do not use it (their numerics are unchanged).
SURFACE_TOLERANCE_M = 1e-9


# ---- triangle meshes ---------------------------------------------------------------------------
def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume (m^3) enclosed by a closed triangle mesh: the sum of the signed tetrahedra
    (centroid, a, b, c) / 6. Positive for outward-facing (counter-clockwise) faces; 0 without
    faces. vertices: (V, 3) metres; faces: (F, 3) int."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        return 0.0
    c = v.mean(axis=0)  # centring only improves the floating-point sum
    a, b, d = v[f[:, 0]] - c, v[f[:, 1]] - c, v[f[:, 2]] - c
    return float(np.einsum("ij,ij->i", a, np.cross(b, d)).sum() / 6.0)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) unit area-weighted vertex normals (zero for a vertex no face uses).
    vertices (V, 3), faces (F, 3)."""
    tri = vertices[faces]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 * area
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, faces[:, k], face_n)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return normals / np.maximum(length, 1e-300)


def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) triangle areas (units of vertices squared). vertices (V, 3), faces (F, 3)."""
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) unit face normals (right-hand rule over the corners); a zero-area face gets a
    zero normal, not NaN. vertices (V, 3), faces (F, 3)."""
    tri = vertices[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(fn, axis=1, keepdims=True)
    return np.divide(fn, length, out=np.zeros_like(fn), where=length > 0)


# ---- boxes -------------------------------------------------------------------------------------
def box_local(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Points (N, 3) world metres in the frame of the box at ``pose`` (4, 4, rigid): (N, 3)."""
    pose = np.asarray(pose, dtype=np.float64)
    return (points - pose[:3, 3]) @ pose[:3, :3]


def _box_parts(local: np.ndarray, half_extents: np.ndarray):
    """Per point (N, 3) box frame: the excess over the half extents q (N, 3), its positive part
    (N, 3), that part's length (N,) and the signed distance (N,)."""
    q = np.abs(local) - half_extents
    outside = np.maximum(q, 0.0)
    out_len = np.linalg.norm(outside, axis=1)
    return q, outside, out_len, out_len + np.minimum(q.max(axis=1), 0.0)


def box_signed_distance_local(local: np.ndarray, half_extents: np.ndarray) -> np.ndarray:
    """Exact signed distance (N,) metres, negative inside, of points (N, 3) given in the box's
    frame to the box centred there with ``half_extents`` (3,) metres."""
    return _box_parts(local, half_extents)[3]


def box_signed_distance(points: np.ndarray, pose: np.ndarray, half_extents: np.ndarray) -> np.ndarray:
    """Exact signed distance (N,) metres, negative inside, of points (N, 3) world metres to the
    box centred on the origin of ``pose`` (4, 4 world-from-box, rigid) with ``half_extents``
    (3,) metres."""
    local = box_local(np.asarray(points, dtype=np.float64), pose)
    return box_signed_distance_local(local, np.asarray(half_extents, dtype=np.float64))


def box_signed_distance_and_gradient(points: np.ndarray, pose: np.ndarray, half_extents: np.ndarray):
    """Signed distance (N,) metres (negative inside) of points (N, 3) world metres to the box
    at ``pose`` (4, 4, rigid) with ``half_extents`` (3,), and its gradient (N, 3), world frame
    (unit length; inside, the normal of the nearest face)."""
    rot = pose[:3, :3]
    local = box_local(points, pose)
    q, outside, out_len, sdf = _box_parts(local, half_extents)
    grad_local = np.where(out_len[:, None] > 0, outside / np.maximum(out_len, 1e-300)[:, None], 0.0)
    axis = np.argmax(q, axis=1)
    in_rows = out_len <= 0
    grad_local[in_rows] = 0.0
    grad_local[in_rows, axis[in_rows]] = 1.0
    grad_local *= np.sign(local) + (local == 0)
    return sdf, grad_local @ rot.T


def box_inside(points: np.ndarray, pose: np.ndarray, half_extents: np.ndarray):
    """The points (N, 3) world metres inside the box at ``pose`` (4, 4, rigid) with
    ``half_extents`` (3,): (ids (I,), signed distances (I,) metres, all negative, and their
    gradients (I, 3) world, the outward normal of the nearest face). The same values as
    :func:`box_signed_distance_and_gradient` at those points, at a fraction of its cost where
    most points are outside (a hand above a table): inside a box the signed distance is the
    largest excess over the half extents, so nothing is built for the points outside."""
    local = box_local(points, pose)
    q = np.abs(local) - half_extents
    excess = q.max(axis=1)
    ids = np.flatnonzero(excess < 0)
    axis = np.argmax(q[ids], axis=1)
    grad_local = np.zeros((len(ids), 3))
    grad_local[np.arange(len(ids)), axis] = 1.0
    grad_local *= np.sign(local[ids]) + (local[ids] == 0)
    return ids, excess[ids], grad_local @ pose[:3, :3].T


def rigid_fit(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The rigid transform (4, 4) moving points ``source`` (N, 3) onto ``target`` (N, 3) with
    the least squared distance (Kabsch; reflections excluded)."""
    cs, ct = source.mean(axis=0), target.mean(axis=0)
    h = (source - cs).T @ (target - ct)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1, 1, d]) @ u.T
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = ct - r @ cs
    return m
