"""A hand inside a larger skeleton (a character's body: spine, arm, hand) cut out as a hand rig.

The hand's root joint is named (``hand_root``, e.g. the forearm or the wrist) or found: the
palm is the one joint where three or more unbranched jointed chains (fingers) start, and the
hand's root is its parent (so the wrist bends). Only that joint's subtree is kept; the surface
is the part of the bound mesh the subtree carries (skin weight share at least one half),
its largest connected piece, each opening left by the cut closed with a fan around the
opening's centre (the cap: it lies at the forearm, far from any contact). Skin weight on joints
outside the subtree goes to the hand's root. When a rig is already only a hand (its palm's
parent is the skeleton's root, or there is no parent), it is returned unchanged."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..errors import InputError
from ..mesh.isosurface import largest_component
from .model import Joint, Rig, SkinnedMesh

#: A vertex belongs to the cut hand when the kept joints carry at least this share of it.
KEEP_SHARE = 0.5
#: rig metadata key: where the cut surface's vertices and triangles are in the file's mesh
SURFACE_SOURCE = "surface_source"


def _children(rig: Rig) -> list[list[int]]:
    out: list[list[int]] = [[] for _ in rig.joints]
    for j, joint in enumerate(rig.joints):
        if joint.parent >= 0:
            out[joint.parent].append(j)
    return out


def _fans(rig: Rig) -> list[int]:
    """Joints where three or more unbranched chains of at least two joints start."""
    children = _children(rig)

    def chain_length(j):  # joints down an unbranched chain from j to its leaf, 0 when it branches
        n = 0
        while True:
            n += 1
            if not children[j]:
                return n
            if len(children[j]) > 1:
                return 0
            j = children[j][0]

    return [j for j in range(rig.n_joints) if sum(chain_length(c) >= 2 for c in children[j]) >= 3]


def find_hand_root(rig: Rig, hand_root: str | None = None) -> int:
    """The joint the hand's subtree starts at (see the module docstring)."""
    if hand_root is not None:
        try:
            return rig.joint_index(hand_root)
        except KeyError:
            raise InputError(f"no joint named {hand_root!r} (--hand-root); joints: "
                             f"{', '.join(rig.joint_names[:12])}{', ...' if rig.n_joints > 12 else ''}",
                             source=rig.name, element="hand_root") from None
    fans = _fans(rig)
    # a fan inside another fan's subtree is part of the same hand (fingers branching from
    # several joints): keep the outermost
    ancestors = {j: set() for j in fans}
    for j in fans:
        p = rig.joints[j].parent
        while p >= 0:
            ancestors[j].add(p)
            p = rig.joints[p].parent
    outer = [j for j in fans if not (ancestors[j] & set(fans))]
    if not outer:
        return 0
    if len(outer) > 1:
        names = ", ".join(rig.joint_names[j] for j in outer)
        raise InputError(f"the skeleton has {len(outer)} hands (fingers branch at {names}): name the one to "
                         "retarget with --hand-root (its wrist or forearm joint)", source=rig.name, element="hand_root")
    palm = outer[0]
    return max(rig.joints[palm].parent, 0)


def cut_hand(rig: Rig, hand_root: str | None = None) -> Rig:
    """The hand of ``rig`` as its own rig (no DOFs kept on the removed joints; the joints of the
    subtree keep theirs). See the module docstring."""
    root = find_hand_root(rig, hand_root)
    if root == 0:
        return rig
    keep = [root]
    children = _children(rig)
    for j in keep:
        keep.extend(children[j])
    keep = sorted(keep)
    new_index = np.full(rig.n_joints, -1, dtype=np.int64)
    new_index[keep] = np.arange(len(keep))
    world = rig.kinematics().bind_world
    joints = []
    for j in keep:
        parent = rig.joints[j].parent
        local = world[j] if j == root else np.array(rig.joints[j].rest_local, float)
        joints.append(Joint(rig.joints[j].name, -1 if j == root else int(new_index[parent]), local))
    dofs = [replace(d, joint=int(new_index[d.joint]), axis=np.array(d.axis, float))
            for d in rig.dofs if new_index[d.joint] >= 0]
    surface, used = _cut_mesh(rig.surface, new_index, int(new_index[root]), rig.n_joints,
                              what=f"{rig.name} surface")
    cut = Rig(name=rig.name, joints=joints, dofs=dofs, surface=surface, visual=None,
              metadata={**rig.metadata, "hand_root": rig.joint_names[root],
                        "cut_from": f"{rig.n_joints} joints, {rig.surface.n_vertices} vertices",
                        SURFACE_SOURCE: surface_source(rig, surface, used)})
    cut.validate(source=f"{rig.name} (the hand below {rig.joint_names[root]!r})")
    return cut


def _cut_mesh(mesh: SkinnedMesh, new_index: np.ndarray, root: int, n_joints: int, *,
              what: str) -> tuple[SkinnedMesh, np.ndarray]:
    """The part of ``mesh`` the kept joints carry, capped; and (n,) the ids of its first n
    vertices in ``mesh`` (the rest are cap centres)."""
    dense = mesh.dense_weights(n_joints)
    kept_joints = np.nonzero(new_index >= 0)[0]
    share = dense[:, kept_joints].sum(axis=1)
    inside = share >= KEEP_SHARE
    faces = mesh.faces[inside[mesh.faces].all(axis=1)]
    if not len(faces):
        raise InputError("no part of the mesh is carried by the hand's joints", source=what)
    # the vertex ids ride along as a fourth column through the compaction
    tagged, faces = largest_component(np.column_stack([mesh.vertices, np.arange(mesh.n_vertices)]), faces)
    vertices, used = tagged[:, :3], tagged[:, 3].astype(np.int64)
    weights = np.zeros((len(vertices), len(kept_joints)))
    weights[:, :] = dense[used][:, kept_joints]
    weights[:, root] += 1.0 - weights.sum(axis=1)  # what the removed joints carried
    vertices, faces, weights = cap_openings(vertices, faces, weights, what=what,
                                            remedy="pick another joint with --hand-root")
    k = min(4, weights.shape[1])
    order = np.argsort(-weights, axis=1)[:, :k]
    top = np.take_along_axis(weights, order, axis=1)
    top /= top.sum(axis=1, keepdims=True)
    return SkinnedMesh(vertices=vertices, faces=faces, joint_indices=order, joint_weights=top), used


def cap_openings(vertices, faces, weights, *, what: str = "the surface", remedy: str = ""):
    """Close every boundary loop of the mesh (vertices (V, 3), faces (F, 3), per-vertex rows
    ``weights`` (V, J)) with a fan around its centroid, oriented like the mesh: one vertex per
    loop (its weights the loop's mean) and its triangles appended after the mesh's own.
    Returns (vertices, faces, weights)."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = {tuple(e) for e in edges.tolist()}
    boundary = [(a, b) for a, b in edges.tolist() if (b, a) not in key]
    if not boundary:
        return vertices, faces, weights
    hint = f"; {remedy}" if remedy else ""
    following = {}
    for a, b in boundary:
        if a in following:
            raise InputError(f"an opening of the mesh is not a simple loop (a non-manifold boundary at vertex {a})"
                             f"{hint}", source=what, element="surface")
        following[a] = b
    new_v, new_f, new_w = [vertices], [faces], [weights]
    n = len(vertices)
    seen = set()
    for start in list(following):
        if start in seen:
            continue
        loop = [start]
        seen.add(start)
        while following[loop[-1]] != start:
            nxt = following[loop[-1]]
            if nxt in seen:
                raise InputError(f"the mesh's openings are tangled{hint}", source=what, element="surface")
            loop.append(nxt)
            seen.add(nxt)
        loop = np.array(loop)
        new_v.append(vertices[loop].mean(axis=0)[None])
        new_w.append(weights[loop].mean(axis=0)[None])
        # the boundary edge a -> b belongs to a face running a -> b: the cap runs b -> a
        new_f.append(np.stack([np.roll(loop, -1), loop, np.full(len(loop), n)], axis=1))
        n += 1
    return np.concatenate(new_v), np.concatenate(new_f), np.concatenate(new_w)


def keep_main_shell(rig: Rig) -> Rig:
    """``rig`` with only the largest connected piece of its surface when the surface has
    several (nails, buttons, separate shells a DCC mesh often carries); what was dropped is
    recorded in ``metadata["warnings"]``. The rig itself when the surface is one piece."""
    surface = rig.surface
    tagged, faces = largest_component(np.column_stack([surface.vertices, np.arange(surface.n_vertices)]),
                                      surface.faces)
    if len(faces) == len(surface.faces):
        return rig
    used = tagged[:, 3].astype(np.int64)
    dropped_faces = len(surface.faces) - len(faces)
    kept = SkinnedMesh(vertices=tagged[:, :3], faces=faces, joint_indices=surface.joint_indices[used],
                       joint_weights=surface.joint_weights[used])
    warning = (f"the surface mesh has more than one piece: kept the largest ({len(faces)} faces), "
               f"left out {surface.n_vertices - len(used)} vertices and {dropped_faces} faces of the others "
               "(nails or separate shells take no part in contacts)")
    return Rig(name=rig.name, joints=list(rig.joints), dofs=list(rig.dofs), surface=kept, visual=rig.visual,
               metadata={**rig.metadata, "warnings": list(rig.metadata.get("warnings", [])) + [warning],
                         SURFACE_SOURCE: surface_source(rig, kept, used)})


def cap_faces(rig: Rig) -> np.ndarray:
    """(K,) ids of the surface triangles that close a cut (no triangle of the file's mesh):
    they never receive contacts (transfer drops contacts carried onto them)."""
    source = rig.metadata.get(SURFACE_SOURCE)
    if not source:
        return np.zeros(0, dtype=np.int64)
    return np.nonzero(np.asarray(source["faces"]) < 0)[0]


def uncapped_faces(rig: Rig) -> int:
    """How many leading triangles of ``rig``'s surface are the file's own: all of them, unless
    caps were appended after them (a MANO hand's closed wrist, :mod:`retarget_core.rig.mano`)."""
    caps = cap_faces(rig)
    n = len(rig.surface.faces)
    if len(caps) and np.array_equal(caps, np.arange(n - len(caps), n)):
        return n - len(caps)
    return n


def surface_matches_hand(rig: Rig, hand_faces: np.ndarray, n_hand_vertices: int | None = None) -> bool:
    """Whether a clip's hand mesh (its triangles (F, 3), and its vertex count) is ``rig``'s
    surface: the same mesh, or the same before the cap triangles and cap centres appended to
    close it."""
    hand_faces = np.asarray(hand_faces)
    n = len(hand_faces)
    faces = rig.surface.faces
    if n == len(faces):
        same_vertices = n_hand_vertices in (None, rig.surface.n_vertices)
    else:
        n_caps = len(faces) - n
        centres = sum(1 for v in (rig.metadata.get(SURFACE_SOURCE) or {}).get("vertices", []) if v < 0)
        same_vertices = n_hand_vertices in (None, rig.surface.n_vertices - centres) and n_caps > 0 \
            and n == uncapped_faces(rig)
    return same_vertices and np.array_equal(faces[:n], hand_faces)


def surface_source(before: Rig, surface: SkinnedMesh, used: np.ndarray) -> dict:
    """Where each vertex and triangle of ``surface`` (cut or pruned from ``before``'s) comes
    from in the file's mesh, so that a tool holding that mesh (the Blender add-in) can carry
    annotation points between the two: {"vertices": [file vertex id, -1 for a cap's centre],
    "faces": [file triangle id, -1 for a cap triangle], "file_vertices", "file_faces"}.
    ``used``: (n,) ids in ``before``'s surface of the first n vertices of ``surface``; the
    kept triangles keep their corner order. Composed with what ``before`` records."""
    prior = before.metadata.get(SURFACE_SOURCE)
    n_used = len(used)
    index = {tuple(int(x) for x in f): i for i, f in enumerate(before.surface.faces)}
    faces = np.full(len(surface.faces), -1, dtype=np.int64)
    for i, f in enumerate(surface.faces):
        if f.max() < n_used:
            faces[i] = index[tuple(int(x) for x in used[f])]
    vertices = np.concatenate([used, np.full(surface.n_vertices - n_used, -1, dtype=np.int64)])
    file_vertices, file_faces = before.surface.n_vertices, len(before.surface.faces)
    if prior is not None:  # ids in ``before`` -> ids in the file
        pv, pf = np.asarray(prior["vertices"]), np.asarray(prior["faces"])
        vertices = np.where(vertices >= 0, pv[np.maximum(vertices, 0)], -1)
        faces = np.where(faces >= 0, pf[np.maximum(faces, 0)], -1)
        file_vertices, file_faces = prior["file_vertices"], prior["file_faces"]
    return {"vertices": vertices.tolist(), "faces": faces.tolist(), "file_vertices": int(file_vertices),
            "file_faces": int(file_faces)}
