"""Object substitution (the paper's extension): the clip's object replaced by another one, its
contacts carried over by tracing each original contact along the original object's normal
(outward first, then inward) onto the new object, in the object's own frame. The hand motion
and the object poses are kept; the normal pipeline then pairs, transfers and retargets as for
any clip.

A new object from elsewhere (a scan) sits in its own frame: it is placed onto the old one
first, by registration (mesh/registration.py) or an explicit transform. Two checks then say
when the result would be wrong: too small a share of the contacts found the new surface, or
the source hand would lie inside the new object.
"""

from __future__ import annotations

from dataclasses import fields

import numpy as np

from ..errors import InputError
from ..mesh.geometry import vertex_normals
from ..mesh.repair import repair_closed_surface
from ..mesh.topology import check_closed_manifold
from .format import Clip

#: metres: a contact farther than this from the new object (along its normal) is dropped
DEFAULT_MAX_DISTANCE = 0.02
#: a substitution that carries over a smaller share of the labelled vertices is refused
DEFAULT_MIN_SHARE = 0.8
#: metres: the source hand deeper than this inside the new object refuses the substitution
DEFAULT_MAX_HAND_DEPTH = 0.002


def trace_onto(vertices: np.ndarray, normals: np.ndarray, new_vertices: np.ndarray, new_faces: np.ndarray,
               max_distance: float = DEFAULT_MAX_DISTANCE) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each point (N, 3) with normal (N, 3) (object frame, metres), where the ray along
    +normal (else -normal) first meets the new surface within ``max_distance``: the new mesh's
    vertex nearest to it (N,), its face (N,) and barycentric coordinates (N, 3) there (the
    point itself, not snapped); -1 (and zeros) where neither ray does."""
    import trimesh

    from ..mesh.surface_points import barycentric_of

    mesh = trimesh.Trimesh(new_vertices, new_faces, process=False)
    best_t = np.full(len(vertices), np.inf)
    best_v = np.full(len(vertices), -1, dtype=np.int64)
    best_f = np.full(len(vertices), -1, dtype=np.int64)
    best_b = np.zeros((len(vertices), 3))
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
        best_f[ray_idx[take]] = tri_idx[take]
        best_b[ray_idx[take]] = barycentric_of(new_vertices[new_faces[tri_idx[take]]], locations[take])
    return best_v, best_f, best_b


def hand_depth_per_frame(clip: Clip, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(T,) metres: how deep the clip's hand goes into the object (V, 3) / (F, 3), given in the
    object's own frame and moved by the clip's object poses, per frame (0: not inside)."""
    from ..mesh.sdf_grid import signed_distances

    lower, upper = vertices.min(axis=0), vertices.max(axis=0)
    points, frame_of = [], []
    for f in range(clip.n_frames):
        pose = clip.object_poses[f]
        local = (clip.hand_vertices[f] - pose[:3, 3]) @ pose[:3, :3]  # world -> object frame
        near = local[np.all((local >= lower) & (local <= upper), axis=1)]  # only these can be inside
        points.append(near)
        frame_of.append(np.full(len(near), f))
    depth = np.zeros(clip.n_frames)
    if sum(len(p) for p in points):  # one query for every frame: the object's trees are built once
        inside = -signed_distances(vertices, faces, np.concatenate(points))
        np.maximum.at(depth, np.concatenate(frame_of), np.maximum(inside, 0.0))
    return depth


def substitute_object(clip: Clip, new_vertices: np.ndarray, new_faces: np.ndarray, *, name: str = "",
                      max_distance: float = DEFAULT_MAX_DISTANCE, register: bool = False,
                      transform: np.ndarray | None = None, min_share: float = DEFAULT_MIN_SHARE,
                      allow_intersection: bool = False, max_hand_depth: float = DEFAULT_MAX_HAND_DEPTH,
                      repair: bool = True) -> tuple[Clip, dict]:
    """A copy of ``clip`` with the object (Vn, 3) m / (Fn, 3) replacing the original, its
    per-frame contact labels (T, Vn) traced from the original's; and a report: labelled
    original vertices, how many were traced, dropped (no new surface within ``max_distance``),
    the share carried over, the transform that placed the new object and, when registered, the
    fit's RMS residual (mm) over the contact region and the whole surface, and the source
    hand's depth inside the new object per frame (mm).

    ``repair``: a new surface that is not one closed object is repaired where that cannot
    change its shape (:func:`~retarget_core.mesh.repair.repair_closed_surface`: welded, stray
    pieces dropped, holes closed; listed in the report's ``repairs``) or refused with the
    reason; without it, refused. Placement: ``transform`` (4, 4) maps the new object's coordinates into the old object's
    frame; else ``register`` fits it (:func:`~retarget_core.mesh.registration.register_surface`
    on the old contact region); else it is taken as given. Refused with an :class:`InputError`
    naming the figure: a share below ``min_share``, or (unless ``allow_intersection``) the
    source hand deeper than ``max_hand_depth`` m inside the new object in any frame (the frames
    listed)."""
    new_vertices = np.asarray(new_vertices, dtype=np.float64)
    new_faces = np.asarray(new_faces, dtype=np.int64)
    if new_vertices.ndim != 2 or new_vertices.shape[1] != 3 or not np.all(np.isfinite(new_vertices)):
        raise InputError("the new object's vertices must be a finite (V, 3) array", element="object vertices")
    if new_faces.ndim != 2 or new_faces.shape[1] != 3 or new_faces.min() < 0 or new_faces.max() >= len(new_vertices):
        raise InputError("the new object's faces must be (F, 3) indices into its vertices", element="object faces")
    repairs = []
    if repair:
        new_vertices, new_faces, repairs = repair_closed_surface(new_vertices, new_faces)
    topo = check_closed_manifold(new_faces, len(new_vertices))
    if not (topo.closed and topo.manifold):
        raise InputError(f"the new object is not a closed manifold surface: {topo.describe()}", element="object mesh")
    labelled = np.nonzero((clip.contact_labels > 0).any(axis=0))[0]
    report = {"repairs": repairs}
    if transform is not None:
        transform = np.asarray(transform, dtype=np.float64)
        if transform.shape != (4, 4) or not np.all(np.isfinite(transform)) or \
                not np.allclose(transform[3], [0, 0, 0, 1]) or abs(np.linalg.det(transform[:3, :3])) < 1e-12:
            raise InputError("the transform must be a finite, invertible affine 4 x 4 matrix", element="transform")
    elif register:
        from ..mesh.registration import register_surface

        fit = register_surface(clip.object_vertices, clip.object_faces, new_vertices, new_faces, region=labelled)
        transform = fit.transform
        report.update(residual_mm=1000 * fit.rms, surface_residual_mm=1000 * fit.surface_rms)
    else:
        transform = np.eye(4)
    new_vertices = new_vertices @ transform[:3, :3].T + transform[:3, 3]
    report["transform"] = transform.tolist()
    normals = vertex_normals(clip.object_vertices, clip.object_faces)
    target = np.full(len(clip.object_vertices), -1, dtype=np.int64)
    face = np.full(len(clip.object_vertices), -1, dtype=np.int64)
    bary = np.zeros((len(clip.object_vertices), 3))
    target[labelled], face[labelled], bary[labelled] = trace_onto(
        clip.object_vertices[labelled], normals[labelled], new_vertices, new_faces, max_distance)
    labels = np.zeros((clip.n_frames, len(new_vertices)), dtype=clip.contact_labels.dtype)
    ok = labelled[target[labelled] >= 0]
    for v in ok:  # several original vertices may land on one new vertex: keep any code present
        code = clip.contact_labels[:, v]
        j = target[v]
        labels[:, j] = np.where(code > 0, code, labels[:, j])
    # each traced contact as the surface point it landed on (what pairing uses); the labels
    # mark their nearest vertices, for display
    rows = [ok[clip.contact_labels[f, ok] > 0] for f in range(clip.n_frames)]
    every = np.concatenate(rows) if rows else np.zeros(0, np.int64)
    frame_of = np.repeat(np.arange(clip.n_frames), [len(r) for r in rows])
    data = {f.name: getattr(clip, f.name) for f in fields(clip)}
    data.update(contact_offsets=np.concatenate([[0], np.cumsum([len(r) for r in rows])]).astype(np.int64),
                contact_faces=face[every], contact_barycentric=bary[every],
                contact_codes=clip.contact_labels[frame_of, every].astype(np.uint8))
    data.update(object_vertices=new_vertices, object_faces=new_faces, contact_labels=labels,
                object_name=name or f"{clip.object_name}->substitute")
    share = float(len(ok) / len(labelled)) if len(labelled) else 1.0
    report.update(labelled_vertices=int(len(labelled)), traced=int(len(ok)), dropped=int(len(labelled) - len(ok)),
                  new_labelled_vertices=int((labels > 0).any(axis=0).sum()), share=share)
    if share < min_share:
        raise InputError(f"only {100 * share:.1f} % of the contacts ({len(ok)} of {len(labelled)} labelled vertices) "
                         f"reach the new object within {100 * max_distance:g} cm (at least {100 * min_share:g} % "
                         "needed): place it where the old object is (register it, or give its transform)",
                         element="new object")
    depth = hand_depth_per_frame(clip, new_vertices, new_faces)
    report["hand_depth_mm"] = (1000 * depth).tolist()
    deep = np.flatnonzero(depth > max_hand_depth)
    if len(deep) and not allow_intersection:
        listed = ", ".join(str(int(f)) for f in deep[:12]) + (", ..." if len(deep) > 12 else "")
        raise InputError(f"the source hand lies up to {1000 * depth.max():.1f} mm inside the new object in "
                         f"{len(deep)} of {clip.n_frames} frames (frames {listed}; more than "
                         f"{1000 * max_hand_depth:g} mm): it cuts through the captured hand. Place or size it "
                         "differently, or allow it (allow_intersection, --allow-intersection)",
                         element="new object")
    return Clip(**data), report
