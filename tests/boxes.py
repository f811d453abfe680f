"""Closed box meshes for the tests (trimesh boxes, subdivided into regular grids)."""

import numpy as np
import trimesh


def box_mesh(extents, center=(0.0, 0.0, 0.0), subdivisions=5):
    """(vertices (V, 3), faces (F, 3)) of a closed box of ``extents`` (3,) m centred on
    ``center``, split ``subdivisions`` times: a regular grid on each face with spacing
    extent / 2**subdivisions."""
    mesh = trimesh.creation.box(extents=extents)
    for _ in range(subdivisions):
        mesh = mesh.subdivide()
    return np.asarray(mesh.vertices) + np.asarray(center), np.asarray(mesh.faces)
