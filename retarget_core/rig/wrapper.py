"""A closed, connected, manifold "wrapper" surface around a robot hand's link geometry.

Robot link meshes are usually not watertight, overlap each other and hide internal parts,
so they cannot serve as the rig's surface directly. :func:`build_wrapper` samples the
unsigned distance to the union of all link meshes on a regular grid and extracts the level
set at ``offset`` metres (a thin "shrink wrap"):

1. distance: ``igl.point_mesh_squared_distance`` against the concatenated link meshes; grid
   nodes far from any geometry (judged on a 4x coarser grid first) are not queried exactly;
2. inside mask = distance < offset; enclosed cavities are filled (no inner shells);
3. if the inside region falls into several pieces (6-connectivity), gaps are bridged by
   morphological closing with a growing ball (up to ``max_bridge`` metres); beyond that an
   :class:`InputError` names the links that stay disconnected;
4. marching cubes -> largest component -> closed manifold check
   (:func:`closed_surface_from_field`).

Skin weights: every wrapper vertex is bound rigidly to the link whose geometry is nearest;
within a narrow band (the two nearest links' distances differ by less than ``blend_band``) it
is blended linearly with the second-nearest link. When ``parents`` is given the second link
must be the parent or a child of the first (so neighbouring fingertips never share vertices).
"""

from __future__ import annotations

from collections.abc import Sequence

import igl
import numpy as np
from scipy import ndimage

from ..errors import InputError
from ..mesh.isosurface import closed_surface_from_field
from .model import SkinnedMesh

#: Largest grid (nodes) sampled; coarser spacing is used beyond it.
MAX_GRID_NODES = 6_000_000


def _concatenate(link_meshes):
    verts, faces, owner = [], [], []
    base = 0
    for joint, v, f in link_meshes:
        v = np.asarray(v, dtype=np.float64).reshape(-1, 3)
        f = np.asarray(f, dtype=np.int64).reshape(-1, 3)
        if len(v) == 0 or len(f) == 0:
            continue
        if not np.all(np.isfinite(v)):
            raise InputError("link geometry has NaN or infinite vertices", element=f"joint {joint}")
        verts.append(v)
        faces.append(f + base)
        owner.append(np.full(len(f), int(joint), dtype=np.int64))
        base += len(v)
    if not verts:
        raise InputError("no link geometry to wrap", element="wrapper")
    return np.concatenate(verts), np.concatenate(faces), np.concatenate(owner)


def _grid_axes(lower, upper, spacing):
    shape = tuple(int(np.ceil((u - l) / spacing)) + 1 for l, u in zip(lower, upper))
    return [lower[i] + spacing * np.arange(shape[i]) for i in range(3)], shape


def _distances(points, verts, faces):
    d2, face, _ = igl.point_mesh_squared_distance(points, verts, faces)
    return np.sqrt(np.maximum(d2, 0.0)), np.asarray(face, dtype=np.int64)


def _nodes(axes, mask):
    """(N, 3) positions of the grid nodes where ``mask`` is true."""
    i, j, k = np.nonzero(mask)
    return np.column_stack([axes[0][i], axes[1][j], axes[2][k]])


def _ball(radius_voxels: int) -> np.ndarray:
    r = radius_voxels
    x, y, z = np.mgrid[-r : r + 1, -r : r + 1, -r : r + 1]
    return (x * x + y * y + z * z) <= r * r + 1e-9


def build_wrapper(
    link_meshes: list[tuple[int, np.ndarray, np.ndarray]],
    resolution: float = 0.002,
    offset: float = 0.0015,
    max_influences: int = 2,
    *,
    parents: Sequence[int] | None = None,
    blend_band: float = 0.002,
    max_bridge: float = 0.01,
    link_names: dict[int, str] | None = None,
) -> SkinnedMesh:
    """Closed, connected, manifold surface around the union of link meshes, skinned to them.

    link_meshes: (joint index, vertices (V, 3) world metres at rest, faces (F, 3)) per piece of
    geometry; several pieces may share a joint. resolution: grid spacing (m), raised
    automatically when the grid would exceed ``MAX_GRID_NODES``. offset: distance of the
    wrapper from the geometry (m, > 0). max_influences: 1 (rigid) or 2 (blend band).
    parents: optional joint parent indices restricting blends to tree neighbours.
    link_names: optional joint index -> name, used in error messages.
    """
    if not (resolution > 0 and np.isfinite(resolution)):
        raise InputError(f"resolution must be a positive number, got {resolution!r}", element="wrapper")
    if not (offset > 0 and np.isfinite(offset)):
        raise InputError(f"offset must be a positive number, got {offset!r}", element="wrapper")
    if max_influences not in (1, 2):
        raise InputError(f"max_influences must be 1 or 2, got {max_influences!r}", element="wrapper")
    verts, faces, face_owner = _concatenate(link_meshes)
    names = link_names or {}

    # ---- grid ---------------------------------------------------------------------------
    margin = offset + 3 * resolution
    lower = verts.min(axis=0) - margin
    upper = verts.max(axis=0) + margin
    spacing = float(resolution)
    extent = upper - lower
    n_nodes = np.prod(np.ceil(extent / spacing) + 1)
    if n_nodes > MAX_GRID_NODES:
        spacing = float((np.prod(extent) / MAX_GRID_NODES) ** (1.0 / 3.0)) * 1.05
        margin = offset + 3 * spacing
        lower = verts.min(axis=0) - margin
        upper = verts.max(axis=0) + margin
    axes, shape = _grid_axes(lower, upper, spacing)

    # Coarse pass (4x spacing): only fine nodes within reach of the level set need an exact
    # distance; the rest keep a lower bound, which is all the level set needs.
    coarse_step = 4
    coarse_axes = [a[::coarse_step] for a in axes]
    coarse_pts = np.stack(np.meshgrid(*coarse_axes, indexing="ij"), axis=-1).reshape(-1, 3)
    coarse_d, _ = _distances(coarse_pts, verts, faces)
    coarse_d = coarse_d.reshape([len(a) for a in coarse_axes])
    # A fine node lies within (coarse_step * sqrt(3) / 2) * spacing of a coarse node... take
    # the max over the 2x2x2 coarse cell around it to be safe.
    idx = [np.minimum(np.arange(n) // coarse_step, len(ca) - 1) for n, ca in zip(shape, coarse_axes)]
    idx_hi = [np.minimum(i + 1, len(ca) - 1) for i, ca in zip(idx, coarse_axes)]
    lower_bound = np.full(shape, np.inf)
    for a in (idx, idx_hi):
        for b in (idx, idx_hi):
            for c in (idx, idx_hi):
                lower_bound = np.minimum(lower_bound, coarse_d[np.ix_(a[0], b[1], c[2])])
    reach = coarse_step * spacing * np.sqrt(3.0)
    lower_bound = lower_bound - reach  # true distance >= this
    band = offset + 2 * spacing
    need = lower_bound < band
    dist = np.maximum(lower_bound, band + spacing)  # positive, outside
    fine_pts = _nodes(axes, need)
    fine_d, _ = _distances(fine_pts, verts, faces)
    dist[need] = fine_d
    field = dist - offset

    # ---- topology of the inside region -----------------------------------------------------
    inside = field < 0
    if not inside.any():
        raise InputError("the link geometry is thinner than the grid; lower the resolution", element="wrapper")
    filled = ndimage.binary_fill_holes(inside)
    field[filled & ~inside] = -spacing
    inside = filled
    labels, n_labels = ndimage.label(inside)
    radius = 1
    max_radius = max(1, int(np.ceil(max_bridge / spacing)))
    while n_labels > 1 and radius <= max_radius:
        ball = _ball(radius)
        pad = radius + 1
        closed = ndimage.binary_closing(np.pad(inside, pad), structure=ball)[pad:-pad, pad:-pad, pad:-pad]
        closed = ndimage.binary_fill_holes(closed | inside)
        test_labels, test_n = ndimage.label(closed)
        if test_n == 1:
            added = closed & ~inside
            field[added] = np.minimum(field[added], -0.25 * spacing)
            inside = closed
            labels, n_labels = test_labels, test_n
            break
        radius += 1
    if n_labels > 1:
        sizes = ndimage.sum(inside, labels, index=np.arange(1, n_labels + 1))
        main = int(np.argmax(sizes)) + 1
        stray_pts = _nodes(axes, (labels != main) & inside)
        _, stray_face = _distances(stray_pts, verts, faces)
        stray = sorted({names.get(int(j), f"joint {int(j)}") for j in face_owner[stray_face]})
        raise InputError(
            f"link geometry stays in {n_labels} separate pieces even after bridging gaps up to "
            f"{max_bridge * 1000:.1f} mm; disconnected from the main piece: {', '.join(stray)}",
            element="wrapper",
        )

    wverts, wfaces = closed_surface_from_field(field, lower, spacing, what="robot wrapper surface")

    # ---- skin weights -------------------------------------------------------------------------
    joint_ids = np.unique(face_owner)
    per_link = np.empty((len(wverts), len(joint_ids)))
    for k, j in enumerate(joint_ids):
        sel = face_owner == j
        used = np.unique(faces[sel])
        remap = np.full(len(verts), -1, dtype=np.int64)
        remap[used] = np.arange(len(used))
        per_link[:, k], _ = _distances(wverts, verts[used], remap[faces[sel]])
    order = np.argsort(per_link, axis=1)
    first = order[:, 0]
    rows = np.arange(len(wverts))
    d1 = per_link[rows, first]
    indices = joint_ids[first][:, None]
    weights = np.ones((len(wverts), 1))
    if max_influences == 2 and len(joint_ids) > 1:
        candidate = per_link.copy()
        if parents is not None:
            parents_arr = np.asarray(parents, dtype=np.int64)
            jid = joint_ids
            # adjacency[a, b]: joints jid[a] and jid[b] are parent and child
            adjacency = (parents_arr[jid][:, None] == jid[None, :]) | (parents_arr[jid][None, :] == jid[:, None])
            candidate[~adjacency[first]] = np.inf
        candidate[rows, first] = np.inf
        second = np.argmin(candidate, axis=1)
        d2 = candidate[rows, second]
        gap = d2 - d1
        w2 = np.where(np.isfinite(gap) & (gap < blend_band), 0.5 * (1.0 - gap / blend_band), 0.0)
        indices = np.column_stack([joint_ids[first], joint_ids[second]])
        weights = np.column_stack([1.0 - w2, w2])
        weights /= weights.sum(axis=1, keepdims=True)
    return SkinnedMesh(wverts, wfaces, indices, weights)
