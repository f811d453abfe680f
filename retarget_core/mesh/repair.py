"""Repairs of a scanned object's surface that cannot change the shape it shows: coincident
vertices welded, degenerate and repeated faces dropped, stray small components dropped, holes
closed by a fan around each hole's centroid, orientation made consistent and outward. What
cannot be repaired safely (a second large component, a surface still not closed) is refused
with the reason."""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .geometry import face_areas, signed_volume
from .topology import check_closed_manifold

#: a component holding more than this share of the surface area is not a stray piece
STRAY_AREA_SHARE = 0.05
#: metres: vertices this close are one (a scan written as separate triangles)
WELD_DISTANCE = 1e-9


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """The closed loops (vertex index arrays, in the direction of their faces' half-edges) of
    a mesh's boundary edges; raises when the boundary does not form simple loops."""
    half = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    keys = {(int(a), int(b)) for a, b in half}
    open_edges = [(a, b) for a, b in keys if (b, a) not in keys]
    nxt = {}
    for a, b in open_edges:
        if a in nxt:
            raise InputError("the surface's boundary passes a vertex twice (not a set of simple holes)",
                             element="object mesh")
        nxt[a] = b
    loops, seen = [], set()
    for start in sorted(nxt):
        if start in seen:
            continue
        loop, v = [], start
        while v not in seen:
            seen.add(v)
            loop.append(v)
            if v not in nxt:
                raise InputError("the surface's boundary does not close into loops", element="object mesh")
            v = nxt[v]
        loops.append(np.array(loop, dtype=np.int64))
    return loops


def repair_closed_surface(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(vertices (V', 3), faces (F', 3), what was done) for a surface (V, 3) / (F, 3) that
    should be one closed object; unchanged and ``[]`` when it already is one. Raises
    :class:`InputError` with the reason when a repair would change the object."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    topo = check_closed_manifold(faces, len(vertices))
    if topo.closed and topo.manifold and topo.components == 1:
        return vertices, faces, []
    done = []
    # weld coincident vertices
    key = np.round(vertices / WELD_DISTANCE).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    if len(first) < len(vertices):
        done.append(f"welded {len(vertices) - len(first)} coincident vertices")
        order = np.argsort(first)  # keep the vertices in their first-seen order
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        vertices = vertices[first[order]]
        faces = rank[inverse.reshape(-1)][faces]
    # drop degenerate and repeated faces
    good = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])
    good &= face_areas(vertices, faces) > 0
    _, unique = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    keep = np.zeros(len(faces), dtype=bool)
    keep[unique] = True
    keep &= good
    if not keep.all():
        done.append(f"dropped {int((~keep).sum())} degenerate or repeated faces")
        faces = faces[keep]
    # keep the largest component when the others are stray pieces
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(len(vertices),) * 2)
    _, label = connected_components(graph, directed=False)
    face_label = label[faces[:, 0]]
    area = np.bincount(face_label, weights=face_areas(vertices, faces))
    if np.count_nonzero(area) > 1:
        main = int(np.argmax(area))
        others = area.sum() - area[main]
        if np.sort(area)[-2] > STRAY_AREA_SHARE * area.sum():
            raise InputError(f"the mesh has {np.count_nonzero(area)} separate pieces and the second largest holds "
                             f"{100 * np.sort(area)[-2] / area.sum():.0f} % of the surface: not a stray piece of a "
                             "scan; give one object", element="object mesh")
        faces = faces[face_label == main]
        done.append(f"dropped {np.count_nonzero(area) - 1} stray piece(s), {100 * others / area.sum():.2g} % of the area")
    used = np.unique(faces)
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    vertices, faces = vertices[used], remap[faces]
    # close the holes: a fan around each boundary loop's centroid, oriented with its faces
    loops = boundary_loops(faces)
    if loops:
        new_faces, new_vertices = [faces], [vertices]
        at = len(vertices)
        for loop in loops:
            new_vertices.append(vertices[loop].mean(axis=0)[None])
            # the loop runs along its faces' half-edges, so the fan runs against it
            new_faces.append(np.stack([np.roll(loop, -1), loop, np.full(len(loop), at)], axis=1))
            at += 1
        perimeters = [float(np.linalg.norm(vertices[np.roll(l, -1)] - vertices[l], axis=1).sum()) for l in loops]
        vertices, faces = np.concatenate(new_vertices), np.concatenate(new_faces)
        done.append(f"closed {len(loops)} hole(s) (perimeter up to {1000 * max(perimeters):.0f} mm)")
    topo = check_closed_manifold(faces, len(vertices))
    if not (topo.closed and topo.manifold and topo.components == 1):
        raise InputError(f"the mesh could not be repaired into one closed surface: it is {topo.describe()}",
                         element="object mesh")
    if signed_volume(vertices, faces) < 0:
        faces = faces[:, ::-1].copy()
        done.append("turned its faces outward")
    return vertices, faces, done
