"""Closed / manifold checks on meshes whose answers are known."""

import numpy as np
import pytest

from retarget_core.errors import InputError
from retarget_core.mesh import check_closed_manifold, require_closed_manifold

# An outward-oriented cube: 8 vertices, 12 triangles.
CUBE_FACES = np.array([
    [0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
    [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7],
])


def test_cube_is_closed_and_manifold():
    report = check_closed_manifold(CUBE_FACES)
    assert report.closed and report.manifold and report.components == 1
    assert report.describe() == "closed, manifold"


def test_missing_face_leaves_three_boundary_edges():
    report = check_closed_manifold(CUBE_FACES[1:], 8)
    assert not report.closed
    assert report.boundary_edges == 3
    assert "open" in report.describe()


def test_flipped_face_is_misoriented():
    faces = CUBE_FACES.copy()
    faces[0] = faces[0, ::-1]
    report = check_closed_manifold(faces)
    assert report.closed and not report.manifold
    assert report.misoriented_edges == 3


def test_edge_shared_by_three_faces_is_nonmanifold():
    faces = np.vstack([CUBE_FACES, [[0, 1, 8]]])
    report = check_closed_manifold(faces)
    assert report.nonmanifold_edges == 1


def test_two_cubes_touching_at_a_vertex_is_a_nonmanifold_vertex():
    second = CUBE_FACES + 7  # shares vertex 7 of the first cube as its vertex 0
    report = check_closed_manifold(np.vstack([CUBE_FACES, second]))
    assert report.closed
    assert report.nonmanifold_vertices == 1
    assert not report.manifold


def test_two_separate_cubes_are_two_components_and_rejected():
    faces = np.vstack([CUBE_FACES, CUBE_FACES + 8])
    report = check_closed_manifold(faces)
    assert report.closed and report.manifold and report.components == 2
    with pytest.raises(InputError, match="2 components"):
        require_closed_manifold(faces, source="two_cubes.obj")


def test_degenerate_face_is_reported():
    faces = np.vstack([CUBE_FACES, [[0, 0, 1]]])
    assert check_closed_manifold(faces).degenerate_faces == 1


def test_require_names_source_and_element():
    with pytest.raises(InputError) as err:
        require_closed_manifold(CUBE_FACES[2:], 8, source="hand.usda", element="Surface")
    assert "hand.usda" in str(err.value) and "Surface" in str(err.value) and "boundary" in str(err.value)
