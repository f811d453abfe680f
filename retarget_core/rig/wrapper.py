"""A closed, connected, manifold "wrapper" surface around a robot hand's link geometry.

Robot link meshes are usually not watertight, overlap each other and hide internal parts,
so they cannot serve as the rig's surface directly. :func:`build_wrapper` samples the
unsigned distance to the union of all link meshes on a regular grid and extracts the level
set at ``level = max(offset, 0.9 * spacing)`` metres (a thin "shrink wrap"; the floor keeps
parts thinner than a grid cell from aliasing into disconnected voxel islands):

1. distance: libigl AABB squared distance against the concatenated link meshes (one tree);
   grid nodes far from any geometry (judged on a 4x coarser grid first) keep a lower bound
   instead of an exact distance, which does not change the level set;
2. inside mask = distance < level; enclosed cavities are filled (no inner shells);
3. if the inside region falls into several pieces (6-connectivity), gaps are bridged by a
   morphological closing with a growing ball (up to ``max_bridge`` metres), applied only near
   the smaller pieces so that fingers are not webbed together elsewhere; bridge voxels can lie
   farther from the geometry than ``level``. If pieces remain, an :class:`InputError` lists
   the links of every piece;
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

#: The level set never sits closer to the geometry than this many grid cells.
MIN_LEVEL_CELLS = 0.9

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


class _Tree:
    """Distance queries against one triangle mesh, AABB tree built once."""

    def __init__(self, verts, faces):
        self.verts, self.faces = verts, faces
        self.aabb = igl.AABB()
        self.aabb.init(verts, faces)

    def query(self, points):
        if len(points) == 0:
            return np.zeros(0), np.zeros(0, dtype=np.int64)
        d2, face, _ = self.aabb.squared_distance(self.verts, self.faces, np.ascontiguousarray(points, dtype=np.float64))
        return np.sqrt(np.maximum(d2, 0.0)), np.asarray(face, dtype=np.int64)


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
    automatically (no warning) when the grid would exceed ``MAX_GRID_NODES``. offset: distance
    of the wrapper from the geometry (m, > 0; at least 0.9 grid cells is used). Away from
    bridges every wrapper vertex lies within ``level + spacing`` of the geometry.
    max_influences: 1 (rigid) or 2 (blend band of width ``blend_band`` metres).
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
    margin = max(offset, MIN_LEVEL_CELLS * resolution) + 3 * resolution
    lower = verts.min(axis=0) - margin
    upper = verts.max(axis=0) + margin
    spacing = float(resolution)
    extent = upper - lower
    n_nodes = np.prod(np.ceil(extent / spacing) + 1)
    if n_nodes > MAX_GRID_NODES:
        spacing = float((np.prod(extent) / MAX_GRID_NODES) ** (1.0 / 3.0)) * 1.05
        margin = max(offset, MIN_LEVEL_CELLS * spacing) + 3 * spacing
        lower = verts.min(axis=0) - margin
        upper = verts.max(axis=0) + margin
    axes, shape = _grid_axes(lower, upper, spacing)
    # Thin parts (thinner than a cell) would alias into disconnected voxel islands if the
    # level sat closer to the geometry than about one cell: never go below 0.9 cells.
    level = max(float(offset), MIN_LEVEL_CELLS * spacing)

    # Coarse pass (4x spacing): only fine nodes within reach of the level set need an exact
    # distance; the rest keep a lower bound, which is all the level set needs.
    coarse_step = 4
    coarse_axes = [a[::coarse_step] for a in axes]
    coarse_pts = np.stack(np.meshgrid(*coarse_axes, indexing="ij"), axis=-1).reshape(-1, 3)
    tree = _Tree(verts, faces)
    coarse_d, _ = tree.query(coarse_pts)
    coarse_d = coarse_d.reshape([len(a) for a in coarse_axes])
    # Each fine node lies within 3 fine steps per axis of its nearest coarse node (2 inside
    # the grid, 3 in the last partial cell), so d(fine) >= d(coarse) - 3 sqrt(3) spacing.
    idx = [np.minimum((np.arange(n) + coarse_step // 2) // coarse_step, len(ca) - 1) for n, ca in zip(shape, coarse_axes)]
    lower_bound = coarse_d[np.ix_(idx[0], idx[1], idx[2])] - 3.0 * np.sqrt(3.0) * spacing
    band = level + 2 * spacing
    need = lower_bound < band
    dist = np.maximum(lower_bound, band + spacing)  # positive, outside
    fine_pts = _nodes(axes, need)
    fine_d, _ = tree.query(fine_pts)
    dist[need] = fine_d
    field = dist - level

    # ---- topology of the inside region -----------------------------------------------------
    inside = field < 0
    if not inside.any():
        raise InputError("the link geometry is thinner than the grid; lower the resolution", element="wrapper")
    filled = ndimage.binary_fill_holes(inside)
    field[filled & ~inside] = -spacing
    inside = filled
    labels, n_labels = ndimage.label(inside)
    bridged_radii: list[int] = []
    # Bridge the pieces to the largest one by a morphological closing restricted to the
    # neighbourhood of the smaller pieces (a global closing would web the fingers together).
    radius = 1
    max_radius = max(1, int(np.ceil(max_bridge / spacing)))
    while n_labels > 1 and radius <= max_radius:
        sizes = ndimage.sum(inside, labels, index=np.arange(1, n_labels + 1))
        main = int(np.argmax(sizes)) + 1
        ball = _ball(radius)
        pad = radius + 1
        closed = ndimage.binary_closing(np.pad(inside, pad), structure=ball)[pad:-pad, pad:-pad, pad:-pad]
        near_pieces = ndimage.binary_dilation((labels != main) & inside, structure=_ball(2 * radius + 1))
        closed = ndimage.binary_fill_holes(inside | (closed & near_pieces))
        labels_new, n_new = ndimage.label(closed)
        if n_new < n_labels:
            added = closed & ~inside
            field[added] = np.minimum(field[added], -0.25 * spacing)
            inside = closed
            labels, n_labels = labels_new, n_new
            bridged_radii.append(radius)
        else:
            radius += 1
    if n_labels > 1:
        sizes = ndimage.sum(inside, labels, index=np.arange(1, n_labels + 1))
        piece_order = np.argsort(-sizes) + 1
        mask = inside & (labels > 0)
        _, piece_face = tree.query(_nodes(axes, mask))
        piece_of_node = labels[mask]
        descriptions = []
        for rank, lab in enumerate(piece_order):
            owners = np.unique(face_owner[piece_face[piece_of_node == lab]])
            link_list = ", ".join(sorted(names.get(int(j), f"joint {int(j)}") for j in owners))
            descriptions.append(("largest piece: " if rank == 0 else "") + link_list)
        raise InputError(
            f"link geometry stays in {n_labels} separate pieces even after bridging gaps up to "
            f"{max_bridge * 1000:.1f} mm; pieces by link: " + " | ".join(descriptions),
            element="wrapper",
        )

    wverts, wfaces = closed_surface_from_field(field, lower, spacing, what="robot wrapper surface")

    # ---- skin weights -------------------------------------------------------------------------
    d1, nearest_face = tree.query(wverts)
    first_joint = face_owner[nearest_face]
    indices = first_joint[:, None]
    weights = np.ones((len(wverts), 1))
    joint_ids = np.unique(face_owner)
    if max_influences == 2 and len(joint_ids) > 1:
        # Distance of each vertex to every eligible second link (tree neighbours of its
        # nearest link when ``parents`` is given, else every other link).
        if parents is not None:
            parents_arr = np.asarray(parents, dtype=np.int64)

            def eligible(k):
                return (parents_arr[first_joint] == k) | (parents_arr[k] == first_joint)
        else:

            def eligible(k):
                return first_joint != k

        d2 = np.full(len(wverts), np.inf)
        second = first_joint.copy()
        for k in joint_ids:
            rows = np.nonzero(eligible(k))[0]
            if len(rows) == 0:
                continue
            sel = face_owner == k
            used = np.unique(faces[sel])
            remap = np.full(len(verts), -1, dtype=np.int64)
            remap[used] = np.arange(len(used))
            dk, _ = _distances(wverts[rows], verts[used], remap[faces[sel]])
            better = dk < d2[rows]
            d2[rows[better]] = dk[better]
            second[rows[better]] = k
        gap = d2 - d1
        w2 = np.where(np.isfinite(gap) & (gap < blend_band), 0.5 * (1.0 - np.maximum(gap, 0.0) / blend_band), 0.0)
        indices = np.column_stack([first_joint, second])
        weights = np.column_stack([1.0 - w2, w2])
        weights /= weights.sum(axis=1, keepdims=True)
    return SkinnedMesh(wverts, wfaces, indices, weights)
