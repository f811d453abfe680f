"""Object substitution (the paper's extension): the clip's object replaced by another one, its
contacts carried over by tracing each original contact along the original object's normal
(outward first, then inward) onto the new object, in the object's own frame. The hand motion
and the object poses are kept; the normal pipeline then pairs, transfers and retargets as for
any clip.
"""

from __future__ import annotations

from dataclasses import fields

import numpy as np

from ..errors import InputError
from ..mesh.geometry import vertex_normals
from ..mesh.topology import check_closed_manifold
from .format import Clip

#: metres: a contact farther than this from the new object (along its normal) is dropped
DEFAULT_MAX_DISTANCE = 0.02


def trace_onto(vertices: np.ndarray, normals: np.ndarray, new_vertices: np.ndarray, new_faces: np.ndarray,
               max_distance: float = DEFAULT_MAX_DISTANCE) -> np.ndarray:
    """For each point (N, 3) with normal (N, 3) (object frame, metres), the index (N,) of the
    new mesh's vertex nearest to where the ray along +normal (else -normal) first meets the
    new surface within ``max_distance``; -1 where neither ray does."""
    import trimesh

    mesh = trimesh.Trimesh(new_vertices, new_faces, process=False)
    best_t = np.full(len(vertices), np.inf)
    best_v = np.full(len(vertices), -1, dtype=np.int64)
    for sign in (1.0, -1.0):
        origins = vertices - sign * 1e-6 * normals  # start just behind the surface: touching counts
        locations, ray_idx, tri_idx = mesh.ray.intersects_location(origins, sign * normals, multiple_hits=False)
        if len(ray_idx) == 0:
            continue
        dist = np.linalg.norm(locations - origins[ray_idx], axis=1)
        corners = new_faces[tri_idx]
        nearest = corners[np.arange(len(tri_idx)), np.argmin(
            np.linalg.norm(new_vertices[corners] - locations[:, None], axis=2), axis=1)]
        # outward hits win; an inward hit only where no outward one was found
        take = (dist <= max_distance) & (best_v[ray_idx] < 0)
        best_t[ray_idx[take]] = dist[take]
        best_v[ray_idx[take]] = nearest[take]
    return best_v


def substitute_object(clip: Clip, new_vertices: np.ndarray, new_faces: np.ndarray, *, name: str = "",
                      max_distance: float = DEFAULT_MAX_DISTANCE) -> tuple[Clip, dict]:
    """A copy of ``clip`` with the object (Vn, 3) m / (Fn, 3) replacing the original, its
    per-frame contact labels (T, Vn) traced from the original's; and a report: labelled
    original vertices, how many were traced, dropped (no new surface within ``max_distance``)."""
    new_vertices = np.asarray(new_vertices, dtype=np.float64)
    new_faces = np.asarray(new_faces, dtype=np.int64)
    if new_vertices.ndim != 2 or new_vertices.shape[1] != 3 or not np.all(np.isfinite(new_vertices)):
        raise InputError("the new object's vertices must be a finite (V, 3) array", element="object vertices")
    if new_faces.ndim != 2 or new_faces.shape[1] != 3 or new_faces.min() < 0 or new_faces.max() >= len(new_vertices):
        raise InputError("the new object's faces must be (F, 3) indices into its vertices", element="object faces")
    topo = check_closed_manifold(new_faces, len(new_vertices))
    if not (topo.closed and topo.manifold):
        raise InputError(f"the new object is not a closed manifold surface: {topo.describe()}", element="object mesh")
    labelled = np.nonzero((clip.contact_labels > 0).any(axis=0))[0]
    normals = vertex_normals(clip.object_vertices, clip.object_faces)
    target = np.full(len(clip.object_vertices), -1, dtype=np.int64)
    target[labelled] = trace_onto(clip.object_vertices[labelled], normals[labelled], new_vertices, new_faces,
                                  max_distance)
    labels = np.zeros((clip.n_frames, len(new_vertices)), dtype=clip.contact_labels.dtype)
    ok = labelled[target[labelled] >= 0]
    for v in ok:  # several original vertices may land on one new vertex: keep any code present
        code = clip.contact_labels[:, v]
        j = target[v]
        labels[:, j] = np.where(code > 0, code, labels[:, j])
    data = {f.name: getattr(clip, f.name) for f in fields(clip)}
    data.update(object_vertices=new_vertices, object_faces=new_faces, contact_labels=labels,
                object_name=name or f"{clip.object_name}->substitute")
    report = {"labelled_vertices": int(len(labelled)), "traced": int(len(ok)),
              "dropped": int(len(labelled) - len(ok)), "new_labelled_vertices": int((labels > 0).any(axis=0).sum())}
    return Clip(**data), report
