"""Closed, manifold triangle surfaces from sampled implicit fields (marching cubes)."""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from skimage.measure import marching_cubes

from ..errors import InputError
from .geometry import signed_volume
from .topology import check_closed_manifold


def sample_grid(lower: np.ndarray, upper: np.ndarray, spacing: float):
    """Grid covering [lower, upper] (metres) with one empty cell of margin.

    Returns (points (N, 3), shape (nx, ny, nz), origin (3,))."""
    lower = np.asarray(lower, float) - 2 * spacing
    upper = np.asarray(upper, float) + 2 * spacing
    shape = tuple(int(np.ceil((u - l) / spacing)) + 1 for l, u in zip(lower, upper))
    axes = [lower[i] + spacing * np.arange(shape[i]) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return grid, shape, lower


def largest_component(vertices: np.ndarray, faces: np.ndarray):
    """Keep the connected component with the most faces; re-index vertices."""
    n = len(vertices)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    face_labels = labels[faces[:, 0]]
    keep_label = np.bincount(face_labels).argmax()
    faces = faces[face_labels == keep_label]
    used = np.unique(faces)
    remap = np.full(n, -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return vertices[used], remap[faces]


def closed_surface_from_field(field: np.ndarray, origin: np.ndarray, spacing: float, *, what: str = "surface"):
    """Extract the zero level set of ``field`` (nx, ny, nz; negative inside) as one closed,
    outward-oriented, manifold triangle mesh. Returns (vertices (V, 3) metres, faces (F, 3)).

    Smaller pieces (stray islands, inner cavity shells) are dropped; an InputError names
    ``what`` if the result is not a closed manifold."""
    # Exact zeros at grid nodes create coincident vertices; nudge them off the level.
    field = np.where(field == 0.0, 1e-12, field)
    padded = np.pad(field, 1, constant_values=max(float(field.max()), 1.0))
    verts, faces, _, _ = marching_cubes(padded, level=0.0, allow_degenerate=False)
    verts = (verts - 1.0) * spacing + np.asarray(origin, float)
    faces = faces.astype(np.int64)
    verts, faces = largest_component(verts, faces)
    if signed_volume(verts, faces) < 0:
        faces = faces[:, ::-1].copy()
    report = check_closed_manifold(faces, len(verts))
    if not (report.closed and report.manifold):
        raise InputError(f"level-set extraction did not give a closed manifold: {report.describe()}", element=what)
    return verts, faces
