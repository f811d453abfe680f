"""Triangle meshes from files (OBJ, PLY, STL, OFF, ... as trimesh reads them), as arrays."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError


def load_mesh_file(path, what: str = "the", element: str = "mesh") -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64, faces (F, 3) int64) of the mesh file at ``path``, read as
    written (no merging or reordering). :class:`InputError` naming ``what`` mesh and
    ``element`` when it cannot be read or holds no usable vertices."""
    import trimesh

    path = Path(path)
    try:
        mesh = trimesh.load(str(path), process=False, force="mesh")
    except Exception as err:  # trimesh raises many kinds for unreadable files
        raise InputError(f"cannot read {what} mesh ({type(err).__name__}: {err})", source=str(path),
                         element=element) from None
    vertices = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), dtype=np.float64)
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), dtype=np.int64)
    if vertices.ndim != 2 or len(vertices) == 0 or not np.all(np.isfinite(vertices)):
        raise InputError(f"{what} mesh has no usable vertices", source=str(path), element=element)
    return vertices, faces
